//! [`super::TrainOps`] kernels for Flex (Burn's CPU backend) on contiguous f32 `[N, C, H, W]` data.
//!
//! Convolutions (stride 1, dilation 1, one group, symmetric zero padding: every convolution of the network) are
//! per-sample im2col + `gemm`, parallel over the batch, in blocks of output rows whose im2col matrix fits in a
//! core's cache: forward `Y = W·col(X) + b`, input gradient the same convolution of ∂Y with the kernel turned
//! by 180° and its channel axes swapped, weight gradient `∂W = Σₙ ∂Yₙ·col(Xₙ)ᵀ`. BatchNorm + LeakyReLU is one
//! pass for the statistics (per channel, f64 sums of x and x²) and one for the output, and the same two for the
//! backward. Elementwise loops run in [`vectorized`]. Anything else (other dtypes, strides, groups) goes to the
//! stock path in [`super::reference`].

use burn::backend::Flex;
use burn::tensor::ops::{ConvOptions, FloatTensor, IntTensor, ModuleOps};
use burn::tensor::{DType, TensorData, TensorMetadata};
use burn_flex::FlexTensor;
use rayon::prelude::*;

use super::{reference, MaxPoolOutput, NormGrads, NormOutput};

/// A contiguous f32 view of a tensor, or `None` when the kernels do not apply (another dtype).
fn f32_data(t: &FlexTensor) -> Option<(FlexTensor, Vec<usize>)> {
    if t.dtype() != DType::F32 {
        return None;
    }
    let t = if t.is_contiguous() {
        t.clone()
    } else {
        t.to_contiguous()
    };
    let shape = t.shape().to_vec();
    Some((t, shape))
}

fn slice(t: &FlexTensor) -> &[f32] {
    t.as_slice::<f32>().expect("contiguous f32 tensor")
}

fn from_vec(values: Vec<f32>, shape: &[usize]) -> FlexTensor {
    FlexTensor::from_data(TensorData::new(values, shape.to_vec()))
}

std::thread_local! {
    /// Per-thread working memory for im2col matrices and transposes, reused across calls: a fresh, zeroed
    /// allocation per sample (tens of MB at width 16) cost more in memset and page faults than im2col itself.
    static SCRATCH: std::cell::RefCell<[Vec<f32>; 2]> = const { std::cell::RefCell::new([Vec::new(), Vec::new()]) };
}

/// Run `f` with two scratch slices of `lens` elements (contents unspecified: callers overwrite what they read).
fn with_scratch<R>(lens: [usize; 2], f: impl FnOnce(&mut [f32], &mut [f32]) -> R) -> R {
    SCRATCH.with(|cell| {
        let mut buffers = cell.borrow_mut();
        for (buffer, &len) in buffers.iter_mut().zip(&lens) {
            if buffer.len() < len {
                buffer.resize(len, 0.0);
            }
        }
        let [a, b] = &mut *buffers;
        f(&mut a[..lens[0]], &mut b[..lens[1]])
    })
}

/// The convolution geometry the kernels support, or `None`.
#[derive(Clone, Copy, Debug)]
struct ConvShape {
    batch: usize,
    c_in: usize,
    c_out: usize,
    height: usize,
    width: usize,
    kernel: [usize; 2],
    padding: [usize; 2],
}

impl ConvShape {
    fn new(x: &[usize], weight: &[usize], options: &ConvOptions<2>) -> Option<Self> {
        let supported = options.stride == [1, 1]
            && options.dilation == [1, 1]
            && options.groups == 1
            && x.len() == 4
            && weight.len() == 4
            && weight[1] == x[1]
            && (0..2).all(|d| 2 * options.padding[d] + 1 == weight[2 + d]);
        supported.then(|| Self {
            batch: x[0],
            c_in: x[1],
            c_out: weight[0],
            height: x[2],
            width: x[3],
            kernel: [weight[2], weight[3]],
            padding: options.padding,
        })
    }

    /// Output positions per sample ("same" padding: the input's).
    fn positions(&self) -> usize {
        self.height * self.width
    }

    /// Elements of one sample's input and of its output.
    fn planes(&self) -> (usize, usize) {
        (self.c_in * self.positions(), self.c_out * self.positions())
    }

    fn input_shape(&self) -> [usize; 4] {
        [self.batch, self.c_in, self.height, self.width]
    }

    /// Rows of the im2col matrix: input channels × kernel taps.
    fn taps(&self) -> usize {
        self.c_in * self.kernel[0] * self.kernel[1]
    }

    /// For output column `ox` reading tap `kx`: the range of `ox` whose input column is inside the image.
    fn valid_columns(&self, kx: usize) -> std::ops::Range<usize> {
        let (w, pad) = (self.width, self.padding[1]);
        let lo = pad.saturating_sub(kx);
        let hi = (w + pad).saturating_sub(kx).min(w);
        lo..hi.max(lo)
    }

    /// A 1×1 convolution without padding: its im2col matrix is the input itself.
    fn is_pointwise(&self) -> bool {
        self.kernel == [1, 1] && self.padding == [0, 0]
    }

    /// `col[(c, ky, kx)][(j, ox)] = x[c][oy + ky − pad][ox + kx − pad]` (0 outside) for the `j`-th output row
    /// `oy` of `rows`, one sample: `col` is `taps × (rows.len() · width)`.
    ///
    /// A tap's row of `col`, over the output rows whose input row is inside the image, is one contiguous run of
    /// the input plane shifted by `kx − pad` (row-major planes continue into the next row), so it is one copy;
    /// only the few columns that wrapped into a neighbouring row are then zeroed. Copying row by row made
    /// one small `memcpy` per output row and tap (64 B at the coarsest level) and cost more than the copy itself.
    fn im2col_rows(&self, x: &[f32], rows: std::ops::Range<usize>, col: &mut [f32]) {
        let (h, w, hw) = (self.height, self.width, self.positions());
        let [kh, kw] = self.kernel;
        let [pad_y, pad_x] = self.padding;
        let n = rows.len() * w;
        for c in 0..self.c_in {
            let plane = &x[c * hw..(c + 1) * hw];
            for ky in 0..kh {
                // Output rows `oy` of this block whose input row `oy + ky − pad_y` lies in 0..h.
                let first = rows.start.max(pad_y.saturating_sub(ky));
                let last = rows.end.min((h + pad_y).saturating_sub(ky)).max(first);
                let (j0, j1) = (first - rows.start, last - rows.start);
                for kx in 0..kw {
                    let row = &mut col[((c * kh + ky) * kw + kx) * n..][..n];
                    row[..j0 * w].fill(0.0);
                    row[j1 * w..].fill(0.0);
                    if j0 == j1 {
                        continue;
                    }
                    let dst = &mut row[j0 * w..j1 * w];
                    // dst[i] = plane[start + i], with `start` possibly −pad_x (the image's first element, shifted
                    // left) or running pad_x past the end; those elements are zero padding.
                    let start = ((first + ky - pad_y) * w + kx) as isize - pad_x as isize;
                    let lo = (-start).clamp(0, dst.len() as isize) as usize;
                    let hi = (hw as isize - start).clamp(lo as isize, dst.len() as isize) as usize;
                    dst[..lo].fill(0.0);
                    dst[hi..].fill(0.0);
                    dst[lo..hi]
                        .copy_from_slice(&plane[(start + lo as isize) as usize..][..hi - lo]);
                    let cols = self.valid_columns(kx);
                    if cols.len() < w {
                        for line in dst.chunks_exact_mut(w) {
                            let (left, rest) = line.split_at_mut(cols.start);
                            let right = &mut rest[cols.len()..];
                            left.iter_mut().chain(right).for_each(|v| *v = 0.0);
                        }
                    }
                }
            }
        }
    }

    /// Output rows per im2col block: enough that one block's columns (`taps × rows × width` floats) stay near
    /// [`BLOCK_FLOATS`], so the matrix im2col writes is still in the core's cache when gemm packs it (a whole
    /// sample's matrix is tens of MB at the finest level and made the convolutions memory-bound). A pointwise
    /// convolution reads its input in place: one block.
    fn block_rows(&self) -> usize {
        if self.is_pointwise() {
            self.height
        } else {
            (BLOCK_FLOATS / (self.taps() * self.width).max(1)).clamp(1, self.height.max(1))
        }
    }

    /// Scratch elements one block of [`Self::block_columns`] needs.
    fn block_len(&self) -> usize {
        if self.is_pointwise() {
            0
        } else {
            self.taps() * self.block_rows() * self.width
        }
    }

    /// The output-row blocks of one sample, in order.
    fn row_blocks(&self) -> impl Iterator<Item = std::ops::Range<usize>> {
        let (h, step) = (self.height, self.block_rows());
        (0..h)
            .step_by(step.max(1))
            .map(move |r| r..(r + step).min(h))
    }

    /// The im2col matrix of output rows `rows` (`taps × positions`): the input itself for a pointwise
    /// convolution (whose single block is the whole plane), else built in `buffer`.
    fn block_columns<'a>(
        &self,
        x: &'a [f32],
        rows: std::ops::Range<usize>,
        buffer: &'a mut [f32],
    ) -> &'a [f32] {
        if self.is_pointwise() {
            x
        } else {
            let len = self.taps() * rows.len() * self.width;
            self.im2col_rows(x, rows, &mut buffer[..len]);
            &buffer[..len]
        }
    }
}

/// Target size of one im2col block, in floats (1 MiB): about a core's L2 on the machines measured.
const BLOCK_FLOATS: usize = 1 << 18;

/// Contiguous f32 input and weight of a convolution the kernels support (with a third operand of the same
/// dtype when given: the bias or the output gradient), or `None`: the caller then takes the stock path.
fn conv_operands(
    x: &FlexTensor,
    weight: &FlexTensor,
    third: Option<&FlexTensor>,
    options: &ConvOptions<2>,
) -> Option<(FlexTensor, FlexTensor, Option<FlexTensor>, ConvShape)> {
    let (xc, x_shape) = f32_data(x)?;
    let (wc, w_shape) = f32_data(weight)?;
    let third = match third {
        Some(t) => Some(f32_data(t)?.0),
        None => None,
    };
    let shape = ConvShape::new(&x_shape, &w_shape, options)?;
    Some((xc, wc, third, shape))
}

/// `dst (m × n) = [dst +] lhs (m × k) · rhs (k × n)`, each matrix given as (row stride, column stride).
#[allow(clippy::too_many_arguments)]
fn matmul(
    [m, n, k]: [usize; 3],
    dst: &mut [f32],
    dst_strides: [usize; 2],
    accumulate: bool,
    lhs: &[f32],
    lhs_strides: [usize; 2],
    rhs: &[f32],
    rhs_strides: [usize; 2],
) {
    let last = |[rs, cs]: [usize; 2], rows: usize, cols: usize| {
        (rows.max(1) - 1) * rs + (cols.max(1) - 1) * cs
    };
    assert!(
        last(dst_strides, m, n) < dst.len().max(1)
            && last(lhs_strides, m, k) < lhs.len().max(1)
            && last(rhs_strides, k, n) < rhs.len().max(1),
        "matmul operands out of bounds"
    );
    // SAFETY: the assertion above keeps every element gemm touches inside the three slices, and `dst` is
    // borrowed mutably, so it aliases neither operand.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr(),
            dst_strides[1] as isize,
            dst_strides[0] as isize,
            accumulate,
            lhs.as_ptr(),
            lhs_strides[1] as isize,
            lhs_strides[0] as isize,
            rhs.as_ptr(),
            rhs_strides[1] as isize,
            rhs_strides[0] as isize,
            1.0,
            1.0,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
}

pub fn conv2d(
    x: FloatTensor<Flex>,
    weight: FloatTensor<Flex>,
    bias: Option<FloatTensor<Flex>>,
    options: ConvOptions<2>,
) -> FloatTensor<Flex> {
    let Some((xc, wc, bias_c, s)) = conv_operands(&x, &weight, bias.as_ref(), &options) else {
        return <Flex as ModuleOps<Flex>>::conv2d(x, weight, bias, options);
    };
    let y = convolve(&s, slice(&xc), slice(&wc), bias_c.as_ref().map(slice));
    from_vec(y, &[s.batch, s.c_out, s.height, s.width])
}

/// `Y = W·col(X) (+ b)` for every sample of contiguous `xs` with weights `w` (`c_out × taps`).
fn convolve(s: &ConvShape, xs: &[f32], w: &[f32], bias: Option<&[f32]>) -> Vec<f32> {
    let (plane_in, plane_out) = s.planes();
    let mut y = vec![0.0f32; s.batch * plane_out];
    y.par_chunks_mut(plane_out)
        .zip(xs.par_chunks(plane_in))
        .for_each(|(y, x)| {
            if let Some(bias) = bias {
                y.chunks_mut(s.positions())
                    .zip(bias)
                    .for_each(|(plane, &b)| plane.fill(b));
            }
            with_scratch([s.block_len(), 0], |buffer, _| {
                convolve_sample(s, x, w, y, bias.is_some(), buffer);
            });
        });
    y
}

/// One sample's `y (c_out × hw) [+]= W·col(x)`, block by block, with `buffer` ([`ConvShape::block_len`]) for the
/// columns.
fn convolve_sample(
    s: &ConvShape,
    x: &[f32],
    w: &[f32],
    y: &mut [f32],
    accumulate: bool,
    buffer: &mut [f32],
) {
    let (hw, taps) = (s.positions(), s.taps());
    for rows in s.row_blocks() {
        let (start, n) = (rows.start * s.width, rows.len() * s.width);
        // A pointwise convolution's single block is the whole plane, with row stride `hw`.
        let col_stride = if s.is_pointwise() { hw } else { n };
        // Y[:, block] (c_out × n) [+]= W (c_out × taps) · col (taps × n)
        matmul(
            [s.c_out, n, taps],
            &mut y[start..],
            [hw, 1],
            accumulate,
            w,
            [taps, 1],
            s.block_columns(x, rows, buffer),
            [col_stride, 1],
        );
    }
}

/// `W′[c][o][ky][kx] = W[o][c][kh−1−ky][kw−1−kx]` of a `c_out × c_in × kh × kw` kernel: the kernel of the
/// convolution that is the adjoint of `W`'s (∂Y → ∂X).
fn turned_kernel(w: &[f32], c_out: usize, c_in: usize, [kh, kw]: [usize; 2]) -> Vec<f32> {
    let mut turned = vec![0.0f32; w.len()];
    for o in 0..c_out {
        for c in 0..c_in {
            for ky in 0..kh {
                for kx in 0..kw {
                    turned[((c * c_out + o) * kh + ky) * kw + kx] =
                        w[((o * c_in + c) * kh + kh - 1 - ky) * kw + kw - 1 - kx];
                }
            }
        }
    }
    turned
}

/// ∂X of a stride-1 "same" convolution is itself one: ∂Y convolved with the kernel turned by 180° and its
/// channel axes swapped (`W′[c][o][ky][kx] = W[o][c][kh−1−ky][kw−1−kx]`, the same padding). Computed that way
/// it writes ∂X once per element; as `col⁻¹(Wᵀ·∂Y)` it scatter-added nine shifted copies per element.
pub fn conv2d_x_grad(
    x: FloatTensor<Flex>,
    weight: FloatTensor<Flex>,
    output_grad: FloatTensor<Flex>,
    options: ConvOptions<2>,
) -> FloatTensor<Flex> {
    let Some((_, wc, Some(dy_c), s)) = conv_operands(&x, &weight, Some(&output_grad), &options)
    else {
        return <Flex as ModuleOps<Flex>>::conv2d_x_backward(x, weight, output_grad, options);
    };
    let turned = turned_kernel(slice(&wc), s.c_out, s.c_in, s.kernel);
    let adjoint = ConvShape {
        c_in: s.c_out,
        c_out: s.c_in,
        ..s
    };
    let dx = convolve(&adjoint, slice(&dy_c), &turned, None);
    from_vec(dx, &s.input_shape())
}

pub fn conv2d_weight_grad(
    x: FloatTensor<Flex>,
    weight: FloatTensor<Flex>,
    output_grad: FloatTensor<Flex>,
    options: ConvOptions<2>,
) -> FloatTensor<Flex> {
    let Some((xc, _, Some(dy_c), s)) = conv_operands(&x, &weight, Some(&output_grad), &options)
    else {
        return <Flex as ModuleOps<Flex>>::conv2d_weight_backward(x, weight, output_grad, options);
    };
    let (xs, dy) = (slice(&xc), slice(&dy_c));
    let taps = s.taps();
    let (plane_in, plane_out) = s.planes();
    // One partial per sample, summed in sample order: the result does not depend on how rayon split the work
    // (a fold/reduce would sum in an order set by work stealing, and training must be reproducible bit for bit).
    let mut partials = vec![0.0f32; s.batch * taps * s.c_out];
    partials
        .par_chunks_mut(taps * s.c_out)
        .zip(xs.par_chunks(plane_in).zip(dy.par_chunks(plane_out)))
        .for_each(|(dw_t, (x, dy))| {
            with_scratch(
                [s.block_len(), s.block_rows() * s.width * s.c_out],
                |col, dy_t| weight_grad_sample(&s, x, dy, dw_t, col, dy_t),
            );
        });
    let dw_t = sum_in_order(&partials, taps * s.c_out);
    let mut dw = vec![0.0f32; s.c_out * taps];
    transpose(&dw_t, taps, s.c_out, &mut dw);
    from_vec(dw, &[s.c_out, s.c_in, s.kernel[0], s.kernel[1]])
}

/// One sample's weight gradient of the convolution `s`, stored as ∂Wᵀ (`taps × c_out`, c_out contiguous):
/// `∂W (c_out × taps) = Σ_blocks ∂Y[:, block] · col(x)[:, block]ᵀ`, `dy` the sample's `c_out × hw` output
/// gradient. Each block of ∂Y is transposed to position-major first (into `dy_t`, `block_rows · width · c_out`),
/// so that every gemm operand has its rows contiguous: the long reduction over positions then packs at memory
/// speed (with ∂Y·colᵀ on row-major data, packing the transposed operand cost more than the arithmetic). Blocks
/// of output rows keep each block's columns (in `col`, [`ConvShape::block_len`]) and ∂Y in cache.
fn weight_grad_sample(
    s: &ConvShape,
    x: &[f32],
    dy: &[f32],
    dw_t: &mut [f32],
    col: &mut [f32],
    dy_t: &mut [f32],
) {
    let (hw, taps) = (s.positions(), s.taps());
    for (b, rows) in s.row_blocks().enumerate() {
        let (start, n) = (rows.start * s.width, rows.len() * s.width);
        let dy_t = &mut dy_t[..n * s.c_out];
        transpose_strided(&dy[start..], s.c_out, n, hw, dy_t);
        // A pointwise convolution's single block is the whole plane, with row stride `hw`.
        let col_stride = if s.is_pointwise() { hw } else { n };
        // ∂W (c_out × taps) [+]= ∂Y[:, block] (c_out × n) · colᵀ (n × taps), stored column-major
        matmul(
            [s.c_out, taps, n],
            dw_t,
            [1, s.c_out],
            b > 0,
            dy_t,
            [1, s.c_out],
            s.block_columns(x, rows, col),
            [1, col_stride],
        );
    }
}

/// The sum of consecutive `len`-element partials (one per sample), added in order: the same bits however the
/// partials were computed in parallel.
fn sum_in_order(partials: &[f32], len: usize) -> Vec<f32> {
    let mut chunks = partials.chunks_exact(len);
    let mut total = chunks.next().expect("a batch of at least one").to_vec();
    for partial in chunks {
        total.iter_mut().zip(partial).for_each(|(a, b)| *a += b);
    }
    total
}

/// `dst (cols × rows) = srcᵀ` for a row-major `src (rows × cols)`, in cache-sized tiles.
fn transpose(src: &[f32], rows: usize, cols: usize, dst: &mut [f32]) {
    transpose_strided(src, rows, cols, cols, dst);
}

/// [`transpose`] of a `rows × cols` matrix whose rows start `src_stride` elements apart.
fn transpose_strided(src: &[f32], rows: usize, cols: usize, src_stride: usize, dst: &mut [f32]) {
    const TILE: usize = 32;
    for r0 in (0..rows).step_by(TILE) {
        for c0 in (0..cols).step_by(TILE) {
            for r in r0..(r0 + TILE).min(rows) {
                for c in c0..(c0 + TILE).min(cols) {
                    dst[c * rows + r] = src[r * src_stride + c];
                }
            }
        }
    }
}

/// Per-channel sums of `[N, C, ...]` as `[C]` (f64 accumulation).
pub fn channel_sums(t: FloatTensor<Flex>) -> FloatTensor<Flex> {
    let Some((tc, shape)) = f32_data(&t) else {
        return reference::channel_sums::<Flex>(t);
    };
    let (c, plane) = (shape[1], shape[2..].iter().product::<usize>());
    let values = slice(&tc);
    let sums: Vec<f32> = (0..c)
        .into_par_iter()
        .map(|k| {
            values
                .chunks(plane)
                .skip(k)
                .step_by(c)
                .map(|p| lane_sums(p, p, |v, _| (v as f64, 0.0)).0)
                .sum::<f64>() as f32
        })
        .collect();
    from_vec(sums, &[c])
}

/// `f()` compiled for the widest SIMD instruction set this CPU has (AVX-512, else AVX2 + FMA, else the
/// baseline), chosen at run time. Release builds target baseline x86-64, where the elementwise loops below got
/// SSE2 code or none at all (`docs/performance.md`). Every variant does the same arithmetic in the same order
/// (Rust never contracts `a·b + c` into a fused multiply-add, and sums run in fixed lanes), so results are
/// bitwise identical whichever runs. Callers mark their closure `#[inline(always)]`: only a closure inlined into
/// the dispatching function is compiled for its instruction set.
#[inline(always)]
fn vectorized<R>(f: impl FnOnce() -> R) -> R {
    pulp::Arch::new().dispatch(f)
}

/// LeakyReLU with `slope` as Burn computes it (`slope·z` where `z < 0`): the one f32 form the kernels here use.
#[inline(always)]
fn leaky_relu(z: f32, slope: f32) -> f32 {
    if z < 0.0 {
        slope * z
    } else {
        z
    }
}

/// The gradient `g` through [`leaky_relu`] at pre-activation `z`: `g·slope` where `z < 0`, else `g`.
#[inline(always)]
fn leaky_relu_grad(z: f32, g: f32, slope: f32) -> f32 {
    if z < 0.0 {
        g * slope
    } else {
        g
    }
}

/// Sums of `f` over the elements of `a` (and `b`, same length), two f64 totals, in 8 independent lanes: one
/// serial f64 chain is bound by the add latency (4 cycles an element), lanes let the compiler vectorise.
#[inline(always)]
fn lane_sums(a: &[f32], b: &[f32], f: impl Fn(f32, f32) -> (f64, f64)) -> (f64, f64) {
    vectorized(
        #[inline(always)]
        || lane_sums_scalar(a, b, f),
    )
}

#[inline(always)]
fn lane_sums_scalar(a: &[f32], b: &[f32], f: impl Fn(f32, f32) -> (f64, f64)) -> (f64, f64) {
    const LANES: usize = 8;
    // Blocks of `BLOCK` elements are mapped through `f` into two f64 arrays first and only then added into the
    // lanes: with the map and the sums in one loop the compiler produced scalar conversions (measured 2× slower
    // per element). Element `i` goes to lane `i % LANES` in order either way, so the sums are the same bits.
    const BLOCK: usize = 64;
    let (mut s0, mut s1) = ([0.0f64; LANES], [0.0f64; LANES]);
    let split = a.len().min(b.len()) / BLOCK * BLOCK;
    let (mut u, mut v) = ([0.0f64; BLOCK], [0.0f64; BLOCK]);
    for (xa, xb) in a[..split]
        .chunks_exact(BLOCK)
        .zip(b[..split].chunks_exact(BLOCK))
    {
        for i in 0..BLOCK {
            (u[i], v[i]) = f(xa[i], xb[i]);
        }
        for (lanes_u, lanes_v) in u.chunks_exact(LANES).zip(v.chunks_exact(LANES)) {
            for l in 0..LANES {
                s0[l] += lanes_u[l];
                s1[l] += lanes_v[l];
            }
        }
    }
    let (ca, cb) = (
        a[split..].chunks_exact(LANES),
        b[split..].chunks_exact(LANES),
    );
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (xa, xb) in ca.zip(cb) {
        for l in 0..LANES {
            let (u, v) = f(xa[l], xb[l]);
            s0[l] += u;
            s1[l] += v;
        }
    }
    let (mut t0, mut t1) = (s0.iter().sum::<f64>(), s1.iter().sum::<f64>());
    for (&x, &y) in ra.iter().zip(rb) {
        let (u, v) = f(x, y);
        t0 += u;
        t1 += v;
    }
    (t0, t1)
}

/// Per-channel mean and biased variance of contiguous `[N, C, plane]` data: one pass of f64 sums of x and x²
/// (f32 data: the cancellation in E[x²] − μ² costs ~1e-16·(1 + μ²/σ²) relative, far below f32 resolution).
fn channel_stats(values: &[f32], c: usize, plane: usize) -> Vec<(f64, f64)> {
    let count = (values.len() / c) as f64;
    (0..c)
        .into_par_iter()
        .map(|k| {
            let (sum, sum_sq) = values
                .chunks(plane)
                .skip(k)
                .step_by(c)
                .map(|p| {
                    lane_sums(p, p, |x, _| {
                        let x = x as f64;
                        (x, x * x)
                    })
                })
                .fold((0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1));
            let mean = sum / count;
            (mean, (sum_sq / count - mean * mean).max(0.0))
        })
        .collect()
}

/// Per channel `(scale, shift)` with `BN(x) = scale·x + shift`: `scale = γ/√(var + ε)`, `shift = β − μ·scale`,
/// from the statistics as stored (f32), so that the backward pass recomputes the forward's pre-activation bit
/// for bit.
fn norm_affine(
    gamma: &[f32],
    beta: &[f32],
    mean: &[f32],
    var: &[f32],
    epsilon: f64,
) -> Vec<(f32, f32)> {
    (0..gamma.len())
        .map(|k| {
            let scale = gamma[k] as f64 / (var[k] as f64 + epsilon).sqrt();
            (
                scale as f32,
                (beta[k] as f64 - mean[k] as f64 * scale) as f32,
            )
        })
        .collect()
}

pub fn batch_norm_leaky_relu(
    x: FloatTensor<Flex>,
    gamma: FloatTensor<Flex>,
    beta: FloatTensor<Flex>,
    epsilon: f64,
    slope: f64,
) -> NormOutput<Flex> {
    let prepared = (f32_data(&x), f32_data(&gamma), f32_data(&beta));
    let (Some((xc, shape)), Some((gamma_c, _)), Some((beta_c, _))) = prepared else {
        return reference::batch_norm_leaky_relu::<Flex>(x, gamma, beta, epsilon, slope);
    };
    let (c, plane) = (shape[1], shape[2..].iter().product::<usize>());
    let values = slice(&xc);
    let stats = channel_stats(values, c, plane);
    let mean: Vec<f32> = stats.iter().map(|s| s.0 as f32).collect();
    let var: Vec<f32> = stats.iter().map(|s| s.1 as f32).collect();
    let affine = norm_affine(slice(&gamma_c), slice(&beta_c), &mean, &var, epsilon);
    let slope = slope as f32;
    let mut out = vec![0.0f32; values.len()];
    out.par_chunks_mut(plane)
        .zip(values.par_chunks(plane))
        .enumerate()
        .for_each(|(p, (y, x))| {
            let (scale, shift) = affine[p % c];
            vectorized(
                #[inline(always)]
                || {
                    y.iter_mut()
                        .zip(x)
                        .for_each(|(y, &x)| *y = leaky_relu(scale * x + shift, slope))
                },
            );
        });
    NormOutput {
        output: from_vec(out, &shape),
        mean: from_vec(mean, &[c]),
        var: from_vec(var, &[c]),
    }
}

/// The backward pass of [`batch_norm_leaky_relu`]. The LeakyReLU's slope applies where the pre-activation
/// `z = scale·x + shift` is negative, recomputed from `x` with the forward's own f32 arithmetic: each pass then
/// reads `x` and `∂Y` only (the forward's output is not read; it is one memory stream fewer per pass).
#[allow(clippy::too_many_arguments)]
pub fn batch_norm_leaky_relu_backward(
    x: FloatTensor<Flex>,
    gamma: FloatTensor<Flex>,
    beta: FloatTensor<Flex>,
    mean: FloatTensor<Flex>,
    var: FloatTensor<Flex>,
    output: FloatTensor<Flex>,
    output_grad: FloatTensor<Flex>,
    epsilon: f64,
    slope: f64,
) -> NormGrads<Flex> {
    let prepared = [&x, &gamma, &beta, &mean, &var, &output_grad].map(f32_data);
    let [Some((xc, shape)), Some((gamma_c, _)), Some((beta_c, _)), Some((mean_c, _)), Some((var_c, _)), Some((dy_c, _))] =
        prepared
    else {
        return reference::batch_norm_leaky_relu_backward::<Flex>(
            x,
            gamma,
            mean,
            var,
            output,
            output_grad,
            epsilon,
            slope,
        );
    };
    let (c, plane) = (shape[1], shape[2..].iter().product::<usize>());
    let (xs, dys) = (slice(&xc), slice(&dy_c));
    let (gamma, mean, var) = (slice(&gamma_c), slice(&mean_c), slice(&var_c));
    let affine = norm_affine(gamma, slice(&beta_c), mean, var, epsilon);
    let inv_std: Vec<f64> = var
        .iter()
        .map(|&v| 1.0 / (v as f64 + epsilon).sqrt())
        .collect();
    let slope = slope as f32;
    // g = ∂L/∂z.
    let dz = move |(scale, shift): (f32, f32), x: f32, dy: f32| {
        leaky_relu_grad(scale * x + shift, dy, slope)
    };
    // Σg and Σg·(x − μ) per channel (× σ⁻¹ below gives Σg·x̂).
    let sums: Vec<(f64, f64)> = (0..c)
        .into_par_iter()
        .map(|k| {
            let (m, ab) = (mean[k], affine[k]);
            let (d_beta, d_gamma) = (k..xs.len() / plane)
                .step_by(c)
                .map(|p| {
                    let r = p * plane..(p + 1) * plane;
                    lane_sums(&xs[r.clone()], &dys[r], |x, dy| {
                        let g = dz(ab, x, dy) as f64;
                        (g, g * (x - m) as f64)
                    })
                })
                .fold((0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1));
            (d_beta, d_gamma * inv_std[k])
        })
        .collect();
    let count = (xs.len() / c) as f64;
    let mut dx = vec![0.0f32; xs.len()];
    dx.par_chunks_mut(plane).enumerate().for_each(|(p, dx)| {
        let k = p % c;
        let r = p * plane..(p + 1) * plane;
        let (d_beta, d_gamma) = sums[k];
        let s = inv_std[k];
        // ∂x = γσ⁻¹ (g − mean(g) − x̂·mean(g·x̂))
        let a = (gamma[k] as f64 * s) as f32;
        let b = (d_beta / count) as f32;
        let e = (d_gamma / count * s) as f32;
        let (m, ab) = (mean[k], affine[k]);
        vectorized(
            #[inline(always)]
            || {
                for (dx, (&x, &dy)) in dx.iter_mut().zip(xs[r.clone()].iter().zip(&dys[r])) {
                    *dx = a * (dz(ab, x, dy) - b - (x - m) * e);
                }
            },
        );
    });
    NormGrads {
        x: from_vec(dx, &shape),
        gamma: from_vec(sums.iter().map(|s| s.1 as f32).collect(), &[c]),
        beta: from_vec(sums.iter().map(|s| s.0 as f32).collect(), &[c]),
    }
}

/// 2 × 2 stride-2 max-pool of even-sized f32 planes; `argmax` holds, per output, the window position (0–3, row
/// major) of the first maximum, as Burn's pooling picks it. Other inputs take the stock path.
pub fn max_pool2x2(x: FloatTensor<Flex>) -> MaxPoolOutput<Flex> {
    let stock = |x| {
        let out = <Flex as ModuleOps<Flex>>::max_pool2d_with_indices(
            x,
            [2, 2],
            [2, 2],
            [0, 0],
            [1, 1],
            false,
        );
        MaxPoolOutput {
            output: out.output,
            argmax: out.indices,
        }
    };
    let Some((xc, shape)) = f32_data(&x) else {
        return stock(x);
    };
    let (h, w) = (shape[2], shape[3]);
    if h % 2 != 0 || w % 2 != 0 {
        return stock(x);
    }
    let (oh, ow) = (h / 2, w / 2);
    let planes = shape[0] * shape[1];
    let values = slice(&xc);
    let mut out = vec![0.0f32; planes * oh * ow];
    let mut argmax = vec![0u8; planes * oh * ow];
    out.par_chunks_mut(oh * ow)
        .zip(argmax.par_chunks_mut(oh * ow))
        .zip(values.par_chunks(h * w))
        .for_each(|((out, argmax), x)| {
            for i in 0..oh {
                let (top, bottom) = (&x[2 * i * w..][..w], &x[(2 * i + 1) * w..][..w]);
                for j in 0..ow {
                    let window = [top[2 * j], top[2 * j + 1], bottom[2 * j], bottom[2 * j + 1]];
                    let (mut best, mut at) = (window[0], 0u8);
                    for (k, &v) in window.iter().enumerate().skip(1) {
                        if v > best {
                            (best, at) = (v, k as u8);
                        }
                    }
                    out[i * ow + j] = best;
                    argmax[i * ow + j] = at;
                }
            }
        });
    let out_shape = [shape[0], shape[1], oh, ow];
    MaxPoolOutput {
        output: from_vec(out, &out_shape),
        argmax: FlexTensor::from_data(TensorData::new(argmax, out_shape.to_vec())),
    }
}

/// The gradient of [`max_pool2x2`]: each output gradient to its window's recorded maximum, zero elsewhere.
pub fn max_pool2x2_backward(
    x: FloatTensor<Flex>,
    output_grad: FloatTensor<Flex>,
    argmax: IntTensor<Flex>,
) -> FloatTensor<Flex> {
    let prepared = (f32_data(&output_grad), argmax.dtype() == DType::U8);
    let (Some((dy_c, dy_shape)), true) = prepared else {
        return <Flex as ModuleOps<Flex>>::max_pool2d_with_indices_backward(
            x,
            [2, 2],
            [2, 2],
            [0, 0],
            [1, 1],
            false,
            output_grad,
            argmax,
        )
        .x_grad;
    };
    let x_shape = x.shape().to_vec();
    let (w, oh, ow) = (x_shape[3], dy_shape[2], dy_shape[3]);
    let argmax = if argmax.is_contiguous() {
        argmax
    } else {
        argmax.to_contiguous()
    };
    let (dy, at) = (
        slice(&dy_c),
        argmax.as_slice::<u8>().expect("contiguous u8"),
    );
    let mut dx = vec![0.0f32; x_shape.iter().product()];
    dx.par_chunks_mut(x_shape[2] * w)
        .zip(dy.par_chunks(oh * ow).zip(at.par_chunks(oh * ow)))
        .for_each(|(dx, (dy, at))| {
            for i in 0..oh {
                for j in 0..ow {
                    let k = at[i * ow + j] as usize;
                    dx[(2 * i + k / 2) * w + 2 * j + k % 2] = dy[i * ow + j];
                }
            }
        });
    from_vec(dx, &x_shape)
}

/// Elements per parallel task of the dropout kernels.
const DROPOUT_CHUNK: usize = 1 << 14;

/// Inverted dropout on f32 data. One 64-bit seed is drawn from Flex's own seeded RNG per call (so
/// `Backend::seed` before a step fixes the masks, as with Burn's dropout); element `i` is kept when the high 32
/// bits of `draw_at(keyed_u64(seed, "dropout-mask", 0), i)` are below `keep · 2³²`.
pub fn dropout(x: FloatTensor<Flex>, prob: f64) -> super::DropoutOutput<Flex> {
    use burn::tensor::ops::FloatTensorOps;
    let Some((xc, shape)) = f32_data(&x) else {
        return reference::dropout::<Flex>(x, prob);
    };
    let draws = <Flex as FloatTensorOps<Flex>>::float_random(
        burn::tensor::Shape::new([2]),
        burn::tensor::Distribution::Default,
        &Default::default(),
        burn::tensor::FloatDType::F32,
    );
    let draws = f32_data(&draws).expect("f32 draws").0;
    let bits = slice(&draws);
    let seed = (u64::from(bits[0].to_bits()) << 32) | u64::from(bits[1].to_bits());
    let (out, mask) = dropout_mask(slice(&xc), prob, seed);
    super::DropoutOutput {
        output: from_vec(out, &shape),
        mask: from_vec(mask, &shape),
    }
}

/// `(x · mask / keep, mask)` with element `i`'s keep decision a stateless draw at `i` (one multiply-and-mix per
/// element, in SIMD lanes; a ChaCha8 stream per chunk cost 11 ms of a width-16 step).
pub(super) fn dropout_mask(values: &[f32], prob: f64, seed: u64) -> (Vec<f32>, Vec<f32>) {
    use dataset::rng::{draw_at, keyed_u64};
    let keep = 1.0 - prob;
    let threshold = (keep * 4_294_967_296.0).min(4_294_967_295.0) as u64;
    let scale = (1.0 / keep) as f32;
    let key = keyed_u64(seed, "dropout-mask", 0);
    let mut out = vec![0.0f32; values.len()];
    let mut mask = vec![0.0f32; values.len()];
    out.par_chunks_mut(DROPOUT_CHUNK)
        .zip(mask.par_chunks_mut(DROPOUT_CHUNK))
        .zip(values.par_chunks(DROPOUT_CHUNK))
        .enumerate()
        .for_each(|(chunk, ((out, mask), x))| {
            let first = (chunk * DROPOUT_CHUNK) as u64;
            vectorized(
                #[inline(always)]
                || {
                    for (i, ((out, mask), &x)) in
                        out.iter_mut().zip(mask.iter_mut()).zip(x).enumerate()
                    {
                        let kept = (draw_at(key, first + i as u64) >> 32) < threshold;
                        *mask = if kept { 1.0 } else { 0.0 };
                        *out = if kept { x * scale } else { 0.0 };
                    }
                },
            );
        });
    (out, mask)
}

pub fn dropout_backward(
    output_grad: FloatTensor<Flex>,
    mask: FloatTensor<Flex>,
    prob: f64,
) -> FloatTensor<Flex> {
    let (Some((dy_c, shape)), Some((mask_c, _))) = (f32_data(&output_grad), f32_data(&mask)) else {
        return reference::dropout_backward::<Flex>(output_grad, mask, prob);
    };
    let scale = (1.0 / (1.0 - prob)) as f32;
    let (dy, m) = (slice(&dy_c), slice(&mask_c));
    let mut dx = vec![0.0f32; dy.len()];
    dx.par_chunks_mut(DROPOUT_CHUNK)
        .zip(
            dy.par_chunks(DROPOUT_CHUNK)
                .zip(m.par_chunks(DROPOUT_CHUNK)),
        )
        .for_each(|(dx, (dy, m))| {
            vectorized(
                #[inline(always)]
                || {
                    dx.iter_mut()
                        .zip(dy.iter().zip(m))
                        .for_each(|(dx, (&dy, &m))| *dx = dy * m * scale)
                },
            );
        });
    from_vec(dx, &shape)
}

/// Rows (or columns) of a 3×3 kernel that fall on each of the two coarse-grid taps of output phase `a` when the
/// input is first repeated ×2 (nearest): phase 0 reads coarse offsets −1 (kernel row 0) and 0 (rows 1, 2); phase 1
/// reads 0 (rows 0, 1) and +1 (row 2).
const PHASE_TAPS: [[&[usize]; 2]; 2] = [[&[0], &[1, 2]], [&[0, 1], &[2]]];

/// The 2×2 coarse-grid convolution of output phase (a, b): same size as the coarse input, padding 1 − a.
fn phase_shape(s: &ConvShape, a: usize, b: usize) -> ConvShape {
    ConvShape {
        kernel: [2, 2],
        padding: [1 - a, 1 - b],
        ..*s
    }
}

/// `K_ab[o][c][t][u] = Σ W[o][c][ky][kx]` over the kernel rows/columns phase (a, b) folds onto coarse tap (t, u).
fn phase_kernel(w: &[f32], c_out: usize, c_in: usize, a: usize, b: usize) -> Vec<f32> {
    let mut k = vec![0.0f32; c_out * c_in * 4];
    for oc in 0..c_out * c_in {
        for t in 0..2 {
            for u in 0..2 {
                k[oc * 4 + t * 2 + u] = PHASE_TAPS[a][t]
                    .iter()
                    .flat_map(|&ky| PHASE_TAPS[b][u].iter().map(move |&kx| (ky, kx)))
                    .map(|(ky, kx)| w[oc * 9 + ky * 3 + kx])
                    .sum();
            }
        }
    }
    k
}

/// The coarse input and 3×3 weight of a supported up-convolution, as [`conv_operands`] (the coarse shape).
fn upsample_conv_operands(
    x: &FlexTensor,
    weight: &FlexTensor,
    third: Option<&FlexTensor>,
) -> Option<(FlexTensor, FlexTensor, Option<FlexTensor>, ConvShape)> {
    let options = ConvOptions::new([1, 1], [1, 1], [1, 1], 1);
    let (xc, wc, third, s) = conv_operands(x, weight, third, &options)?;
    (s.kernel == [3, 3]).then_some((xc, wc, third, s))
}

/// `conv3×3(nearest×2(x)) + b` computed on the coarse grid: for each of the four output phases a 2×2
/// convolution with the 3×3 kernel's taps summed where they read the same coarse pixel (4/9 of the
/// multiply-adds, and no upsampled copy of the input), in cache-sized row blocks as [`conv2d`].
pub fn upsample_conv2d(
    x: FloatTensor<Flex>,
    weight: FloatTensor<Flex>,
    bias: Option<FloatTensor<Flex>>,
) -> FloatTensor<Flex> {
    let Some((xc, wc, bias_c, s)) = upsample_conv_operands(&x, &weight, bias.as_ref()) else {
        return reference::upsample_conv2d::<Flex>(x, weight, bias);
    };
    let (xs, bias) = (slice(&xc), bias_c.as_ref().map(slice));
    let (h, w, hw) = (s.height, s.width, s.positions());
    let (plane_in, _) = s.planes();
    let kernels: Vec<Vec<f32>> = (0..4)
        .map(|p| phase_kernel(slice(&wc), s.c_out, s.c_in, p / 2, p % 2))
        .collect();
    let block = phase_shape(&s, 0, 0).block_len();
    let mut y = vec![0.0f32; s.batch * s.c_out * 4 * hw];
    y.par_chunks_mut(s.c_out * 4 * hw)
        .zip(xs.par_chunks(plane_in))
        .for_each(|(y, x)| {
            with_scratch([block, s.c_out * hw], |col, y_ab| {
                for (p, k) in kernels.iter().enumerate() {
                    let (a, b) = (p / 2, p % 2);
                    convolve_sample(&phase_shape(&s, a, b), x, k, y_ab, false, col);
                    for (o, plane) in y_ab.chunks(hw).enumerate() {
                        let shift = bias.map_or(0.0, |b| b[o]);
                        let out = &mut y[o * 4 * hw..(o + 1) * 4 * hw];
                        for i in 0..h {
                            let row = &mut out[(2 * i + a) * 2 * w..][..2 * w];
                            for j in 0..w {
                                row[2 * j + b] = plane[i * w + j] + shift;
                            }
                        }
                    }
                }
            });
        });
    from_vec(y, &[s.batch, s.c_out, 2 * h, 2 * w])
}

/// Phase (a, b) of one sample's `[c_out, 2h, 2w]` gradient as a contiguous `[c_out, h·w]` block.
fn gather_phase(dy: &[f32], s: &ConvShape, a: usize, b: usize, out: &mut [f32]) {
    let (h, w, hw) = (s.height, s.width, s.positions());
    for (o, plane) in out.chunks_mut(hw).enumerate() {
        let fine = &dy[o * 4 * hw..(o + 1) * 4 * hw];
        for i in 0..h {
            let row = &fine[(2 * i + a) * 2 * w..][..2 * w];
            for j in 0..w {
                plane[i * w + j] = row[2 * j + b];
            }
        }
    }
}

/// ∂X (coarse) of the up convolution: the sum over the four phases of each phase convolution's adjoint, a 2×2
/// convolution of that phase's ∂Y with the phase kernel turned by 180° (padding `a`, `b` where the forward had
/// `1 − a`, `1 − b`), accumulated into ∂X without a scatter.
pub fn upsample_conv2d_x_grad(
    x: FloatTensor<Flex>,
    weight: FloatTensor<Flex>,
    output_grad: FloatTensor<Flex>,
) -> FloatTensor<Flex> {
    let Some((_, wc, Some(dy_c), s)) = upsample_conv_operands(&x, &weight, Some(&output_grad))
    else {
        return reference::upsample_conv2d_x_grad::<Flex>(x, weight, output_grad);
    };
    let dy = slice(&dy_c);
    let hw = s.positions();
    let (plane_in, _) = s.planes();
    let adjoint = |a: usize, b: usize| ConvShape {
        c_in: s.c_out,
        c_out: s.c_in,
        kernel: [2, 2],
        padding: [a, b],
        ..s
    };
    let turned: Vec<Vec<f32>> = (0..4)
        .map(|p| {
            let k = phase_kernel(slice(&wc), s.c_out, s.c_in, p / 2, p % 2);
            turned_kernel(&k, s.c_out, s.c_in, [2, 2])
        })
        .collect();
    let block = adjoint(0, 0).block_len();
    let mut dx = vec![0.0f32; s.batch * plane_in];
    dx.par_chunks_mut(plane_in)
        .zip(dy.par_chunks(s.c_out * 4 * hw))
        .for_each(|(dx, dy)| {
            with_scratch([block, s.c_out * hw], |col, dy_ab| {
                for (p, k) in turned.iter().enumerate() {
                    let (a, b) = (p / 2, p % 2);
                    gather_phase(dy, &s, a, b, dy_ab);
                    convolve_sample(&adjoint(a, b), dy_ab, k, dx, p > 0, col);
                }
            });
        });
    from_vec(dx, &s.input_shape())
}

pub fn upsample_conv2d_weight_grad(
    x: FloatTensor<Flex>,
    weight: FloatTensor<Flex>,
    output_grad: FloatTensor<Flex>,
) -> FloatTensor<Flex> {
    let Some((xc, _, Some(dy_c), s)) = upsample_conv_operands(&x, &weight, Some(&output_grad))
    else {
        return reference::upsample_conv2d_weight_grad::<Flex>(x, weight, output_grad);
    };
    let (xs, dy) = (slice(&xc), slice(&dy_c));
    let hw = s.positions();
    let (plane_in, _) = s.planes();
    let phase_len = 4 * s.c_in * s.c_out;
    let phase = |a: usize, b: usize| phase_shape(&s, a, b);
    let block_positions = phase(0, 0).block_rows() * s.width;
    // One partial per sample of the four phase kernels' gradients ∂K_ab (stored ∂K_abᵀ: taps × c_out), summed
    // in sample order (bit-reproducible, as the plain convolution's); the fold of each coarse tap back onto the
    // 3×3 taps it summed is linear, so it runs once on the sum instead of once per sample (it scatters with a
    // stride of c_in·9 and cost as much as the arithmetic when done per sample).
    let mut partials = vec![0.0f32; s.batch * 4 * phase_len];
    partials
        .par_chunks_mut(4 * phase_len)
        .zip(xs.par_chunks(plane_in).zip(dy.par_chunks(s.c_out * 4 * hw)))
        .for_each(|(dk_t, (x, dy))| {
            let lens = [phase(0, 0).block_len(), s.c_out * (hw + block_positions)];
            with_scratch(lens, |col, buffers| {
                let (dy_ab, dy_t) = buffers.split_at_mut(s.c_out * hw);
                for (p, dk_t) in dk_t.chunks_mut(phase_len).enumerate() {
                    let (a, b) = (p / 2, p % 2);
                    gather_phase(dy, &s, a, b, dy_ab);
                    weight_grad_sample(&phase(a, b), x, dy_ab, dk_t, col, dy_t);
                }
            });
        });
    let dk_t = sum_in_order(&partials, 4 * phase_len);
    // Each coarse tap (t, u) of phase (a, b) spreads back onto the 3×3 taps it summed.
    let mut dw = vec![0.0f32; s.c_out * s.c_in * 9];
    for (p, dk_t) in dk_t.chunks(phase_len).enumerate() {
        let (a, b) = (p / 2, p % 2);
        for c in 0..s.c_in {
            for t in 0..2 {
                for u in 0..2 {
                    let row = &dk_t[((c * 2 + t) * 2 + u) * s.c_out..][..s.c_out];
                    for &ky in PHASE_TAPS[a][t] {
                        for &kx in PHASE_TAPS[b][u] {
                            for (o, &g) in row.iter().enumerate() {
                                dw[(o * s.c_in + c) * 9 + ky * 3 + kx] += g;
                            }
                        }
                    }
                }
            }
        }
    }
    from_vec(dw, &[s.c_out, s.c_in, 3, 3])
}

/// `[LeakyReLU(a), b]` along channels, per sample: the first part activated as it is copied, the second copied.
pub fn join_channels(a: FloatTensor<Flex>, b: FloatTensor<Flex>, slope: f64) -> FloatTensor<Flex> {
    let (Some((ac, a_shape)), Some((bc, b_shape))) = (f32_data(&a), f32_data(&b)) else {
        return reference::join_channels::<Flex>(a, b, slope);
    };
    let (sample_a, sample_b) = (
        a_shape[1..].iter().product::<usize>(),
        b_shape[1..].iter().product::<usize>(),
    );
    if sample_a == 0 || sample_b == 0 {
        return reference::join_channels::<Flex>(a, b, slope);
    }
    let slope = slope as f32;
    let mut out = vec![0.0f32; a_shape[0] * (sample_a + sample_b)];
    out.par_chunks_mut(sample_a + sample_b)
        .zip(
            slice(&ac)
                .par_chunks(sample_a)
                .zip(slice(&bc).par_chunks(sample_b)),
        )
        .for_each(|(out, (a, b))| {
            let (out_a, out_b) = out.split_at_mut(sample_a);
            vectorized(
                #[inline(always)]
                || {
                    out_a
                        .iter_mut()
                        .zip(a)
                        .for_each(|(y, &x)| *y = leaky_relu(x, slope))
                },
            );
            out_b.copy_from_slice(b);
        });
    let mut shape = a_shape;
    shape[1] += b_shape[1];
    from_vec(out, &shape)
}

/// The gradient of [`join_channels`]: per sample the output gradient's first `a` channels times LeakyReLU's
/// slope where `a < 0`, and the rest copied, each into a contiguous tensor.
pub fn join_channels_backward(
    a: FloatTensor<Flex>,
    grad: FloatTensor<Flex>,
    slope: f64,
) -> (FloatTensor<Flex>, FloatTensor<Flex>) {
    let (Some((ac, a_shape)), Some((gc, shape))) = (f32_data(&a), f32_data(&grad)) else {
        return reference::join_channels_backward::<Flex>(a, grad, slope);
    };
    let plane = shape[2..].iter().product::<usize>();
    let (sample, sample_a) = (shape[1] * plane, a_shape[1] * plane);
    let sample_b = sample - sample_a;
    if sample_a == 0 || sample_b == 0 {
        return reference::join_channels_backward::<Flex>(a, grad, slope);
    }
    let slope = slope as f32;
    let (mut grad_a, mut grad_b) = (
        vec![0.0f32; shape[0] * sample_a],
        vec![0.0f32; shape[0] * sample_b],
    );
    grad_a
        .par_chunks_mut(sample_a)
        .zip(grad_b.par_chunks_mut(sample_b))
        .zip(
            slice(&gc)
                .par_chunks(sample)
                .zip(slice(&ac).par_chunks(sample_a)),
        )
        .for_each(|((grad_a, grad_b), (g, a))| {
            vectorized(
                #[inline(always)]
                || {
                    grad_a
                        .iter_mut()
                        .zip(g[..sample_a].iter().zip(a))
                        .for_each(|(d, (&g, &a))| *d = leaky_relu_grad(a, g, slope))
                },
            );
            grad_b.copy_from_slice(&g[sample_a..]);
        });
    let mut b_shape = shape;
    b_shape[1] -= a_shape[1];
    (from_vec(grad_a, &a_shape), from_vec(grad_b, &b_shape))
}

/// The renderer layer's loss in one pass per sample: rendered `r = Σ_k LeakyReLU(p_k)·T_k`, masked squared error
/// summed in f64 per sample (then in sample order: the same bits on any thread count), and the loss's gradient
/// with respect to `r`, `2·valid·(r − I)/count`, which the backward pass reuses.
pub fn render_masked_mse(
    raw: FloatTensor<Flex>,
    terms: FloatTensor<Flex>,
    image: FloatTensor<Flex>,
    valid: FloatTensor<Flex>,
    slope: f64,
) -> super::RenderLoss<Flex> {
    let prepared = [&raw, &terms, &image, &valid].map(f32_data);
    let [Some((raw_c, shape)), Some((terms_c, terms_shape)), Some((image_c, _)), Some((valid_c, _))] =
        prepared
    else {
        return reference::render_masked_mse::<Flex>(raw, terms, image, valid, slope);
    };
    assert_eq!(
        shape, terms_shape,
        "parameter maps and scene terms differ in shape"
    );
    let (p, plane) = (shape[1], shape[2..].iter().product::<usize>());
    let (raw, terms, image, valid) = (
        slice(&raw_c),
        slice(&terms_c),
        slice(&image_c),
        slice(&valid_c),
    );
    let slope = slope as f32;
    let mut residual = vec![0.0f32; shape[0] * plane];
    // (Σ valid·d², Σ valid) per sample, with d = r − I; `residual` holds valid·d until scaled below.
    let partials: Vec<(f64, f64)> = residual
        .par_chunks_mut(plane)
        .enumerate()
        .map(|(n, resid)| {
            let (raw, terms) = (
                &raw[n * p * plane..(n + 1) * p * plane],
                &terms[n * p * plane..(n + 1) * p * plane],
            );
            let (image, valid) = (
                &image[n * plane..(n + 1) * plane],
                &valid[n * plane..(n + 1) * plane],
            );
            resid.iter_mut().enumerate().for_each(|(px, r)| {
                let rendered: f32 = (0..p)
                    .map(|k| leaky_relu(raw[k * plane + px], slope) * terms[k * plane + px])
                    .sum();
                *r = valid[px] * (rendered - image[px]);
            });
            lane_sums(resid, valid, |d, v| ((d * d) as f64 * v as f64, v as f64))
        })
        .collect();
    let (sum, count) = partials
        .iter()
        .fold((0.0f64, 0.0f64), |a, b| (a.0 + b.0, a.1 + b.1));
    let count = count.max(1.0);
    let scale = (2.0 / count) as f32;
    residual.par_iter_mut().for_each(|r| *r *= scale);
    let mut residual_shape = shape;
    residual_shape[1] = 1;
    super::RenderLoss {
        loss: from_vec(vec![(sum / count) as f32], &[1]),
        residual: from_vec(residual, &residual_shape),
    }
}

/// ∂loss/∂p_k = g · residual · T_k · LeakyReLU′(p_k), `g` the loss's incoming gradient (`[1]`).
pub fn render_masked_mse_backward(
    raw: FloatTensor<Flex>,
    terms: FloatTensor<Flex>,
    residual: FloatTensor<Flex>,
    loss_grad: FloatTensor<Flex>,
    slope: f64,
) -> FloatTensor<Flex> {
    let prepared = [&raw, &terms, &residual, &loss_grad].map(f32_data);
    let [Some((raw_c, shape)), Some((terms_c, _)), Some((resid_c, _)), Some((grad_c, _))] =
        prepared
    else {
        return reference::render_masked_mse_backward::<Flex>(
            raw, terms, residual, loss_grad, slope,
        );
    };
    let (p, plane) = (shape[1], shape[2..].iter().product::<usize>());
    let (raw, terms, resid) = (slice(&raw_c), slice(&terms_c), slice(&resid_c));
    let (g, slope) = (slice(&grad_c)[0], slope as f32);
    let mut d_raw = vec![0.0f32; raw.len()];
    d_raw.par_chunks_mut(plane).enumerate().for_each(|(i, d)| {
        let n = i / p;
        let (raw, terms) = (
            &raw[i * plane..(i + 1) * plane],
            &terms[i * plane..(i + 1) * plane],
        );
        let resid = &resid[n * plane..(n + 1) * plane];
        for (px, d) in d.iter_mut().enumerate() {
            *d = leaky_relu_grad(raw[px], g * resid[px] * terms[px], slope);
        }
    });
    from_vec(d_raw, &shape)
}

//! Convolutions as im2col + gemm: forward, input gradient, weight gradient, and the bias gradient's per-channel
//! sums. The geometry ([`ConvShape`]) and the blocked im2col + gemm are shared with [`super::upsample_conv`].

use super::*;

std::thread_local! {
    /// Per-thread working memory for im2col matrices and transposes, reused across calls: a fresh, zeroed
    /// allocation per sample (tens of MB at width 16) cost more in memset and page faults than im2col itself.
    static SCRATCH: std::cell::RefCell<[Vec<f32>; 2]> = const { std::cell::RefCell::new([Vec::new(), Vec::new()]) };
}

/// Run `f` with two scratch slices of `lens` elements (contents unspecified: callers overwrite what they read).
pub(super) fn with_scratch<R>(lens: [usize; 2], f: impl FnOnce(&mut [f32], &mut [f32]) -> R) -> R {
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
pub(super) struct ConvShape {
    pub(super) batch: usize,
    pub(super) c_in: usize,
    pub(super) c_out: usize,
    pub(super) height: usize,
    pub(super) width: usize,
    pub(super) kernel: [usize; 2],
    pub(super) padding: [usize; 2],
}

impl ConvShape {
    pub(super) fn new(x: &[usize], weight: &[usize], options: &ConvOptions<2>) -> Option<Self> {
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
    pub(super) fn positions(&self) -> usize {
        self.height * self.width
    }

    /// Elements of one sample's input and of its output.
    pub(super) fn planes(&self) -> (usize, usize) {
        (self.c_in * self.positions(), self.c_out * self.positions())
    }

    pub(super) fn input_shape(&self) -> [usize; 4] {
        [self.batch, self.c_in, self.height, self.width]
    }

    /// Rows of the im2col matrix: input channels × kernel taps.
    pub(super) fn taps(&self) -> usize {
        self.c_in * self.kernel[0] * self.kernel[1]
    }

    /// For output column `ox` reading tap `kx`: the range of `ox` whose input column is inside the image.
    pub(super) fn valid_columns(&self, kx: usize) -> std::ops::Range<usize> {
        let (w, pad) = (self.width, self.padding[1]);
        let lo = pad.saturating_sub(kx);
        let hi = (w + pad).saturating_sub(kx).min(w);
        lo..hi.max(lo)
    }

    /// A 1×1 convolution without padding: its im2col matrix is the input itself.
    pub(super) fn is_pointwise(&self) -> bool {
        self.kernel == [1, 1] && self.padding == [0, 0]
    }

    /// `col[(c, ky, kx)][(j, ox)] = x[c][oy + ky − pad][ox + kx − pad]` (0 outside) for the `j`-th output row
    /// `oy` of `rows`, one sample: `col` is `taps × (rows.len() · width)`.
    ///
    /// A tap's row of `col`, over the output rows whose input row is inside the image, is one contiguous run of
    /// the input plane shifted by `kx − pad` (row-major planes continue into the next row), so it is one copy;
    /// only the few columns that wrapped into a neighbouring row are then zeroed. Copying row by row made
    /// one small `memcpy` per output row and tap (64 B at the coarsest level) and cost more than the copy itself.
    pub(super) fn im2col_rows(&self, x: &[f32], rows: std::ops::Range<usize>, col: &mut [f32]) {
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
    pub(super) fn block_rows(&self) -> usize {
        if self.is_pointwise() {
            self.height
        } else {
            (BLOCK_FLOATS / (self.taps() * self.width).max(1)).clamp(1, self.height.max(1))
        }
    }

    /// Scratch elements one block of [`Self::block_columns`] needs.
    pub(super) fn block_len(&self) -> usize {
        if self.is_pointwise() {
            0
        } else {
            self.taps() * self.block_rows() * self.width
        }
    }

    /// The output-row blocks of one sample, in order.
    pub(super) fn row_blocks(&self) -> impl Iterator<Item = std::ops::Range<usize>> {
        let (h, step) = (self.height, self.block_rows());
        (0..h)
            .step_by(step.max(1))
            .map(move |r| r..(r + step).min(h))
    }

    /// The im2col matrix of output rows `rows` (`taps × positions`): the input itself for a pointwise
    /// convolution (whose single block is the whole plane), else built in `buffer`.
    pub(super) fn block_columns<'a>(
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
pub(super) const BLOCK_FLOATS: usize = 1 << 18;

/// Contiguous f32 input and weight of a convolution the kernels support (with a third operand of the same
/// dtype when given: the bias or the output gradient), or `None`: the caller then takes the stock path.
pub(super) fn conv_operands(
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

/// Where a [`matmul`] puts its product: written over `dst`'s values, or added to them. Both are initialised
/// memory: gemm's edge tiles copy `dst` into a temporary even when they do not add to it.
pub(super) enum Dst<'a> {
    Write(&'a mut [f32]),
    Add(&'a mut [f32]),
}

impl<'a> Dst<'a> {
    /// Added to when `accumulate`, else written over.
    pub(super) fn init(d: &'a mut [f32], accumulate: bool) -> Self {
        if accumulate {
            Dst::Add(d)
        } else {
            Dst::Write(d)
        }
    }

    /// The same destination from element `start` on.
    pub(super) fn from(&mut self, start: usize) -> Dst<'_> {
        match self {
            Dst::Write(d) => Dst::Write(&mut d[start..]),
            Dst::Add(d) => Dst::Add(&mut d[start..]),
        }
    }
}

/// `dst (m × n) = [dst +] lhs (m × k) · rhs (k × n)`, each matrix given as (row stride, column stride).
#[allow(clippy::too_many_arguments)]
pub(super) fn matmul(
    [m, n, k]: [usize; 3],
    dst: Dst<'_>,
    dst_strides: [usize; 2],
    lhs: &[f32],
    lhs_strides: [usize; 2],
    rhs: &[f32],
    rhs_strides: [usize; 2],
) {
    let (dst_ptr, dst_len, accumulate) = match dst {
        Dst::Write(d) => (d.as_mut_ptr(), d.len(), false),
        Dst::Add(d) => (d.as_mut_ptr(), d.len(), true),
    };
    let last = |[rs, cs]: [usize; 2], rows: usize, cols: usize| {
        (rows.max(1) - 1) * rs + (cols.max(1) - 1) * cs
    };
    assert!(
        last(dst_strides, m, n) < dst_len.max(1)
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
            dst_ptr,
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

/// `Y = W·col(X) (+ b)` for every sample of contiguous `xs` with weights `w` (`c_out × taps`). With a bias the
/// output is never zeroed: the bias planes are written first and gemm adds to them.
pub(super) fn convolve(s: &ConvShape, xs: &[f32], w: &[f32], bias: Option<&[f32]>) -> Vec<f32> {
    let (plane_in, plane_out) = s.planes();
    let hw = s.positions();
    let fill = |n: usize, y: &mut [std::mem::MaybeUninit<f32>]| {
        // Zeros without a bias: gemm overwrites them, but its edge tiles copy `dst` before they do.
        y.chunks_mut(hw).enumerate().for_each(|(o, plane)| {
            plane.fill(std::mem::MaybeUninit::new(bias.map_or(0.0, |b| b[o])))
        });
        // SAFETY: every element was just written (`c_out` planes of `hw`).
        let y = unsafe { &mut *(y as *mut [std::mem::MaybeUninit<f32>] as *mut [f32]) };
        with_scratch([s.block_len(), 0], |buffer, _| {
            let x = &xs[n * plane_in..(n + 1) * plane_in];
            convolve_sample(s, x, w, Dst::init(y, bias.is_some()), buffer);
        });
    };
    // SAFETY: `fill` writes each sample's `c_out × hw` output whole before gemm runs on it.
    unsafe { par_written(s.batch * plane_out, plane_out, fill) }
}

/// One sample's `y (c_out × hw) [+]= W·col(x)`, block by block, with `buffer` ([`ConvShape::block_len`]) for the
/// columns.
pub(super) fn convolve_sample(
    s: &ConvShape,
    x: &[f32],
    w: &[f32],
    mut y: Dst<'_>,
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
            y.from(start),
            [hw, 1],
            w,
            [taps, 1],
            s.block_columns(x, rows, buffer),
            [col_stride, 1],
        );
    }
}

/// `W′[c][o][ky][kx] = W[o][c][kh−1−ky][kw−1−kx]` of a `c_out × c_in × kh × kw` kernel: the kernel of the
/// convolution that is the adjoint of `W`'s (∂Y → ∂X).
pub(super) fn turned_kernel(
    w: &[f32],
    c_out: usize,
    c_in: usize,
    [kh, kw]: [usize; 2],
) -> Vec<f32> {
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
pub(super) fn weight_grad_sample(
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
        // The first block's product is written over whatever `dw_t` held; the others add to it.
        matmul(
            [s.c_out, taps, n],
            Dst::init(&mut *dw_t, b > 0),
            [1, s.c_out],
            dy_t,
            [1, s.c_out],
            s.block_columns(x, rows, col),
            [1, col_stride],
        );
    }
}

/// The sum of consecutive `len`-element partials (one per sample), added in order: the same bits however the
/// partials were computed in parallel.
pub(super) fn sum_in_order(partials: &[f32], len: usize) -> Vec<f32> {
    let mut chunks = partials.chunks_exact(len);
    let mut total = chunks.next().expect("a batch of at least one").to_vec();
    for partial in chunks {
        total.iter_mut().zip(partial).for_each(|(a, b)| *a += b);
    }
    total
}

/// `dst (cols × rows) = srcᵀ` for a row-major `src (rows × cols)`, in cache-sized tiles.
pub(super) fn transpose(src: &[f32], rows: usize, cols: usize, dst: &mut [f32]) {
    transpose_strided(src, rows, cols, cols, dst);
}

/// [`transpose`] of a `rows × cols` matrix whose rows start `src_stride` elements apart.
pub(super) fn transpose_strided(
    src: &[f32],
    rows: usize,
    cols: usize,
    src_stride: usize,
    dst: &mut [f32],
) {
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
        return stock::channel_sums::<Flex>(t);
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

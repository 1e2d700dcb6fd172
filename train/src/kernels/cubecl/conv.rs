//! Convolution gradients as the operations a GPU runs well, written with Burn tensor operations so that any
//! backend runs them (the CubeCL backends use them; tests hold them to the stock gradients on Flex and wgpu).
//!
//! **Input gradient.** For stride 1, `∂X` is the forward convolution of `∂Y`, padded by `k − 1 − p`, with the
//! kernel turned by 180° and its channel axes swapped. burn-cubecl computes it as a transposed convolution whose
//! direct kernel took 10× the forward convolution's time for the same products (lavapipe, `docs/performance.md`);
//! [`conv2d_x_grad`] calls the forward convolution instead.
//!
//! **Weight gradient.**
//! For a stride-1 convolution `Y = W ⋆ X` with zero padding `p`, `∂W[o, c, i, j] = Σ_{n,y,x} ∂Y[n, o, y, x] ·
//! Xp[n, c, y + i, x + j]`, Xp the padded input. With the im2col matrix `col[n, y, x, (c, i, j)] = Xp[n, c, y + i,
//! x + j]` (position-major, so that a run of whole output rows is a contiguous block of rows), that is `∂W =
//! Σ_pieces ∂Yᵀ_piece · col_piece` over pieces of whole rows: one batch of a batched matmul per piece, then a sum
//! over the pieces. The pieces give the GPU parallelism over the long `N · H · W` reduction (the output itself is
//! only `C_out × C_in·k²`), and keep each f32 running sum short.

use burn::prelude::*;
use burn::tensor::ops::{ConvOptions, FloatTensor, PadMode};

use super::super::{primitive, stock, tensor};

/// Output positions per piece of the reduction, at most (a piece is whole rows; a row longer than this is one
/// piece). 1024 positions make a 128 × 128 plane 16 pieces, so a batch of 8 gives a 128-batch matmul: enough
/// independent tiles for a GPU's streaming multiprocessors while each still multiplies a 1024-long panel.
pub const PIECE_POSITIONS: usize = 1024;

/// The largest im2col matrix built at once, in bytes (a larger batch is taken in groups of samples).
pub const COL_BYTES: usize = 128 << 20;

/// ∂L/∂x of a stride-1, dilation-1, one-group convolution with zero padding `p ≤ k − 1` (every convolution of the
/// network): the forward convolution of the output gradient by the turned, transposed kernel; any other goes to
/// the backend's own kernel.
pub fn conv2d_x_grad<B: Backend>(
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    output_grad: FloatTensor<B>,
    options: ConvOptions<2>,
) -> FloatTensor<B> {
    let [_, _, kh, kw] = tensor::<B, 4>(weight.clone()).dims();
    let [ph, pw] = options.padding;
    if options.stride != [1, 1]
        || options.dilation != [1, 1]
        || options.groups != 1
        || ph >= kh
        || pw >= kw
    {
        return B::conv2d_x_backward(x, weight, output_grad, options);
    }
    x_grad_by_forward_conv::<B>(weight, output_grad, [kh, kw], [ph, pw])
}

/// ∂L/∂x (coarse) of `conv3×3(nearest×2(x))`: the input gradient on the fine grid, each 2 × 2 block summed.
pub fn upsample_conv2d_x_grad<B: Backend>(
    weight: FloatTensor<B>,
    output_grad: FloatTensor<B>,
) -> FloatTensor<B> {
    let [_, _, kh, kw] = tensor::<B, 4>(weight.clone()).dims();
    let fine = x_grad_by_forward_conv::<B>(weight, output_grad, [kh, kw], [1, 1]);
    primitive(stock::sum_2x2_blocks(tensor::<B, 4>(fine)))
}

fn x_grad_by_forward_conv<B: Backend>(
    weight: FloatTensor<B>,
    output_grad: FloatTensor<B>,
    [kh, kw]: [usize; 2],
    [ph, pw]: [usize; 2],
) -> FloatTensor<B> {
    let turned = tensor::<B, 4>(weight).swap_dims(0, 1).flip([2, 3]);
    let options = ConvOptions::new([1, 1], [kh - 1 - ph, kw - 1 - pw], [1, 1], 1);
    B::conv2d(output_grad, primitive(turned), None, options)
}

/// ∂L/∂weight of a stride-1, dilation-1, one-group convolution with symmetric zero padding (every convolution of
/// the network); any other convolution goes to the backend's own kernel.
pub fn conv2d_weight_grad<B: Backend>(
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    output_grad: FloatTensor<B>,
    options: ConvOptions<2>,
) -> FloatTensor<B> {
    if options.stride != [1, 1] || options.dilation != [1, 1] || options.groups != 1 {
        return B::conv2d_weight_backward(x, weight, output_grad, options);
    }
    let [_, _, kh, kw] = tensor::<B, 4>(weight).dims();
    primitive(weight_grad_by_samples(
        tensor::<B, 4>(x),
        tensor::<B, 4>(output_grad),
        [kh, kw],
        options.padding,
        COL_BYTES,
    ))
}

/// ∂L/∂weight of `conv3×3(nearest×2(x))` (stride 1, padding 1): the convolution's weight gradient on the
/// upsampled input.
pub fn upsample_conv2d_weight_grad<B: Backend>(
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    output_grad: FloatTensor<B>,
) -> FloatTensor<B> {
    let [_, _, kh, kw] = tensor::<B, 4>(weight).dims();
    let fine = stock::upsample2x(tensor::<B, 4>(x));
    primitive(weight_grad_by_samples(
        fine,
        tensor::<B, 4>(output_grad),
        [kh, kw],
        [1, 1],
        COL_BYTES,
    ))
}

/// Rows of output per piece: the largest divisor of `rows` whose rows hold at most [`PIECE_POSITIONS`]
/// positions (at least one row).
fn rows_per_piece(rows: usize, cols: usize) -> usize {
    (1..=rows)
        .rev()
        .find(|&r| rows.is_multiple_of(r) && r * cols <= PIECE_POSITIONS)
        .unwrap_or(1)
}

fn weight_grad<B: Backend>(
    x: Tensor<B, 4>,
    output_grad: Tensor<B, 4>,
    [kh, kw]: [usize; 2],
    [ph, pw]: [usize; 2],
) -> Tensor<B, 4> {
    let [n, c, h, w] = x.dims();
    let [n_out, c_out, h_out, w_out] = output_grad.dims();
    assert!(
        n == n_out && h + 2 * ph + 1 == h_out + kh && w + 2 * pw + 1 == w_out + kw,
        "a {kh}x{kw} convolution padded by {ph}, {pw} maps {n}x{c}x{h}x{w} to the output gradient's \
         {n_out}x{c_out}x{h_out}x{w_out}"
    );
    // [N, H + 2p, W + 2p, C]: position-major, so each tap below is a plain window of rows and columns.
    let mut planes = x.permute([0, 2, 3, 1]);
    if ph + pw > 0 {
        planes = planes.pad([(0, 0), (ph, ph), (pw, pw), (0, 0)], PadMode::Constant(0.0));
    }
    let taps = (0..kh)
        .flat_map(|i| (0..kw).map(move |j| (i, j)))
        .map(|(i, j)| {
            planes
                .clone()
                .slice([0..n, i..i + h_out, j..j + w_out, 0..c])
        })
        .collect();
    // [N, H', W', C, kh·kw]: the last two axes flatten to the weight's (c, i, j) order.
    let col: Tensor<B, 5> = Tensor::stack(taps, 4);
    let rows = rows_per_piece(h_out, w_out);
    let (pieces, positions, k) = (n * h_out / rows, rows * w_out, c * kh * kw);
    let col = col.reshape([pieces, positions, k]);
    let dy = output_grad
        .permute([0, 2, 3, 1])
        .reshape([pieces, positions, c_out]);
    dy.swap_dims(1, 2)
        .matmul(col)
        .sum_dim(0)
        .reshape([c_out, c, kh, kw])
}

/// [`weight_grad`] over groups of samples whose im2col matrix stays under `col_bytes` ([`COL_BYTES`] in use),
/// summed: the matrix holds `k²` copies of the input (151 MB for 32 channels at 128 × 128, batch 8), and wgpu caps
/// one buffer at the adapter's largest storage binding, a few hundred MiB on some GPUs. A sample's size is taken
/// on the padded plane, a little above the matrix's own, so a group errs small.
pub(super) fn weight_grad_by_samples<B: Backend>(
    x: Tensor<B, 4>,
    output_grad: Tensor<B, 4>,
    kernel: [usize; 2],
    padding: [usize; 2],
    col_bytes: usize,
) -> Tensor<B, 4> {
    let [n, c, h, w] = x.dims();
    let per_sample = (h + 2 * padding[0]) * (w + 2 * padding[1]) * c * kernel[0] * kernel[1] * 4;
    let group = (col_bytes / per_sample.max(1)).clamp(1, n.max(1));
    (0..n)
        .step_by(group)
        .map(|start| {
            let len = group.min(n - start);
            weight_grad(
                x.clone().narrow(0, start, len),
                output_grad.clone().narrow(0, start, len),
                kernel,
                padding,
            )
        })
        .reduce(|a, b| a + b)
        .expect("a batch of at least one sample")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pieces_are_whole_rows_within_the_bound() {
        assert_eq!(rows_per_piece(128, 128), 8);
        assert_eq!(rows_per_piece(8, 8), 8);
        // A prime row count: one row a piece.
        assert_eq!(rows_per_piece(127, 128), 1);
        // A row longer than the bound is a piece of its own.
        assert_eq!(rows_per_piece(4, 2048), 1);
        for (rows, cols) in [(128, 128), (64, 64), (30, 17), (13, 11)] {
            let r = rows_per_piece(rows, cols);
            assert!(rows.is_multiple_of(r) && r * cols <= PIECE_POSITIONS.max(cols));
        }
    }
}

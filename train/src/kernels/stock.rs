//! [`super::TrainOps`]'s defaults written with stock Burn tensor operations: the math every backend shares, used
//! as is where no faster kernel exists (CUDA; CPU tensors that are not f32).

use burn::prelude::*;
use burn::tensor::activation::leaky_relu;
use burn::tensor::ops::FloatTensor;

use super::{primitive, tensor, DropoutOutput, MaxPoolOutput, NormGrads, NormOutput, RenderLoss};

/// Per-channel mean of `[N, C, H, W]` as `[1, C, 1, 1]`, as Burn's BatchNorm computes it.
fn channel_mean<B: Backend>(x: Tensor<B, 4>) -> Tensor<B, 4> {
    let [n, c, h, w] = x.dims();
    x.swap_dims(0, 1)
        .reshape([c, n * h * w])
        .mean_dim(1)
        .reshape([1, c, 1, 1])
}

/// Per-channel sum of `[N, C, H, W]` as `[C]`.
pub fn channel_sums<B: Backend>(x: FloatTensor<B>) -> FloatTensor<B> {
    let x = tensor::<B, 4>(x);
    let [n, c, h, w] = x.dims();
    primitive(
        x.swap_dims(0, 1)
            .reshape([c, n * h * w])
            .sum_dim(1)
            .reshape([c]),
    )
}

pub fn batch_norm_leaky_relu<B: Backend>(
    x: FloatTensor<B>,
    gamma: FloatTensor<B>,
    beta: FloatTensor<B>,
    epsilon: f64,
    slope: f64,
) -> NormOutput<B> {
    let x = tensor::<B, 4>(x);
    let c = x.dims()[1];
    let mean = channel_mean(x.clone());
    let var = channel_mean((x.clone() - mean.clone()).square());
    let normalised = (x - mean.clone()) / (var.clone() + epsilon).sqrt();
    let gamma = tensor::<B, 1>(gamma).reshape([1, c, 1, 1]);
    let beta = tensor::<B, 1>(beta).reshape([1, c, 1, 1]);
    NormOutput {
        output: primitive(leaky_relu(normalised * gamma + beta, slope)),
        mean: primitive(mean.reshape([c])),
        var: primitive(var.reshape([c])),
    }
}

/// Inference-mode BatchNorm (the running statistics `mean`, `var`) followed by LeakyReLU, as Burn's own module
/// computes it (`BatchNorm::forward` without autodiff): `(x − μ) / √(var + ε) · γ + β`.
pub fn batch_norm_leaky_relu_inference<B: Backend>(
    x: FloatTensor<B>,
    gamma: FloatTensor<B>,
    beta: FloatTensor<B>,
    mean: FloatTensor<B>,
    var: FloatTensor<B>,
    epsilon: f64,
    slope: f64,
) -> FloatTensor<B> {
    let x = tensor::<B, 4>(x);
    let c = x.dims()[1];
    let per_channel = |t: FloatTensor<B>| tensor::<B, 1>(t).reshape([1, c, 1, 1]);
    let std = per_channel(var).add_scalar(epsilon).sqrt();
    let normalised = (x - per_channel(mean)) / std * per_channel(gamma) + per_channel(beta);
    primitive(leaky_relu(normalised, slope))
}

/// With x̂ = (x − μ)/σ, z = γx̂ + β, y = LeakyReLU(z) and g = ∂L/∂z (z < 0 exactly where y < 0):
/// ∂L/∂β = Σg, ∂L/∂γ = Σg·x̂, ∂L/∂x = γ/(σM) · (M·g − ∂L/∂β − x̂·∂L/∂γ), M = N·H·W (μ and σ depend on x).
#[allow(clippy::too_many_arguments)]
pub fn batch_norm_leaky_relu_backward<B: Backend>(
    x: FloatTensor<B>,
    gamma: FloatTensor<B>,
    mean: FloatTensor<B>,
    var: FloatTensor<B>,
    output: FloatTensor<B>,
    output_grad: FloatTensor<B>,
    epsilon: f64,
    slope: f64,
) -> NormGrads<B> {
    let x = tensor::<B, 4>(x);
    let [n, c, h, w] = x.dims();
    let per_channel = |t: FloatTensor<B>| tensor::<B, 1>(t).reshape([1, c, 1, 1]);
    let inv_std = (per_channel(var) + epsilon).sqrt().recip();
    let normalised = (x - per_channel(mean)) * inv_std.clone();
    let dy = tensor::<B, 4>(output_grad);
    let negative = tensor::<B, 4>(output).lower_elem(0.0);
    let dz = dy.clone().mask_where(negative, dy * slope);
    let d_beta = tensor::<B, 1>(channel_sums::<B>(primitive(dz.clone())));
    let d_gamma = tensor::<B, 1>(channel_sums::<B>(primitive(
        dz.clone() * normalised.clone(),
    )));
    let count = (n * h * w) as f64;
    let dx = (dz * count
        - d_beta.clone().reshape([1, c, 1, 1])
        - normalised * d_gamma.clone().reshape([1, c, 1, 1]))
        * (per_channel(gamma) * inv_std / count);
    NormGrads {
        x: primitive(dx),
        gamma: primitive(d_gamma),
        beta: primitive(d_beta),
    }
}

/// Burn's `Dropout::forward` arithmetic (a Bernoulli keep mask from the backend RNG, then `x · mask / keep`).
pub fn dropout<B: Backend>(x: FloatTensor<B>, prob: f64) -> DropoutOutput<B> {
    let x = tensor::<B, 4>(x);
    let keep = 1.0 - prob;
    let mask = x.random_like(burn::tensor::Distribution::Bernoulli(keep));
    DropoutOutput {
        output: primitive((x * mask.clone()) * (1.0 / keep)),
        mask: primitive(mask),
    }
}

pub fn dropout_backward<B: Backend>(
    output_grad: FloatTensor<B>,
    mask: FloatTensor<B>,
    prob: f64,
) -> FloatTensor<B> {
    primitive((tensor::<B, 4>(output_grad) * tensor::<B, 4>(mask)) * (1.0 / (1.0 - prob)))
}

/// 2 × 2 max-pool with stride 2 and where each maximum came from, by the backend's own kernel.
pub fn max_pool2x2<B: Backend>(x: FloatTensor<B>) -> MaxPoolOutput<B> {
    let out = B::max_pool2d_with_indices(x, [2, 2], [2, 2], [0, 0], [1, 1], false);
    MaxPoolOutput {
        output: out.output,
        argmax: out.indices,
    }
}

/// The backward of [`max_pool2x2`]: each output gradient to its window's maximum.
pub fn max_pool2x2_backward<B: Backend>(
    x: FloatTensor<B>,
    output_grad: FloatTensor<B>,
    argmax: burn::tensor::ops::IntTensor<B>,
) -> FloatTensor<B> {
    B::max_pool2d_with_indices_backward(
        x,
        [2, 2],
        [2, 2],
        [0, 0],
        [1, 1],
        false,
        output_grad,
        argmax,
    )
    .x_grad
}

/// Nearest ×2 upsampling (the stock interpolation).
pub fn upsample2x<B: Backend>(x: Tensor<B, 4>) -> Tensor<B, 4> {
    use burn::tensor::ops::{InterpolateMode, InterpolateOptions};
    let [_, _, h, w] = x.dims();
    burn::tensor::module::interpolate(
        x,
        [2 * h, 2 * w],
        InterpolateOptions::new(InterpolateMode::Nearest),
    )
}

fn same_3x3() -> burn::tensor::ops::ConvOptions<2> {
    burn::tensor::ops::ConvOptions::new([1, 1], [1, 1], [1, 1], 1)
}

/// `conv3×3(nearest×2(x)) + b` with stock operations.
pub fn upsample_conv2d<B: Backend>(
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    bias: Option<FloatTensor<B>>,
) -> FloatTensor<B> {
    B::conv2d(
        primitive(upsample2x(tensor::<B, 4>(x))),
        weight,
        bias,
        same_3x3(),
    )
}

/// ∂L/∂x: the stock convolution's input gradient on the fine grid, each 2 × 2 block summed.
pub fn upsample_conv2d_x_grad<B: Backend>(
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    output_grad: FloatTensor<B>,
) -> FloatTensor<B> {
    let fine = primitive(upsample2x(tensor::<B, 4>(x)));
    primitive(sum_2x2_blocks(tensor::<B, 4>(B::conv2d_x_backward(
        fine,
        weight,
        output_grad,
        same_3x3(),
    ))))
}

/// Each 2 × 2 block of `[N, C, 2h, 2w]` summed to `[N, C, h, w]`: the gradient of nearest ×2 upsampling.
pub fn sum_2x2_blocks<B: Backend>(g: Tensor<B, 4>) -> Tensor<B, 4> {
    let [n, c, h2, w2] = g.dims();
    g.reshape([n, c, h2 / 2, 2, w2 / 2, 2])
        .sum_dim(5)
        .sum_dim(3)
        .reshape([n, c, h2 / 2, w2 / 2])
}

pub fn upsample_conv2d_weight_grad<B: Backend>(
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    output_grad: FloatTensor<B>,
) -> FloatTensor<B> {
    let fine = primitive(upsample2x(tensor::<B, 4>(x)));
    B::conv2d_weight_backward(fine, weight, output_grad, same_3x3())
}

/// `[LeakyReLU(a), b]` along channels.
pub fn join_channels<B: Backend>(
    a: FloatTensor<B>,
    b: FloatTensor<B>,
    slope: f64,
) -> FloatTensor<B> {
    primitive(Tensor::cat(
        vec![leaky_relu(tensor::<B, 4>(a), slope), tensor::<B, 4>(b)],
        1,
    ))
}

/// The gradient of [`join_channels`] for `a` and `b`: the output gradient's channels split at `a`'s count, the
/// first part times `slope` where `a < 0`.
pub fn join_channels_backward<B: Backend>(
    a: FloatTensor<B>,
    grad: FloatTensor<B>,
    slope: f64,
) -> (FloatTensor<B>, FloatTensor<B>) {
    let a = tensor::<B, 4>(a);
    let (grad_a, grad_b) = split_channels::<B>(grad, a.dims()[1]);
    let grad_a = tensor::<B, 4>(grad_a);
    let negative = a.lower_elem(0.0);
    (
        primitive(grad_a.clone().mask_where(negative, grad_a * slope)),
        grad_b,
    )
}

/// Channels `..first` and `first..` of `[N, C, H, W]` (stock slices: views where the backend makes them).
fn split_channels<B: Backend>(t: FloatTensor<B>, first: usize) -> (FloatTensor<B>, FloatTensor<B>) {
    let t = tensor::<B, 4>(t);
    let c = t.dims()[1];
    (
        primitive(t.clone().narrow(1, 0, first)),
        primitive(t.narrow(1, first, c - first)),
    )
}

/// Rendered I/F `[N, 1, H, W]` = Σ_k LeakyReLU(p_k, slope) · T_k from raw parameter maps and the scene's terms
/// (both `[N, P, H, W]`): the renderer layer's forward in stock operations, which [`render_masked_mse`] and the
/// layer's own `render` share.
pub fn render<B: Backend>(raw: Tensor<B, 4>, terms: Tensor<B, 4>, slope: f64) -> Tensor<B, 4> {
    (leaky_relu(raw, slope) * terms).sum_dim(1)
}

/// The renderer layer's masked MSE with stock operations: rendered `r = Σ_k LeakyReLU(p_k)·T_k`,
/// `loss = Σ valid·(r − I)² / max(Σ valid, 1)`, and `∂loss/∂r = 2·valid·(r − I)/max(Σ valid, 1)`.
pub fn render_masked_mse<B: Backend>(
    raw: FloatTensor<B>,
    terms: FloatTensor<B>,
    image: FloatTensor<B>,
    valid: FloatTensor<B>,
    slope: f64,
) -> RenderLoss<B> {
    let rendered = render(tensor::<B, 4>(raw), tensor::<B, 4>(terms), slope);
    let valid = tensor::<B, 4>(valid);
    let count = valid.clone().sum().clamp_min(1.0);
    let diff = (rendered - tensor::<B, 4>(image)) * valid;
    let loss = diff.clone().square().sum() / count.clone();
    let residual = diff * (count.recip() * 2.0).reshape([1, 1, 1, 1]);
    RenderLoss {
        loss: primitive(loss),
        residual: primitive(residual),
    }
}

/// ∂loss/∂p_k = g · residual · T_k · LeakyReLU′(p_k) (slope where p_k < 0, else 1, as Burn's LeakyReLU).
pub fn render_masked_mse_backward<B: Backend>(
    raw: FloatTensor<B>,
    terms: FloatTensor<B>,
    residual: FloatTensor<B>,
    loss_grad: FloatTensor<B>,
    slope: f64,
) -> FloatTensor<B> {
    let raw = tensor::<B, 4>(raw);
    let negative = raw.clone().lower_elem(0.0);
    let lrelu_grad = raw.ones_like().mask_fill(negative, slope);
    let g = tensor::<B, 1>(loss_grad).reshape([1, 1, 1, 1]);
    primitive(tensor::<B, 4>(residual) * g * tensor::<B, 4>(terms) * lrelu_grad)
}

//! The U-Net's hot operations as one backend extension, [`TrainOps`], each with an analytic backward pass: the
//! convolutions (plain, pointwise over joined inputs, and upsample-then-convolve), a training-mode BatchNorm fused
//! with the LeakyReLU that follows it everywhere in the network (and the same fusion in inference mode, from the
//! running statistics), dropout, 2 × 2 max pooling, the channel join of a skip connection, and the masked render
//! loss.
//!
//! Why: written as stock tensor operations, BatchNorm's statistics and its autodiff graph (swap_dims, reshape,
//! broadcast sub/div/mul and their broadcast-reducing backward passes) and the stock convolution backward
//! (a 128 × 128-kernel convolution over swapped dims for the weight gradient) cost most of a CPU train step in
//! strided copies rather than arithmetic (`docs/performance.md` has the profile). Here:
//! - `autodiff` implements the trait for `Autodiff<B>`: forward on the inner backend, one graph node per
//!   operation, and a backward pass that calls the inner backend's gradient kernels;
//! - `flex/` implements it for Flex with contiguous f32 kernels, one file per operation (im2col + gemm, one pass
//!   per channel);
//! - `cubecl/` implements it for the CubeCL backends (CUDA, wgpu): the convolutions' weight gradients as batched
//!   matrix products and input gradients as forward convolutions, the rest stock Burn operations (`stock`), the
//!   same math.
//!
//! The model calls the free functions here ([`conv2d`], [`batch_norm_leaky_relu`], …) on Burn's own `Conv2d` and
//! `BatchNorm` modules, so
//! parameters, running statistics and checkpoints are exactly Burn's. Tests hold every kernel to the stock
//! operations and Burn's autodiff (values, gradients, running statistics).

mod autodiff;
pub mod cubecl;
mod flex;
pub mod profile;
pub mod stock;

use burn::nn::conv::Conv2d;
use burn::nn::pool::MaxPool2d;
use burn::nn::{BatchNorm, Dropout, PaddingConfig2d};
use burn::prelude::*;
use burn::tensor::backend::AutodiffBackend;
use burn::tensor::ops::{ConvOptions, FloatTensor, IntTensor};
use burn::tensor::TensorPrimitive;

use profile::{timed_synced, Kernel};

/// Output of the fused training-mode BatchNorm + LeakyReLU: the activation and the batch statistics that update
/// the running ones (`var` biased, as Burn's BatchNorm uses it for both normalisation and running variance).
#[derive(Debug, Clone)]
pub struct NormOutput<B: Backend> {
    /// `[N, C, H, W]`.
    pub output: FloatTensor<B>,
    /// `[C]`.
    pub mean: FloatTensor<B>,
    /// `[C]`.
    pub var: FloatTensor<B>,
}

/// Dropout's output and its keep mask (1 kept, 0 dropped), which the backward pass reuses.
#[derive(Debug, Clone)]
pub struct DropoutOutput<B: Backend> {
    pub output: FloatTensor<B>,
    pub mask: FloatTensor<B>,
}

/// A 2 × 2 max-pool's output and where each maximum came from (the backend's own encoding).
#[derive(Debug, Clone)]
pub struct MaxPoolOutput<B: Backend> {
    pub output: FloatTensor<B>,
    pub argmax: IntTensor<B>,
}

/// The renderer layer's loss (`[1]`) and its gradient with respect to the rendered image, `[N, 1, H, W]`.
#[derive(Debug, Clone)]
pub struct RenderLoss<B: Backend> {
    pub loss: FloatTensor<B>,
    pub residual: FloatTensor<B>,
}

/// Gradients of the fused BatchNorm + LeakyReLU with respect to its input, scale and shift.
#[derive(Debug, Clone)]
pub struct NormGrads<B: Backend> {
    pub x: FloatTensor<B>,
    pub gamma: FloatTensor<B>,
    pub beta: FloatTensor<B>,
}

/// The train step's hot operations. Defaults are stock Burn operations ([`stock`]), each timed with the device
/// synced while [`profile`] is on; a backend overrides what it can do faster. Inputs are `[N, C, H, W]`, `gamma`/`beta` `[C]`.
pub trait TrainOps: Backend {
    /// Convolution forward (the stock one unless overridden). `Autodiff` makes it a graph node whose backward
    /// calls the gradient methods below on the inner backend.
    fn train_conv2d(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: Option<FloatTensor<Self>>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self> {
        let device = Self::float_device(&x);
        timed_synced::<Self, _>(Kernel::ConvForward, &device, || {
            Self::conv2d(x, weight, bias, options)
        })
    }

    /// ∂L/∂x of a convolution, given ∂L/∂output.
    fn train_conv2d_x_grad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        output_grad: FloatTensor<Self>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self> {
        let device = Self::float_device(&x);
        timed_synced::<Self, _>(Kernel::ConvInputGrad, &device, || {
            Self::conv2d_x_backward(x, weight, output_grad, options)
        })
    }

    /// ∂L/∂weight of a convolution.
    fn train_conv2d_weight_grad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        output_grad: FloatTensor<Self>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self> {
        let device = Self::float_device(&x);
        timed_synced::<Self, _>(Kernel::ConvWeightGrad, &device, || {
            Self::conv2d_weight_backward(x, weight, output_grad, options)
        })
    }

    /// `conv3×3(nearest×2(x)) + bias` (stride 1, padding 1): the U-Net's up convolution, `[N, C, h, w]` →
    /// `[N, C', 2h, 2w]`. Graph node under `Autodiff` with the two gradient methods below.
    fn train_upsample_conv2d(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: Option<FloatTensor<Self>>,
    ) -> FloatTensor<Self> {
        let device = Self::float_device(&x);
        timed_synced::<Self, _>(Kernel::UpConvForward, &device, || {
            stock::upsample_conv2d::<Self>(x, weight, bias)
        })
    }

    /// ∂L/∂x (coarse) of [`TrainOps::train_upsample_conv2d`].
    fn train_upsample_conv2d_x_grad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        output_grad: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let device = Self::float_device(&x);
        timed_synced::<Self, _>(Kernel::UpConvInputGrad, &device, || {
            stock::upsample_conv2d_x_grad::<Self>(x, weight, output_grad)
        })
    }

    /// ∂L/∂weight of [`TrainOps::train_upsample_conv2d`].
    fn train_upsample_conv2d_weight_grad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        output_grad: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let device = Self::float_device(&x);
        timed_synced::<Self, _>(Kernel::UpConvWeightGrad, &device, || {
            stock::upsample_conv2d_weight_grad::<Self>(x, weight, output_grad)
        })
    }

    /// ∂L/∂bias of a convolution: the output gradient summed over batch and positions, `[C_out]`.
    fn train_conv2d_bias_grad(output_grad: FloatTensor<Self>) -> FloatTensor<Self> {
        let device = Self::float_device(&output_grad);
        timed_synced::<Self, _>(Kernel::ConvBiasGrad, &device, || {
            stock::channel_sums::<Self>(output_grad)
        })
    }

    /// Inverted dropout (training): `x · mask / (1 − prob)` with a keep mask drawn from the backend's seeded RNG.
    fn dropout(x: FloatTensor<Self>, prob: f64) -> DropoutOutput<Self> {
        let device = Self::float_device(&x);
        timed_synced::<Self, _>(Kernel::DropoutForward, &device, || {
            stock::dropout::<Self>(x, prob)
        })
    }

    /// ∂L/∂x of [`TrainOps::dropout`]: `∂y · mask / (1 − prob)`.
    fn dropout_backward(
        output_grad: FloatTensor<Self>,
        mask: FloatTensor<Self>,
        prob: f64,
    ) -> FloatTensor<Self> {
        let device = Self::float_device(&output_grad);
        timed_synced::<Self, _>(Kernel::DropoutBackward, &device, || {
            stock::dropout_backward::<Self>(output_grad, mask, prob)
        })
    }

    /// 2 × 2 max-pool with stride 2 (floor mode): the output and the backend's record of where each maximum was.
    fn max_pool2x2(x: FloatTensor<Self>) -> MaxPoolOutput<Self> {
        let device = Self::float_device(&x);
        timed_synced::<Self, _>(Kernel::PoolForward, &device, || {
            stock::max_pool2x2::<Self>(x)
        })
    }

    /// ∂L/∂x of [`TrainOps::max_pool2x2`]: each output gradient goes to its window's maximum.
    fn max_pool2x2_backward(
        x: FloatTensor<Self>,
        output_grad: FloatTensor<Self>,
        argmax: IntTensor<Self>,
    ) -> FloatTensor<Self> {
        let device = Self::float_device(&x);
        timed_synced::<Self, _>(Kernel::PoolBackward, &device, || {
            stock::max_pool2x2_backward::<Self>(x, output_grad, argmax)
        })
    }

    /// `[LeakyReLU(a), b]` joined along channels (`[N, Ca, H, W]`, `[N, Cb, H, W]` → `[N, Ca + Cb, H, W]`): the
    /// U-Net's up path, the up convolution's raw output activated and joined with the skip in one pass. Graph
    /// node under `Autodiff`, whose backward ([`TrainOps::train_join_channels_backward`]) hands each input a
    /// contiguous gradient where the stock concatenation's slices left strided views that every following
    /// operation, and the gradient sum at the skip, iterated slowly.
    fn train_join_channels(
        a: FloatTensor<Self>,
        b: FloatTensor<Self>,
        slope: f64,
    ) -> FloatTensor<Self> {
        let device = Self::float_device(&a);
        timed_synced::<Self, _>(Kernel::JoinChannels, &device, || {
            stock::join_channels::<Self>(a, b, slope)
        })
    }

    /// The gradients of [`TrainOps::train_join_channels`] for `a` and `b` from the output's gradient.
    fn train_join_channels_backward(
        a: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        slope: f64,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let device = Self::float_device(&a);
        timed_synced::<Self, _>(Kernel::JoinChannelsBackward, &device, || {
            stock::join_channels_backward::<Self>(a, grad, slope)
        })
    }

    /// The renderer layer's masked MSE from raw parameter maps `[N, P, H, W]`, the scene's terms (same shape),
    /// the photograph and its 0/1 valid mask (`[N, 1, H, W]`): `Σ valid·(Σ_k LeakyReLU(p_k)·T_k − I)² /
    /// max(Σ valid, 1)`. Under `Autodiff` one graph node whose only tracked input is `raw` (the scene is a
    /// constant of the batch), in place of a dozen stock operations and their broadcasting backward passes.
    fn render_masked_mse(
        raw: FloatTensor<Self>,
        terms: FloatTensor<Self>,
        image: FloatTensor<Self>,
        valid: FloatTensor<Self>,
        slope: f64,
    ) -> RenderLoss<Self> {
        let device = Self::float_device(&raw);
        timed_synced::<Self, _>(Kernel::RenderLoss, &device, || {
            stock::render_masked_mse::<Self>(raw, terms, image, valid, slope)
        })
    }

    /// ∂L/∂raw of [`TrainOps::render_masked_mse`], given the loss's incoming gradient `loss_grad` (`[1]`).
    fn render_masked_mse_backward(
        raw: FloatTensor<Self>,
        terms: FloatTensor<Self>,
        residual: FloatTensor<Self>,
        loss_grad: FloatTensor<Self>,
        slope: f64,
    ) -> FloatTensor<Self> {
        let device = Self::float_device(&raw);
        timed_synced::<Self, _>(Kernel::RenderLossBackward, &device, || {
            stock::render_masked_mse_backward::<Self>(raw, terms, residual, loss_grad, slope)
        })
    }

    /// Training-mode BatchNorm (batch statistics) followed by LeakyReLU with `slope`.
    fn batch_norm_leaky_relu(
        x: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        epsilon: f64,
        slope: f64,
    ) -> NormOutput<Self> {
        let device = Self::float_device(&x);
        timed_synced::<Self, _>(Kernel::NormForward, &device, || {
            stock::batch_norm_leaky_relu::<Self>(x, gamma, beta, epsilon, slope)
        })
    }

    /// Inference-mode BatchNorm (running statistics `mean`, `var`, `[C]`) followed by LeakyReLU with `slope`:
    /// validation, evaluation and inference.
    #[allow(clippy::too_many_arguments)]
    fn batch_norm_leaky_relu_inference(
        x: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        epsilon: f64,
        slope: f64,
    ) -> FloatTensor<Self> {
        let device = Self::float_device(&x);
        timed_synced::<Self, _>(Kernel::NormInference, &device, || {
            stock::batch_norm_leaky_relu_inference::<Self>(
                x, gamma, beta, mean, var, epsilon, slope,
            )
        })
    }

    /// Backward of [`TrainOps::batch_norm_leaky_relu`] given the forward's input, parameters, statistics and
    /// output. The stock path takes the LeakyReLU's slope mask from `output`; a kernel may instead recompute the
    /// pre-activation from `x`, `gamma`, `beta` and the statistics (one memory stream fewer per pass).
    #[allow(clippy::too_many_arguments)]
    fn batch_norm_leaky_relu_backward(
        x: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        mean: FloatTensor<Self>,
        var: FloatTensor<Self>,
        output: FloatTensor<Self>,
        output_grad: FloatTensor<Self>,
        epsilon: f64,
        slope: f64,
    ) -> NormGrads<Self> {
        let _ = beta;
        let device = Self::float_device(&x);
        timed_synced::<Self, _>(Kernel::NormBackward, &device, || {
            stock::batch_norm_leaky_relu_backward::<Self>(
                x,
                gamma,
                mean,
                var,
                output,
                output_grad,
                epsilon,
                slope,
            )
        })
    }
}

/// A backend the trainer can fit on: autodiff with [`TrainOps`] on both the autodiff and the inner backend.
pub trait TrainBackend: AutodiffBackend<InnerBackend: TrainOps> + TrainOps {}

impl<B: AutodiffBackend<InnerBackend: TrainOps> + TrainOps> TrainBackend for B {}

fn primitive<B: Backend, const D: usize>(t: Tensor<B, D>) -> FloatTensor<B> {
    t.into_primitive().tensor()
}

fn tensor<B: Backend, const D: usize>(p: FloatTensor<B>) -> Tensor<B, D> {
    Tensor::from_primitive(TensorPrimitive::Float(p))
}

/// `conv.forward(x)` through [`TrainOps::train_conv2d`]. Supports the paddings the network uses: `Valid` and
/// symmetric `Explicit` (panics on others rather than pad differently from Burn).
pub fn conv2d<B: TrainOps>(conv: &Conv2d<B>, x: Tensor<B, 4>) -> Tensor<B, 4> {
    let padding = match conv.padding {
        PaddingConfig2d::Valid => [0, 0],
        PaddingConfig2d::Explicit(top, left, bottom, right) if top == bottom && left == right => {
            [top, left]
        }
        ref other => {
            panic!("kernels::conv2d supports Valid and symmetric Explicit padding, not {other:?}")
        }
    };
    let options = ConvOptions::new(conv.stride, padding, conv.dilation, conv.groups);
    tensor(B::train_conv2d(
        primitive(x),
        primitive(conv.weight.val()),
        conv.bias.as_ref().map(|b| primitive(b.val())),
        options,
    ))
}

/// A 1×1 convolution of `x` (`[N, C, H, W]`) joined with `features` (`[N, K]`) as `K` planes constant over
/// each sample: `conv(cat[x, features broadcast])` without building the planes. Over a constant plane a 1×1
/// convolution is a per-sample offset, so it is `conv_x(x) + W_f · features` with the weight split by input
/// channel (`W = [W_x | W_f]`). At the head the planes were `K / C` times the features the network computes
/// there (32 planes beside 8 at width 8): building them, the joined gemm over them and their gradients'
/// reduction back to `[N, K]` cost more of a train step than the head's own work.
pub fn pointwise_conv2d_joined<B: TrainOps>(
    conv: &Conv2d<B>,
    x: Tensor<B, 4>,
    features: &Tensor<B, 2>,
) -> Tensor<B, 4> {
    let [p, joined, kh, kw] = conv.weight.dims();
    let ([n, c, h, w], [nf, k]) = (x.dims(), features.dims());
    assert!(
        [kh, kw] == [1, 1]
            && matches!(conv.padding, PaddingConfig2d::Valid)
            && conv.stride == [1, 1]
            && conv.dilation == [1, 1]
            && conv.groups == 1,
        "pointwise_conv2d_joined needs a 1x1, stride-1, unpadded convolution"
    );
    assert!(
        joined == c + k && nf == n,
        "a {joined}-channel convolution cannot join {c} channels with {k} features of {nf} samples"
    );
    let weight = conv.weight.val();
    let local_weight = weight.clone().narrow(1, 0, c);
    let feature_weight = weight.narrow(1, c, k).reshape([p, k]);
    let local = tensor(B::train_conv2d(
        primitive(x),
        primitive(local_weight),
        conv.bias.as_ref().map(|b| primitive(b.val())),
        ConvOptions::new([1, 1], [0, 0], [1, 1], 1),
    ));
    let offset = features.clone().matmul(feature_weight.transpose());
    local + offset.reshape([n, p, 1, 1]).expand([n, p, h, w])
}

/// `dropout.forward(x)` through [`TrainOps::dropout`]: the identity in inference or at probability 0, as Burn's.
pub fn dropout<B: TrainOps>(dropout: &Dropout, x: Tensor<B, 4>) -> Tensor<B, 4> {
    if !B::ad_enabled(&x.device()) || dropout.prob == 0.0 {
        return x;
    }
    tensor(B::dropout(primitive(x), dropout.prob).output)
}

/// `conv.forward(nearest×2(x))` through [`TrainOps::train_upsample_conv2d`]: the up path's convolution, computed
/// on the coarse grid. Panics unless `conv` is a 3×3, stride-1, padding-1 convolution (what the network builds).
pub fn upsample_conv2d<B: TrainOps>(conv: &Conv2d<B>, x: Tensor<B, 4>) -> Tensor<B, 4> {
    assert!(
        conv.kernel_size == [3, 3]
            && conv.stride == [1, 1]
            && conv.dilation == [1, 1]
            && conv.groups == 1
            && matches!(conv.padding, PaddingConfig2d::Explicit(1, 1, 1, 1)),
        "kernels::upsample_conv2d supports the network's 3x3 same convolutions only"
    );
    tensor(B::train_upsample_conv2d(
        primitive(x),
        primitive(conv.weight.val()),
        conv.bias.as_ref().map(|b| primitive(b.val())),
    ))
}

/// `Tensor::cat(vec![leaky_relu(a, slope), b], 1)` through [`TrainOps::train_join_channels`].
pub fn join_channels<B: TrainOps>(a: Tensor<B, 4>, b: Tensor<B, 4>, slope: f64) -> Tensor<B, 4> {
    tensor(B::train_join_channels(primitive(a), primitive(b), slope))
}

/// The renderer layer's masked MSE through [`TrainOps::render_masked_mse`] (LeakyReLU slope `slope` on the raw
/// parameters); `terms`, `image` and `valid` are constants of the batch and get no gradient.
pub fn render_masked_mse<B: TrainOps>(
    raw: Tensor<B, 4>,
    terms: Tensor<B, 4>,
    image: Tensor<B, 4>,
    valid: Tensor<B, 4>,
    slope: f64,
) -> Tensor<B, 1> {
    tensor(
        B::render_masked_mse(
            primitive(raw),
            primitive(terms),
            primitive(image),
            primitive(valid),
            slope,
        )
        .loss,
    )
}

/// `pool.forward(x)` through [`TrainOps::max_pool2x2`]; the network pools 2 × 2 with stride 2 only (panics on
/// another configuration rather than pool differently from Burn).
pub fn max_pool2d<B: TrainOps>(pool: &MaxPool2d, x: Tensor<B, 4>) -> Tensor<B, 4> {
    assert!(
        pool.kernel_size == [2, 2]
            && pool.stride == [2, 2]
            && pool.dilation == [1, 1]
            && !pool.ceil_mode
            && matches!(
                pool.padding,
                PaddingConfig2d::Valid | PaddingConfig2d::Explicit(0, 0, 0, 0)
            ),
        "kernels::max_pool2d supports 2x2 stride-2 pooling only, not {pool:?}"
    );
    tensor(B::max_pool2x2(primitive(x)).output)
}

/// `leaky_relu(norm.forward(x), slope)`. When the backend tracks gradients (training), one fused operation with
/// batch statistics that also updates the running statistics exactly as Burn's `BatchNorm` does; otherwise
/// (inference) Burn's own running-statistics path.
pub fn batch_norm_leaky_relu<B: TrainOps>(
    norm: &BatchNorm<B>,
    x: Tensor<B, 4>,
    slope: f64,
) -> Tensor<B, 4> {
    let device = x.device();
    if !B::ad_enabled(&device) {
        return tensor(B::batch_norm_leaky_relu_inference(
            primitive(x),
            primitive(norm.gamma.val()),
            primitive(norm.beta.val()),
            primitive(norm.running_mean.value().to_device(&device)),
            primitive(norm.running_var.value().to_device(&device)),
            norm.epsilon,
            slope,
        ));
    }
    let out = B::batch_norm_leaky_relu(
        primitive(x),
        primitive(norm.gamma.val()),
        primitive(norm.beta.val()),
        norm.epsilon,
        slope,
    );
    let m = norm.momentum;
    let update = |state: &burn::module::RunningState<Tensor<B, 1>>, batch: FloatTensor<B>| {
        let batch = tensor::<B, 1>(batch).detach();
        let running = state.value_sync().to_device(&device);
        state.update(
            running
                .mul_scalar(1.0 - m)
                .add(batch.mul_scalar(m))
                .detach(),
        );
    };
    update(&norm.running_mean, out.mean);
    update(&norm.running_var, out.var);
    tensor(out.output)
}

#[cfg(test)]
mod tests;

//! [`TrainOps`] for the CubeCL backends (CUDA, wgpu): the convolutions' weight gradients as matrix products and
//! their input gradients as forward convolutions ([`conv`]), every other operation the stock one
//! ([`super::stock`]), each timed with the device synced when profiling is on.
//!
//! Why: without autotune, burn-cubecl 0.21 computes a convolution's weight gradient as a direct convolution of the
//! input by the output gradient over swapped dims, a convolution whose kernel is the whole 128 × 128 feature map.
//! Its output (`C_out × C_in × 3 × 3`) is a few thousand values, so a few thousand GPU threads each run a serial
//! sum of `N · H · W` products: on an H200 that made the backward 78 % of a step and the trainer 0.05–0.09×
//! PyTorch (`docs/performance.md`, GPU). [`conv::conv2d_weight_grad`] builds the im2col matrix of the padded input
//! instead, splits the long `N · H · W` reduction into pieces of whole rows, multiplies each piece as one batch of
//! a batched matmul (CubeCL's tiled matmul) and sums the pieces: the same math, with parallelism over the pieces
//! and the matmul's tiles. Autotune, which would find Burn 0.22's im2col kernels, is not needed (and took over 20 s
//! a shape on the H200). The input gradient, a direct transposed convolution in burn-cubecl, becomes the forward
//! convolution of the output gradient by the turned kernel ([`conv::conv2d_x_grad`]).
//!
//! [`set_conv_backward`] switches back to the stock kernels at run time, so `bench --compare-conv-backward` can
//! time both in one process.

pub mod conv;

use std::sync::atomic::{AtomicBool, Ordering};

/// Which convolution gradient kernels (weight and input) the CubeCL backends run.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ConvBackward {
    /// Weight gradients as im2col + batched matmul over pieces of the reduction, input gradients as forward
    /// convolutions ([`conv`]).
    Gemm,
    /// burn-cubecl's own without autotune: a direct convolution with a feature-map-sized kernel for the weight
    /// gradient, a direct transposed convolution for the input gradient.
    Stock,
}

impl ConvBackward {
    pub fn name(self) -> &'static str {
        match self {
            Self::Gemm => "gemm",
            Self::Stock => "stock",
        }
    }
}

static STOCK: AtomicBool = AtomicBool::new(false);

/// Choose the convolution gradient kernels of every CubeCL backend in this process (default [`ConvBackward::Gemm`]).
/// Flex has its own kernels and ignores it.
pub fn set_conv_backward(kind: ConvBackward) {
    STOCK.store(kind == ConvBackward::Stock, Ordering::Relaxed);
}

/// The kernel [`set_conv_backward`] chose.
pub fn conv_backward() -> ConvBackward {
    if STOCK.load(Ordering::Relaxed) {
        ConvBackward::Stock
    } else {
        ConvBackward::Gemm
    }
}

/// `impl TrainOps for $backend`: the convolution gradients through [`conv`] (unless switched to stock), the rest
/// stock, each call timed with the device synced while [`super::profile`] is on.
macro_rules! cubecl_train_ops {
    ($backend:ty) => {
        impl $crate::kernels::TrainOps for $backend {
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

            fn train_conv2d_x_grad(
                x: FloatTensor<Self>,
                weight: FloatTensor<Self>,
                output_grad: FloatTensor<Self>,
                options: ConvOptions<2>,
            ) -> FloatTensor<Self> {
                let device = Self::float_device(&x);
                timed_synced::<Self, _>(Kernel::ConvInputGrad, &device, || match conv_backward() {
                    ConvBackward::Gemm => {
                        conv::conv2d_x_grad::<Self>(x, weight, output_grad, options)
                    }
                    ConvBackward::Stock => Self::conv2d_x_backward(x, weight, output_grad, options),
                })
            }

            fn train_conv2d_weight_grad(
                x: FloatTensor<Self>,
                weight: FloatTensor<Self>,
                output_grad: FloatTensor<Self>,
                options: ConvOptions<2>,
            ) -> FloatTensor<Self> {
                let device = Self::float_device(&x);
                timed_synced::<Self, _>(Kernel::ConvWeightGrad, &device, || match conv_backward() {
                    ConvBackward::Gemm => {
                        conv::conv2d_weight_grad::<Self>(x, weight, output_grad, options)
                    }
                    ConvBackward::Stock => {
                        Self::conv2d_weight_backward(x, weight, output_grad, options)
                    }
                })
            }

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

            fn train_upsample_conv2d_x_grad(
                x: FloatTensor<Self>,
                weight: FloatTensor<Self>,
                output_grad: FloatTensor<Self>,
            ) -> FloatTensor<Self> {
                let device = Self::float_device(&x);
                timed_synced::<Self, _>(Kernel::UpConvInputGrad, &device, || {
                    match conv_backward() {
                        ConvBackward::Gemm => {
                            conv::upsample_conv2d_x_grad::<Self>(weight, output_grad)
                        }
                        ConvBackward::Stock => {
                            stock::upsample_conv2d_x_grad::<Self>(x, weight, output_grad)
                        }
                    }
                })
            }

            fn train_upsample_conv2d_weight_grad(
                x: FloatTensor<Self>,
                weight: FloatTensor<Self>,
                output_grad: FloatTensor<Self>,
            ) -> FloatTensor<Self> {
                let device = Self::float_device(&x);
                timed_synced::<Self, _>(Kernel::UpConvWeightGrad, &device, || {
                    match conv_backward() {
                        ConvBackward::Gemm => {
                            conv::upsample_conv2d_weight_grad::<Self>(x, weight, output_grad)
                        }
                        ConvBackward::Stock => {
                            stock::upsample_conv2d_weight_grad::<Self>(x, weight, output_grad)
                        }
                    }
                })
            }

            fn train_conv2d_bias_grad(output_grad: FloatTensor<Self>) -> FloatTensor<Self> {
                let device = Self::float_device(&output_grad);
                timed_synced::<Self, _>(Kernel::ConvBiasGrad, &device, || {
                    stock::channel_sums::<Self>(output_grad)
                })
            }

            fn dropout(x: FloatTensor<Self>, prob: f64) -> DropoutOutput<Self> {
                let device = Self::float_device(&x);
                timed_synced::<Self, _>(Kernel::DropoutForward, &device, || {
                    stock::dropout::<Self>(x, prob)
                })
            }

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

            fn max_pool2x2(x: FloatTensor<Self>) -> MaxPoolOutput<Self> {
                let device = Self::float_device(&x);
                timed_synced::<Self, _>(Kernel::PoolForward, &device, || {
                    stock::max_pool2x2::<Self>(x)
                })
            }

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

            fn render_masked_mse_backward(
                raw: FloatTensor<Self>,
                terms: FloatTensor<Self>,
                residual: FloatTensor<Self>,
                loss_grad: FloatTensor<Self>,
                slope: f64,
            ) -> FloatTensor<Self> {
                let device = Self::float_device(&raw);
                timed_synced::<Self, _>(Kernel::RenderLossBackward, &device, || {
                    stock::render_masked_mse_backward::<Self>(
                        raw, terms, residual, loss_grad, slope,
                    )
                })
            }

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

            fn batch_norm_leaky_relu_backward(
                x: FloatTensor<Self>,
                gamma: FloatTensor<Self>,
                _beta: FloatTensor<Self>,
                mean: FloatTensor<Self>,
                var: FloatTensor<Self>,
                output: FloatTensor<Self>,
                output_grad: FloatTensor<Self>,
                epsilon: f64,
                slope: f64,
            ) -> NormGrads<Self> {
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
    };
}

#[cfg(any(feature = "cuda", feature = "wgpu"))]
mod backends {
    use burn::tensor::ops::{ConvOptions, FloatTensor, FloatTensorOps, IntTensor, ModuleOps};

    use super::super::profile::{timed_synced, Kernel};
    use super::super::{stock, DropoutOutput, MaxPoolOutput, NormGrads, NormOutput, RenderLoss};
    use super::{conv, conv_backward, ConvBackward};

    #[cfg(feature = "cuda")]
    cubecl_train_ops!(burn::backend::Cuda);

    #[cfg(feature = "wgpu")]
    cubecl_train_ops!(burn::backend::Wgpu);
}

#[cfg(test)]
mod tests;

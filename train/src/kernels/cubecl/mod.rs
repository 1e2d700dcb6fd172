//! [`crate::kernels::TrainOps`] for the CubeCL backends (CUDA, wgpu): the convolutions' weight gradients as matrix products and
//! their input gradients as forward convolutions ([`conv`]); every other operation is the trait's default (stock
//! Burn operations, timed with the device synced when profiling is on).
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

/// `impl TrainOps for $backend`: the four convolution gradients through [`conv`] unless switched to stock, the
/// rest the trait's defaults.
#[cfg(any(feature = "cuda", feature = "wgpu"))]
macro_rules! cubecl_train_ops {
    ($backend:ty) => {
        impl TrainOps for $backend {
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
        }
    };
}

#[cfg(any(feature = "cuda", feature = "wgpu"))]
mod backends {
    use burn::tensor::ops::{ConvOptions, FloatTensor, FloatTensorOps, ModuleOps};

    use super::super::profile::{timed_synced, Kernel};
    use super::super::{stock, TrainOps};
    use super::{conv, conv_backward, ConvBackward};

    #[cfg(feature = "cuda")]
    cubecl_train_ops!(burn::backend::Cuda);

    #[cfg(feature = "wgpu")]
    cubecl_train_ops!(burn::backend::Wgpu);
}

#[cfg(test)]
mod tests;

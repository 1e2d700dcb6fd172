//! [`TrainOps`] for Flex (Burn's CPU backend): contiguous f32 `[N, C, H, W]` kernels, one file per operation,
//! each with its backward pass:
//! - [`conv`]: convolutions (stride 1, dilation 1, one group, symmetric zero padding: every convolution of the
//!   network) as per-sample im2col + `gemm`, parallel over the batch, in blocks of output rows whose im2col
//!   matrix fits in a core's cache: forward `Y = W·col(X) + b`, input gradient the same convolution of ∂Y with
//!   the kernel turned by 180° and its channel axes swapped, weight gradient `∂W = Σₙ ∂Yₙ·col(Xₙ)ᵀ`, bias
//!   gradient per-channel sums;
//! - [`upsample_conv`]: nearest ×2 then a 3×3 convolution, as four 2×2 convolutions on the coarse grid;
//! - [`batch_norm`]: BatchNorm + LeakyReLU, one pass for the statistics (per channel, f64 sums of x and x²)
//!   and one for the output, and the same two for the backward; in inference mode the output pass alone, from
//!   the running statistics;
//! - [`pool`], [`dropout`], [`join`] (LeakyReLU while concatenating a skip), [`render_loss`] (the renderer
//!   layer's masked squared error).
//!
//! Elementwise loops run in [`vectorized`]. Anything else (other dtypes, strides, groups) goes to the stock path
//! in [`super::stock`].

use burn::backend::Flex;
use burn::tensor::ops::{ConvOptions, FloatTensor, IntTensor, ModuleOps};
use burn::tensor::{DType, TensorData, TensorMetadata};
use burn_flex::FlexTensor;
use rayon::prelude::*;

use super::profile::{timed, Kernel};
use super::{stock, DropoutOutput, MaxPoolOutput, NormGrads, NormOutput, RenderLoss, TrainOps};

mod batch_norm;
mod conv;
pub(super) mod dropout;
mod join;
mod pool;
mod render_loss;
mod upsample_conv;

impl TrainOps for Flex {
    fn train_conv2d(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: Option<FloatTensor<Self>>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self> {
        timed(Kernel::ConvForward, || {
            conv::conv2d(x, weight, bias, options)
        })
    }

    fn train_conv2d_x_grad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        output_grad: FloatTensor<Self>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self> {
        timed(Kernel::ConvInputGrad, || {
            conv::conv2d_x_grad(x, weight, output_grad, options)
        })
    }

    fn train_conv2d_weight_grad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        output_grad: FloatTensor<Self>,
        options: ConvOptions<2>,
    ) -> FloatTensor<Self> {
        timed(Kernel::ConvWeightGrad, || {
            conv::conv2d_weight_grad(x, weight, output_grad, options)
        })
    }

    fn train_upsample_conv2d(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        bias: Option<FloatTensor<Self>>,
    ) -> FloatTensor<Self> {
        timed(Kernel::UpConvForward, || {
            upsample_conv::upsample_conv2d(x, weight, bias)
        })
    }

    fn train_upsample_conv2d_x_grad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        output_grad: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        timed(Kernel::UpConvInputGrad, || {
            upsample_conv::upsample_conv2d_x_grad(x, weight, output_grad)
        })
    }

    fn train_upsample_conv2d_weight_grad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        output_grad: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        timed(Kernel::UpConvWeightGrad, || {
            upsample_conv::upsample_conv2d_weight_grad(x, weight, output_grad)
        })
    }

    fn train_conv2d_bias_grad(output_grad: FloatTensor<Self>) -> FloatTensor<Self> {
        timed(Kernel::ConvBiasGrad, || conv::channel_sums(output_grad))
    }

    fn dropout(x: FloatTensor<Self>, prob: f64) -> DropoutOutput<Self> {
        timed(Kernel::DropoutForward, || dropout::dropout(x, prob))
    }

    fn dropout_backward(
        output_grad: FloatTensor<Self>,
        mask: FloatTensor<Self>,
        prob: f64,
    ) -> FloatTensor<Self> {
        timed(Kernel::DropoutBackward, || {
            dropout::dropout_backward(output_grad, mask, prob)
        })
    }

    fn max_pool2x2(x: FloatTensor<Self>) -> MaxPoolOutput<Self> {
        timed(Kernel::PoolForward, || pool::max_pool2x2(x))
    }

    fn max_pool2x2_backward(
        x: FloatTensor<Self>,
        output_grad: FloatTensor<Self>,
        argmax: IntTensor<Self>,
    ) -> FloatTensor<Self> {
        timed(Kernel::PoolBackward, || {
            pool::max_pool2x2_backward(x, output_grad, argmax)
        })
    }

    fn render_masked_mse(
        raw: FloatTensor<Self>,
        terms: FloatTensor<Self>,
        image: FloatTensor<Self>,
        valid: FloatTensor<Self>,
        slope: f64,
    ) -> RenderLoss<Self> {
        timed(Kernel::RenderLoss, || {
            render_loss::render_masked_mse(raw, terms, image, valid, slope)
        })
    }

    fn render_masked_mse_backward(
        raw: FloatTensor<Self>,
        terms: FloatTensor<Self>,
        residual: FloatTensor<Self>,
        loss_grad: FloatTensor<Self>,
        slope: f64,
    ) -> FloatTensor<Self> {
        timed(Kernel::RenderLossBackward, || {
            render_loss::render_masked_mse_backward(raw, terms, residual, loss_grad, slope)
        })
    }

    fn train_join_channels(
        a: FloatTensor<Self>,
        b: FloatTensor<Self>,
        slope: f64,
    ) -> FloatTensor<Self> {
        timed(Kernel::JoinChannels, || join::join_channels(a, b, slope))
    }

    fn train_join_channels_backward(
        a: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        slope: f64,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        timed(Kernel::JoinChannelsBackward, || {
            join::join_channels_backward(a, grad, slope)
        })
    }

    fn batch_norm_leaky_relu(
        x: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        epsilon: f64,
        slope: f64,
    ) -> NormOutput<Self> {
        timed(Kernel::NormForward, || {
            batch_norm::batch_norm_leaky_relu(x, gamma, beta, epsilon, slope)
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
        timed(Kernel::NormInference, || {
            batch_norm::batch_norm_leaky_relu_inference(x, gamma, beta, mean, var, epsilon, slope)
        })
    }

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
        timed(Kernel::NormBackward, || {
            batch_norm::batch_norm_leaky_relu_backward(
                x,
                gamma,
                beta,
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

/// `len` floats, chunk `i` (`chunk` elements, the last possibly fewer) written by `fill(i, chunk)` in parallel,
/// without zeroing them first: a kernel that overwrites its whole output paid a second pass over it for the zeros
/// (memset was 5 % of a train step's samples outside im2col).
///
/// # Safety
/// `fill` writes every element of the chunk it is given.
unsafe fn par_written(
    len: usize,
    chunk: usize,
    fill: impl Fn(usize, &mut [std::mem::MaybeUninit<f32>]) + Sync + Send,
) -> Vec<f32> {
    let mut out = Vec::with_capacity(len);
    out.spare_capacity_mut()[..len]
        .par_chunks_mut(chunk.max(1))
        .enumerate()
        .for_each(|(i, chunk)| fill(i, chunk));
    // SAFETY: the first `len` elements are initialised: the caller's `fill` wrote every chunk, and the chunks
    // cover `0..len`.
    unsafe { out.set_len(len) };
    out
}

fn from_vec(values: Vec<f32>, shape: &[usize]) -> FlexTensor {
    FlexTensor::from_data(TensorData::new(values, shape.to_vec()))
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

//! Wall time spent in each train-step kernel, summed over calls while profiling is on: the per-operation breakdown
//! `g2r-train bench` prints. Off by default (one relaxed atomic load per call). Flex runs synchronously, so a
//! wall-clock span there is the operation's cost ([`timed`]); a GPU backend queues work and returns, so its spans
//! are taken with the device synced before and after ([`timed_synced`]), which costs the overlap of queued work
//! and makes the profiled step slower than an unprofiled one.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Instant;

/// The timed kernels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Kernel {
    ConvForward,
    ConvInputGrad,
    ConvWeightGrad,
    ConvBiasGrad,
    NormForward,
    NormBackward,
    /// Inference-mode BatchNorm + LeakyReLU (running statistics): validation, evaluation, inference.
    NormInference,
    PoolForward,
    PoolBackward,
    DropoutForward,
    DropoutBackward,
    /// The up path's nearest ×2 + 3×3 convolution (computed on the coarse grid).
    UpConvForward,
    UpConvInputGrad,
    UpConvWeightGrad,
    /// The up path's join (LeakyReLU of the up convolution's output, concatenated with the skip) and its backward
    /// (the gradient split, the first part through LeakyReLU's slope).
    JoinChannels,
    JoinChannelsBackward,
    /// The renderer layer's fused render + masked MSE, forward and backward.
    RenderLoss,
    RenderLossBackward,
}

impl Kernel {
    pub const ALL: [Kernel; 18] = [
        Kernel::ConvForward,
        Kernel::ConvInputGrad,
        Kernel::ConvWeightGrad,
        Kernel::ConvBiasGrad,
        Kernel::NormForward,
        Kernel::NormBackward,
        Kernel::NormInference,
        Kernel::PoolForward,
        Kernel::PoolBackward,
        Kernel::DropoutForward,
        Kernel::DropoutBackward,
        Kernel::UpConvForward,
        Kernel::UpConvInputGrad,
        Kernel::UpConvWeightGrad,
        Kernel::JoinChannels,
        Kernel::JoinChannelsBackward,
        Kernel::RenderLoss,
        Kernel::RenderLossBackward,
    ];
}

static ENABLED: AtomicBool = AtomicBool::new(false);
static NANOS: [AtomicU64; Kernel::ALL.len()] = [const { AtomicU64::new(0) }; Kernel::ALL.len()];
static CALLS: [AtomicU64; Kernel::ALL.len()] = [const { AtomicU64::new(0) }; Kernel::ALL.len()];

/// Run `f`, adding its wall time to `kernel`'s total when profiling is on.
pub fn timed<T>(kernel: Kernel, f: impl FnOnce() -> T) -> T {
    if !ENABLED.load(Ordering::Relaxed) {
        return f();
    }
    let start = Instant::now();
    let out = f();
    let k = kernel as usize;
    NANOS[k].fetch_add(start.elapsed().as_nanos() as u64, Ordering::Relaxed);
    CALLS[k].fetch_add(1, Ordering::Relaxed);
    out
}

/// [`timed`] for a backend that queues work: with profiling on, the device finishes what was queued before `f`
/// and what `f` queued, so the span is `f`'s device time (plus one sync's latency).
pub fn timed_synced<B: burn::tensor::backend::Backend, T>(
    kernel: Kernel,
    device: &B::Device,
    f: impl FnOnce() -> T,
) -> T {
    if !ENABLED.load(Ordering::Relaxed) {
        return f();
    }
    let sync = || B::sync(device).expect("the device finishes its queued work");
    sync();
    timed(kernel, || {
        let out = f();
        sync();
        out
    })
}

/// Zero the totals and switch profiling on or off.
pub fn reset(enabled: bool) {
    for k in 0..Kernel::ALL.len() {
        NANOS[k].store(0, Ordering::Relaxed);
        CALLS[k].store(0, Ordering::Relaxed);
    }
    ENABLED.store(enabled, Ordering::Relaxed);
}

/// One kernel's total since the last [`reset`].
#[derive(Debug, Clone, serde::Serialize)]
pub struct KernelTime {
    pub kernel: Kernel,
    pub calls: u64,
    pub ms: f64,
}

/// Totals since the last [`reset`], in [`Kernel::ALL`] order.
pub fn totals() -> Vec<KernelTime> {
    Kernel::ALL
        .iter()
        .map(|&kernel| KernelTime {
            kernel,
            calls: CALLS[kernel as usize].load(Ordering::Relaxed),
            ms: NANOS[kernel as usize].load(Ordering::Relaxed) as f64 * 1e-6,
        })
        .collect()
}

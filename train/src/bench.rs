//! Throughput of the train step (U-Net + renderer layer, forward + backward + Adam) and of the renderer layer
//! alone (forward + backward w.r.t. the parameter maps), on synthetic crops so no dataset is needed.

use std::time::Instant;

use burn::optim::{AdamConfig, GradientsParams, Optimizer};
use burn::prelude::*;
use dataset::contract::schema::CROP_PX;
use dataset::science::brdf::BrdfModel;

use crate::kernels::TrainBackend;
use crate::model::UNetConfig;
use crate::renderer_layer::{render_loss, SceneTerms};
use crate::synthetic::synthetic_batch;
use crate::training::train_loss;

#[derive(Debug, Clone, serde::Serialize)]
pub struct BenchReport {
    pub backend: String,
    pub batch: usize,
    pub base_width: usize,
    pub model: String,
    /// Trainable U-Net weights (Burn's `num_params` minus BatchNorm running stats).
    pub trainable_params: usize,
    pub train_step_samples_per_s: f64,
    pub train_step_ms: f64,
    pub layer_samples_per_s: f64,
    pub layer_ms: f64,
    /// Of `layer_ms`: the scene terms, evaluated on the host and uploaded ([`SceneTerms::from_host`]).
    pub layer_terms_ms: f64,
    /// The train step's phases, ms per step: network + renderer + loss forward, backward, Adam.
    pub forward_ms: f64,
    pub backward_ms: f64,
    pub optimizer_ms: f64,
    /// The CubeCL backends' convolution gradient kernels in force (Flex runs its own whatever it says).
    pub conv_backward: &'static str,
    /// Time per step inside each kernel (forward and backward), from separate profiled steps after the timed ones:
    /// on a GPU each kernel is timed with the device synced around it, so these steps run slower than the timed.
    pub kernels: Vec<crate::kernels::profile::KernelTime>,
}

/// Time `iters` steps after one warm-up step.
pub fn bench<B: TrainBackend>(
    backend_name: &str,
    model: BrdfModel,
    batch_size: usize,
    base_width: usize,
    iters: usize,
    device: &B::Device,
) -> BenchReport {
    let batch = synthetic_batch(batch_size, 7);
    B::seed(device, 7);
    let config = UNetConfig::new(model.param_count()).with_base_width(base_width);
    let mut net = config.init::<B>(device);
    let trainable_params = crate::training::trainable_params(&net, &config);
    let mut optim = AdamConfig::new()
        .with_epsilon(1e-8)
        .init::<B, crate::model::UNet<B>>();
    // Forward, backward and optimizer phases timed apart; kernel totals from `kernels::profile`.
    let mut phases = [0.0f64; 3];
    // A GPU backend queues work and returns: each phase ends with a sync so that its time is the device's, not
    // the enqueue's (a no-op on the CPU backend). A fit reads the loss every step, which syncs as often.
    let sync = || B::sync(device).expect("the device finishes its queued work");
    let mut step = |net: crate::model::UNet<B>, phases: &mut [f64; 3]| {
        let t = Instant::now();
        let loss = train_loss(&net, model, &batch, device);
        sync();
        let t_forward = t.elapsed().as_secs_f64();
        let grads = GradientsParams::from_grads(loss.backward(), &net);
        sync();
        let t_backward = t.elapsed().as_secs_f64();
        let net = optim.step(1e-4, net, grads);
        sync();
        let t_step = t.elapsed().as_secs_f64();
        for (total, span) in
            phases
                .iter_mut()
                .zip([t_forward, t_backward - t_forward, t_step - t_backward])
        {
            *total += span;
        }
        net
    };
    net = step(net, &mut [0.0; 3]);
    let t = Instant::now();
    for _ in 0..iters {
        net = step(net, &mut phases);
    }
    let train_s = t.elapsed().as_secs_f64() / iters as f64;
    crate::kernels::profile::reset(true);
    for _ in 0..iters {
        net = step(net, &mut [0.0; 3]);
    }
    let kernels = crate::kernels::profile::totals()
        .into_iter()
        .map(|mut k| {
            k.ms /= iters as f64;
            k.calls /= iters as u64;
            k
        })
        .collect();
    crate::kernels::profile::reset(false);
    let [forward_ms, backward_ms, optimizer_ms] = phases.map(|s| s * 1e3 / iters as f64);

    // Layer alone: geometry + render + loss, backward to the parameter maps.
    let n = batch.len();
    let params_data = TensorData::new(
        vec![0.1f64; n * model.param_count() * CROP_PX * CROP_PX],
        [n, model.param_count(), CROP_PX, CROP_PX],
    );
    let image = Tensor::<B, 4>::from_data(
        TensorData::new(batch.image.clone(), [n, 1, CROP_PX, CROP_PX]),
        device,
    );
    let terms_s = std::cell::Cell::new(0.0f64);
    let layer = || {
        let params = Tensor::<B, 4>::from_data(params_data.clone(), device).require_grad();
        let t = Instant::now();
        let scene = SceneTerms::<B>::from_host(&batch, model, device);
        terms_s.set(terms_s.get() + t.elapsed().as_secs_f64());
        let loss = render_loss(params.clone(), &scene, image.clone());
        let grads = loss.backward();
        params
            .grad(&grads)
            .expect("parameter maps get a gradient")
            .into_data()
    };
    layer();
    terms_s.set(0.0);
    let t = Instant::now();
    for _ in 0..iters {
        layer();
    }
    let layer_s = t.elapsed().as_secs_f64() / iters as f64;
    let layer_terms_ms = terms_s.get() * 1e3 / iters as f64;
    BenchReport {
        backend: backend_name.to_string(),
        batch: batch_size,
        base_width,
        model: model.name().to_string(),
        trainable_params,
        train_step_samples_per_s: batch_size as f64 / train_s,
        train_step_ms: train_s * 1e3,
        layer_samples_per_s: batch_size as f64 / layer_s,
        layer_ms: layer_s * 1e3,
        layer_terms_ms,
        forward_ms,
        backward_ms,
        optimizer_ms,
        conv_backward: crate::kernels::cubecl::conv_backward().name(),
        kernels,
    }
}

/// One round of [`compare_conv_backward`]: the stock convolution gradients and the rewritten ones, back to back
/// (stock first in even rounds, the rewrites first in odd ones).
#[derive(Debug, Clone, serde::Serialize)]
pub struct ConvBackwardRound {
    pub stock_samples_per_s: f64,
    pub gemm_samples_per_s: f64,
    /// gemm / stock samples/s (> 1: the rewritten gradients make the step faster).
    pub ratio: f64,
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct ConvBackwardComparison {
    /// The last round's full reports (with their phase and kernel breakdowns).
    pub stock: BenchReport,
    pub gemm: BenchReport,
    pub rounds: Vec<ConvBackwardRound>,
    /// Median over rounds of gemm / stock samples/s.
    pub median_ratio: f64,
}

/// Alternate [`bench()`] with the stock and the rewritten convolution gradients ([`ConvBackward`]) `rounds`
/// times in one process, so both see the same machine state: the before and after of the CubeCL backends'
/// kernels. On Flex both arms run Flex's own kernels (a check of the bench's noise).
///
/// [`ConvBackward`]: crate::kernels::cubecl::ConvBackward
pub fn compare_conv_backward<B: TrainBackend>(
    backend_name: &str,
    model: BrdfModel,
    batch_size: usize,
    base_width: usize,
    iters: usize,
    rounds: usize,
    device: &B::Device,
) -> ConvBackwardComparison {
    use crate::kernels::cubecl::{conv_backward, set_conv_backward, ConvBackward};
    let chosen = conv_backward();
    let mut results = Vec::new();
    let mut last = None;
    for round in 0..rounds.max(1) {
        let run = |kind| {
            set_conv_backward(kind);
            bench::<B>(backend_name, model, batch_size, base_width, iters, device)
        };
        // Which side goes first alternates, so neither always meets the device warmer.
        let (stock, gemm) = if round.is_multiple_of(2) {
            let stock = run(ConvBackward::Stock);
            (stock, run(ConvBackward::Gemm))
        } else {
            let gemm = run(ConvBackward::Gemm);
            (run(ConvBackward::Stock), gemm)
        };
        results.push(ConvBackwardRound {
            stock_samples_per_s: stock.train_step_samples_per_s,
            gemm_samples_per_s: gemm.train_step_samples_per_s,
            ratio: gemm.train_step_samples_per_s / stock.train_step_samples_per_s,
        });
        last = Some((stock, gemm));
    }
    set_conv_backward(chosen);
    let (stock, gemm) = last.expect("at least one round");
    ConvBackwardComparison {
        stock,
        gemm,
        median_ratio: median(results.iter().map(|r| r.ratio)),
        rounds: results,
    }
}

/// The median (of an even count, the mean of the middle two).
fn median(values: impl Iterator<Item = f64>) -> f64 {
    let mut sorted: Vec<f64> = values.collect();
    sorted.sort_by(f64::total_cmp);
    let mid = sorted.len() / 2;
    if sorted.len().is_multiple_of(2) {
        (sorted[mid - 1] + sorted[mid]) / 2.0
    } else {
        sorted[mid]
    }
}

/// The PyTorch peer of the train step, carried in the binary so anyone can re-measure against it.
pub const TORCH_PEER: &str = include_str!("../bench/torch_peer.py");

/// One run of the PyTorch peer (its JSON line).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct TorchReport {
    pub torch: String,
    pub device: String,
    pub threads: usize,
    pub step_ms: f64,
    pub samples_per_s: f64,
}

/// Run the PyTorch peer with `python` at the bench's width and batch: `device` is `cpu` or `cuda`, `threads`
/// PyTorch's intra-op threads (the same count the Rust step uses).
pub fn run_torch_peer(
    python: &std::path::Path,
    width: usize,
    batch: usize,
    iters: usize,
    device: &str,
    threads: usize,
) -> anyhow::Result<TorchReport> {
    use anyhow::Context;
    let script = std::env::temp_dir().join(format!("g2r-torch-peer-{}.py", std::process::id()));
    std::fs::write(&script, TORCH_PEER)
        .with_context(|| format!("writing the PyTorch peer to {}", script.display()))?;
    let output = std::process::Command::new(python)
        .arg(&script)
        .args(["--width", &width.to_string(), "--batch", &batch.to_string()])
        .args(["--iters", &iters.to_string(), "--device", device])
        .args(["--threads", &threads.to_string()])
        .output();
    let _ = std::fs::remove_file(&script);
    let output = output.with_context(|| {
        format!(
            "running {}: give --torch a Python with torch installed \
             (python3 -m venv /tmp/torch-venv && /tmp/torch-venv/bin/pip install torch numpy)",
            python.display()
        )
    })?;
    let stdout = String::from_utf8_lossy(&output.stdout);
    let stderr = String::from_utf8_lossy(&output.stderr);
    anyhow::ensure!(
        output.status.success(),
        "the PyTorch peer failed under {} ({}): {}",
        python.display(),
        output.status,
        stderr.lines().last().unwrap_or("no message")
    );
    let line = stdout.lines().last().unwrap_or_default();
    serde_json::from_str(line)
        .with_context(|| format!("reading the PyTorch peer's report line {line:?}"))
}

/// One round of [`compare_with_torch`]: the peer, then this crate's step, back to back.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ComparisonRound {
    pub torch_samples_per_s: f64,
    pub g2r_samples_per_s: f64,
    /// g2r / PyTorch samples/s (≥ 1: as fast as the reference or faster).
    pub ratio: f64,
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct Comparison {
    pub torch: TorchReport,
    /// The last round's full report of this crate's step (with its breakdown).
    pub g2r: BenchReport,
    pub rounds: Vec<ComparisonRound>,
    /// Median over rounds of g2r / PyTorch samples/s.
    pub median_ratio: f64,
}

/// Alternate the PyTorch peer and [`bench()`] `rounds` times on the same machine (so both see the same machine
/// state) and report each round's samples/s and their ratio.
#[allow(clippy::too_many_arguments)]
pub fn compare_with_torch<B: TrainBackend>(
    python: &std::path::Path,
    backend_name: &str,
    torch_device: &str,
    batch_size: usize,
    base_width: usize,
    iters: usize,
    rounds: usize,
    device: &B::Device,
) -> anyhow::Result<Comparison> {
    let threads = rayon::current_num_threads();
    let mut results = Vec::new();
    let mut last = None;
    for _ in 0..rounds.max(1) {
        let torch = run_torch_peer(python, base_width, batch_size, iters, torch_device, threads)?;
        let g2r = bench::<B>(
            backend_name,
            BrdfModel::M2,
            batch_size,
            base_width,
            iters,
            device,
        );
        results.push(ComparisonRound {
            torch_samples_per_s: torch.samples_per_s,
            g2r_samples_per_s: g2r.train_step_samples_per_s,
            ratio: g2r.train_step_samples_per_s / torch.samples_per_s,
        });
        last = Some((torch, g2r));
    }
    let (torch, g2r) = last.expect("at least one round");
    Ok(Comparison {
        torch,
        g2r,
        median_ratio: median(results.iter().map(|r| r.ratio)),
        rounds: results,
    })
}

#[cfg(test)]
mod tests {
    #[test]
    fn median_of_odd_and_even_counts() {
        assert_eq!(super::median([3.0, 1.0, 2.0].into_iter()), 2.0);
        assert_eq!(super::median([4.0, 1.0, 3.0, 2.0].into_iter()), 2.5);
        assert_eq!(super::median([0.8].into_iter()), 0.8);
    }
}

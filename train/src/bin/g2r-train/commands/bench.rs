//! `g2r-train bench`.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use dataset::science::brdf::BrdfModel;
use train::backend::BackendKind;
use train::kernels::cubecl::ConvBackward;
use train::with_backend;

/// Samples/s of the train step (U-Net + renderer layer, forward + backward + Adam) and of the layer alone,
/// with the step's phases and per-kernel times; with --torch, alternately against the PyTorch peer.
#[derive(Args, Debug)]
#[command(
    long_about = "Samples/s of the train step (U-Net + renderer layer, forward + backward + Adam) on synthetic \
crops, its forward/backward/optimizer phases and the time inside each CPU kernel, and the renderer layer alone \
(scene terms + render + loss + backward). Prints JSON.\n\nWith --torch PYTHON, runs the PyTorch peer of the same \
step (carried in the binary; needs torch in that Python) and this step alternately for --rounds rounds, at the \
same width, batch and thread count, and prints each round's ratio and the median (g2r / PyTorch samples/s). \
Measure on an idle machine; compare only figures from the same sitting."
)]
pub struct BenchArgs {
    #[arg(long, default_value_t = 8)]
    pub batch: usize,
    #[arg(long, default_value_t = 16)]
    pub width: usize,
    #[arg(long, default_value = "m2")]
    pub model: BrdfModel,
    /// Timed steps per measurement (after one warm-up step).
    #[arg(long, default_value_t = 3)]
    pub iters: usize,
    #[arg(long, value_enum, default_value = "flex")]
    pub backend: BackendKind,
    /// A Python interpreter with torch: run the PyTorch peer alternately with this step (model m2).
    #[arg(long, value_name = "PYTHON", conflicts_with = "compare_conv_backward")]
    pub torch: Option<PathBuf>,
    /// The CubeCL backends' (cuda, wgpu) convolution gradients: `gemm`, weight gradients as im2col and batched
    /// matrix products over pieces of the reduction and input gradients as forward convolutions, or `stock`,
    /// Burn's own (direct kernels, the slow path this project replaced). Flex runs its own kernels either way.
    #[arg(long, value_enum, default_value = "gemm")]
    pub conv_backward: ConvBackward,
    /// Alternate `--conv-backward stock` and `gemm` in one process and report each round's samples/s and
    /// their ratio: the before and after of the rewritten gradients on this machine.
    #[arg(long)]
    pub compare_conv_backward: bool,
    /// Alternating rounds with --torch or --compare-conv-backward.
    #[arg(long, default_value_t = 3)]
    pub rounds: usize,
}

pub fn run(args: BenchArgs) -> Result<()> {
    let BenchArgs {
        batch,
        width,
        model,
        iters,
        backend,
        torch,
        conv_backward,
        compare_conv_backward,
        rounds,
    } = args;
    let (name, torch_device) = (backend.name(), backend.torch_device());
    train::kernels::cubecl::set_conv_backward(conv_backward);
    let measured = match torch {
        None if compare_conv_backward => {
            let comparison = with_backend!(backend, B => Ok::<_, anyhow::Error>(
                train::bench::compare_conv_backward::<B>(
                    name, model, batch, width, iters, rounds, &Default::default()
                )
            ))?;
            serde_json::to_value(&comparison)?
        }
        Some(python) => {
            anyhow::ensure!(
                model == BrdfModel::M2,
                "--torch compares the M2 step only: drop --model or use --model m2"
            );
            let comparison = with_backend!(backend, B => train::bench::compare_with_torch::<B>(
                &python, name, torch_device, batch, width, iters, rounds, &Default::default()
            ))?;
            serde_json::to_value(&comparison)?
        }
        None => {
            let report: train::bench::BenchReport = with_backend!(backend, B => Ok::<_, anyhow::Error>(
                train::bench::bench::<B>(name, model, batch, width, iters, &Default::default())
            ))?;
            serde_json::to_value(&report)?
        }
    };
    let provenance = dataset::provenance::Provenance::capture();
    let record = serde_json::json!({ "bench": measured, "provenance": provenance });
    dataset::outln!("{}", serde_json::to_string_pretty(&record)?);
    Ok(())
}

//! `g2r-train eval`.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use train::backend::Inner;
use train::data::open_source;
use train::with_backend;

use super::RunsArgs;

/// Evaluate a run on held-out tiles against the Hapke baselines, Lunar-Lambert and (with --world) the oracle;
/// writes metrics.json, metrics.md and PNG panels (GT | each method | |learned - GT|), and counts the crops whose
/// inputs lie outside the run's training range (input_range.json).
#[derive(Args, Debug)]
pub struct EvalArgs {
    #[command(flatten)]
    pub runs: RunsArgs,
    /// Dataset directory or server URL.
    #[arg(long)]
    pub data: String,
    #[arg(long, default_value = "test")]
    pub split: dataset::contract::schema::Split,
    /// Synthetic world directory: adds the oracle (its true Hapke maps). Only evaluation reads truth/.
    #[arg(long)]
    pub world: Option<PathBuf>,
    /// Output directory (default RUN/eval-SPLIT).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Images to evaluate, spread evenly over the split so every ortho and tile is represented (default: all).
    #[arg(long)]
    pub max_samples: Option<usize>,
    #[arg(long, default_value_t = 8)]
    pub batch: usize,
    /// Train crops (spread evenly over the split) used to fit the honest Hapke scale and Lunar-Lambert albedo.
    #[arg(long, default_value_t = 256)]
    pub calibration_samples: usize,
    /// PNG panels for the first N images.
    #[arg(long, default_value_t = 8)]
    pub panels: usize,
    /// Render "learned" as the mean of the network's 8 dihedral views: the terrain (and context window) turned
    /// and mirrored with its geometry, each parameter map turned back, the 8 renderings averaged. An 8-member
    /// ensemble from one network: its error is at most the members' mean; costs 8× network and renderer time.
    #[arg(long)]
    pub symmetry_mean: bool,
    /// Feed every crop as if the dataset had no crater catalogue: a --crater-frame-input run's crops unframed,
    /// and no crater level. Against the same eval without it, this is what the catalogue adds (or, with a
    /// catalogue listing craters that are not there, what it costs).
    #[arg(long)]
    pub without_crater_frames: bool,
    /// Feed each framed crop its crater's relief over diameter clamped into the run's training range
    /// (input_range.json): a crater fresher than any the run trained on is fed as the freshest it saw. Against
    /// the same eval without it, this is what the out-of-range relief costs.
    #[arg(long, conflicts_with = "without_crater_frames")]
    pub clamp_crater_relief: bool,
}

pub fn run(args: EvalArgs) -> Result<()> {
    let EvalArgs {
        runs,
        data,
        split,
        world,
        out,
        max_samples,
        batch,
        calibration_samples,
        panels,
        symmetry_mean,
        without_crater_frames,
        clamp_crater_relief,
    } = args;
    let source = open_source(&data)?;
    let out = out.unwrap_or_else(|| runs.run.join(format!("eval-{split}")));
    let paths = runs.paths();
    let job = train::evaluation::EvalJob {
        runs: &paths,
        checkpoint: runs.checkpoint,
        source: source.as_ref(),
        world: world.as_deref(),
        out: &out,
        options: train::evaluation::EvalOptions {
            split,
            max_samples,
            batch_size: batch.max(1),
            calibration_samples,
            panels,
            symmetry_mean,
            without_crater_frames,
            clamp_crater_relief,
        },
    };
    let report = with_backend!(runs.backend, B => {
        train::evaluation::run_job::<Inner<B>>(&job, &Default::default())
    })?;
    dataset::out!("{}", train::evaluation::markdown(&report));
    dataset::outln!(
        "\nwrote {}/metrics.json, metrics.md and panels/",
        out.display()
    );
    Ok(())
}

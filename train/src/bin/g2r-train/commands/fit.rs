//! `g2r-train fit`: one process, or one rank of a data-parallel fit.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::Result;
use clap::Args;
use dataset::science::brdf::BrdfModel;
use train::backend::RankDevice;
use train::crater_level_fit::CraterLevelOptions;
use train::data::SampleSource;
use train::fit_config::FitConfig;
use train::with_backend;

use super::training_args::{training_source, TrainArgs};

/// Train one model; writes config.json, metrics.jsonl (one line per epoch), best/ and last/ checkpoints.
#[derive(Args, Debug)]
pub struct FitArgs {
    /// Published dataset directory (contains manifest.json), the URL of `g2r-dataset serve`
    /// (http://127.0.0.1:8080), or an object-storage prefix it was uploaded to (s3://bucket/prefix, with AWS_*
    /// settings from the environment; `g2r-dataset upload`): all give the same batches.
    #[arg(long)]
    pub data: String,
    /// Run directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Continue the run in --out exactly where its last checkpoint stopped (same flags required).
    #[arg(long)]
    pub resume: bool,
    /// Stop after this many optimiser steps in total, leaving a resumable checkpoint.
    #[arg(long)]
    pub stop_after_steps: Option<u64>,
    /// When training has finished, fit the run's crater level on the same data, as `g2r-train crater-level
    /// --run OUT --data DATA` does (H1 runs on a dataset published with inputs.crater_catalogue): one command
    /// makes the whole shipped model.
    #[arg(long)]
    pub crater_level: bool,
    #[command(flatten)]
    pub training: TrainArgs,
}

pub fn run(args: FitArgs) -> Result<()> {
    let FitArgs {
        data,
        out,
        resume,
        stop_after_steps,
        crater_level,
        training,
    } = args;
    if crater_level && training.model != BrdfModel::H1 {
        anyhow::bail!(
            "--crater-level scales H1's one scale, but --model is {}: train with --model h1, or drop --crater-level",
            training.model.name()
        );
    }
    let (source, config) = training_source(&data, &training)?;
    let Some(outcome) = fit_as_rank(
        source.clone(),
        &config,
        &training,
        &out,
        resume,
        stop_after_steps,
    )?
    else {
        // Another rank of a data-parallel fit: the lead reports and fits the crater level.
        return Ok(());
    };
    // The crater level is fitted and written before anything is printed: a reader that stops early
    // (`| head`) ends the process at its first print, and must not cut the fit short.
    let crater_level_text = if !crater_level {
        String::new()
    } else if outcome.cursor.epoch < config.epochs {
        "training stopped before its last epoch: the crater level is fitted when it finishes (--resume --crater-level)\n".to_string()
    } else {
        let options = CraterLevelOptions {
            train_samples: None,
            val_samples: None,
            batch_size: 8,
        };
        let run = (
            out.as_path(),
            train::run_dir::Checkpoint::Auto,
            training.backend,
        );
        super::crater_level::fit_and_write(run, source.as_ref(), &options, None, None)?
    };
    dataset::outln!(
        "{}: {} steps, {} trainable parameters, {:.3} s/step; metrics in {}",
        out.display(),
        outcome.cursor.step,
        outcome.trainable_params,
        outcome.seconds_per_step,
        out.join("metrics.jsonl").display()
    );
    if let Some(last) = outcome.history.last() {
        dataset::outln!(
            "last epoch: val per-pixel MSE {:.4e}, PSNR {:.2} dB, SSIM {}",
            last.val_pixel_mse,
            last.val_psnr_db,
            train::metrics::ssim_text(last.val_ssim)
        );
    }
    dataset::out!("{crater_level_text}");
    Ok(())
}

/// Train as this process's rank ([`train::data_parallel::launch`]): the outcome, on the lead rank only.
fn fit_as_rank(
    source: Arc<dyn SampleSource>,
    config: &FitConfig,
    args: &TrainArgs,
    out: &Path,
    resume: bool,
    stop: Option<u64>,
) -> Result<Option<train::training::FitOutcome>> {
    let env = |name: &str| std::env::var(name).ok();
    let timeout = std::time::Duration::from_secs(args.collective_timeout);
    let ranks = train::data_parallel::launch(&env, timeout)?;
    let outcome = with_backend!(args.backend, B => {
        let device = <B as RankDevice>::rank_device(ranks.local_rank());
        train::training::fit_ranks::<B>(source, config, out, resume, stop, &device, &ranks, true)
    })
    .map_err(|e| ranks.end_on_error(e))?;
    Ok(ranks.leads().then_some(outcome))
}

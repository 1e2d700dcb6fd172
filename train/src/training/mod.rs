//! The fit loop: Adam (AdamW when the run asks for weight decay) on the masked MSE through the renderer layer,
//! metrics JSONL per epoch, best-val and last checkpoints, and exact resume.
//!
//! Exact resume rests on three things: (1) batches are a pure function of (seed, epoch, position)
//! ([`crate::data`]); (2) the backend RNG, which drives dropout, is re-seeded before every step from
//! (seed, step), so no RNG state needs saving; (3) the last checkpoint holds the model (with BatchNorm running
//! stats and parameter ids), the optimiser's state keyed by those ids, and the cursor (epoch, next batch, step).
//!
//! Files: `start` (a new run or a resumed one), `epochs` (a replica's steps, validation and checkpoints; one
//! replica alone, or one of [`crate::data_parallel`]'s ranks), `loss` (what a step minimises, and validation).

mod epochs;
mod loss;
mod start;

pub use loss::{train_loss, train_loss_with_terms, validate};
pub use start::{input_normalisation, ELEVATION_NORMALISATION_SAMPLES, UNIFORM_INIT_SAMPLES};

use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use burn::optim::{AdamConfig, AdamWConfig};
use burn::prelude::*;
use dataset::contract::schema::Split;

use crate::data::{steep_row_weights, SampleSource, STEEP_SLOPE_DEG};
use crate::data_parallel::Ranks;
use crate::fit_config::FitConfig;
use crate::kernels::TrainBackend;
use crate::model::{UNet, UNetConfig};
use crate::run_dir::{Cursor, EpochMetrics};

use epochs::{launch, ReplicaState, RunContext};

/// What a run ended with.
#[derive(Debug, Clone)]
pub struct FitOutcome {
    pub cursor: Cursor,
    pub history: Vec<EpochMetrics>,
    pub trainable_params: usize,
    /// Mean optimiser-step time in this run (forward + backward + Adam; excludes data waits, validation and
    /// checkpoints).
    pub seconds_per_step: f64,
}

/// Trainable weights (Burn's `num_params` also counts BatchNorm running stats).
pub fn trainable_params<B: Backend>(net: &UNet<B>, config: &UNetConfig) -> usize {
    net.num_params() - config.running_stat_count()
}

/// Train (or resume) into `out`. `stop_after_steps` ends the run early with a resumable last checkpoint
/// (used by the resume test and for wall-clock-bounded jobs). `show_progress` reports the steps
/// ([`dataset::progress`]: a bar on a terminal, log lines elsewhere); off, the run reports only its epochs.
pub fn fit<B: TrainBackend>(
    source: Arc<dyn SampleSource>,
    config: &FitConfig,
    out: &Path,
    resume: bool,
    stop_after_steps: Option<u64>,
    device: &B::Device,
    show_progress: bool,
) -> Result<FitOutcome> {
    fit_ranks::<B>(
        source,
        config,
        out,
        resume,
        stop_after_steps,
        device,
        &Ranks::alone(),
        show_progress,
    )
}

/// [`fit`] as one of `ranks.world()` data-parallel ranks ([`crate::data_parallel`]), each with
/// `config.stream.batch_size / ranks.world()` crops a step on its own `device`. Every rank calls this with the
/// same arguments; rank 0 alone writes into `out`, which every rank reads on `--resume` (a shared file system).
#[allow(clippy::too_many_arguments)]
pub fn fit_ranks<B: TrainBackend>(
    source: Arc<dyn SampleSource>,
    config: &FitConfig,
    out: &Path,
    resume: bool,
    stop_after_steps: Option<u64>,
    device: &B::Device,
    ranks: &Ranks,
    show_progress: bool,
) -> Result<FitOutcome> {
    if !config.stream.batch_size.is_multiple_of(ranks.world()) {
        bail!(
            "--batch {} does not split into {} ranks: choose a batch that the rank count divides",
            config.stream.batch_size,
            ranks.world()
        );
    }
    if config.crop_level && !config.elevation_input {
        bail!("the crop-level branch reads the absolute elevation plane: the run needs --elevation-input");
    }
    if config.film && !config.context_input {
        bail!("the decoder's modulation reads the context features: the run needs --context-input");
    }
    if ranks.leads() {
        std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    }
    let start::Start {
        net,
        cursor,
        history,
        input,
        average,
    } = start::start_or_resume::<B>(&*source, config, out, resume, device, ranks)?;
    input.check_dataset(&*source)?;
    let trainable = trainable_params(&net, &config.net_config());
    tracing::info!(
        model = config.model.name(),
        trainable_params = trainable,
        base_width = config.base_width,
        "U-Net ready"
    );

    // Steep-weighted epochs: every crop's weight from its slope, once per process (a pure function of the data,
    // so a resumed run draws what an uninterrupted one would).
    let row_weights: Option<Arc<[f64]>> = if config.steep_weight == 1.0 {
        None
    } else {
        if config.stream.max_samples.is_none() {
            bail!(
                "--steep-weight {} needs --max-train-samples: an epoch over every crop has nothing to weight",
                config.steep_weight
            );
        }
        let started = Instant::now();
        let weights = steep_row_weights(&*source, Split::Train, config.steep_weight)?;
        let steep = weights.iter().filter(|&&w| w != 1.0).count();
        tracing::info!(
            steep_crops = steep,
            crops = weights.len(),
            min_slope_deg = STEEP_SLOPE_DEG,
            weight = config.steep_weight,
            seconds = format!("{:.1}", started.elapsed().as_secs_f64()),
            "steep-weighted epochs"
        );
        Some(weights.into())
    };

    let run = RunContext {
        source,
        config: config.clone(),
        out: out.to_path_buf(),
        input,
        row_weights,
        stop_after_steps,
        show_progress,
        trainable,
    };
    // Adam's and AdamW's updates are different types (and different arithmetic even at zero decay), so the loop
    // is generic over the optimiser and a run without decay keeps Adam's exact steps.
    let state = ReplicaState {
        net,
        optim: (),
        cursor,
        history,
        average,
    };
    let adam_epsilon = 1e-8;
    match config.weight_decay {
        None => launch(
            run,
            state,
            AdamConfig::new()
                .with_epsilon(adam_epsilon)
                .init::<B, UNet<B>>(),
            resume,
            device,
            ranks,
        ),
        Some(decay) => launch(
            run,
            state,
            AdamWConfig::new()
                .with_epsilon(adam_epsilon)
                .with_weight_decay(decay as f32)
                .init::<B, UNet<B>>(),
            resume,
            device,
            ranks,
        ),
    }
}

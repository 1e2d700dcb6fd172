//! The fit loop: Adam (AdamW when the run asks for weight decay) on the masked MSE through the renderer layer,
//! metrics JSONL per epoch, best-val and last checkpoints, and exact resume.
//!
//! Exact resume rests on three things: (1) batches are a pure function of (seed, epoch, position)
//! ([`crate::data`]); (2) the backend RNG, which drives dropout, is re-seeded before every step from
//! (seed, step), so no RNG state needs saving; (3) the last checkpoint holds the model (with BatchNorm running
//! stats and parameter ids), the optimiser's state keyed by those ids, and the cursor (epoch, next batch, step).

use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use burn::module::AutodiffModule;
use burn::optim::{AdamConfig, AdamWConfig, GradientsParams, Optimizer};
use burn::prelude::*;
use burn::record::Recorder;
use dataset::contract::rng::keyed_u64;
use dataset::science::brdf::BrdfModel;

use crate::data::{
    crop_interior_m, ContextNormalisation, ElevationNormalisation, EpochStream, HostBatch,
    InputNormalisation, SampleSource, StreamConfig,
};
use crate::data::{for_each_sample_group, steep_row_weights, STEEP_SLOPE_DEG};
use crate::data_parallel::Ranks;
use crate::kernels::{TrainBackend, TrainOps};
use crate::metrics::{AggregateMetrics, MetricsAccumulator};
use crate::model::{UNet, UNetConfig};
use crate::renderer_layer::{render_loss, HostTerms, SceneTerms};
use dataset::contract::schema::{Split, CROP_PX};

use crate::fit_config::FitConfig;
use crate::prediction::{net_outputs, predict_images};
use crate::run_dir::{
    append_jsonl, read_history, read_json, run_input, save_last, save_model, write_json,
    Checkpoint, Cursor, EpochMetrics, Rec, RunNormalisation, ValMetrics,
};

/// Train crops the elevation input's mean and std are taken over (spread over the split).
pub const ELEVATION_NORMALISATION_SAMPLES: usize = 256;

/// The input normalisation a new run trains with: the manifest's train-split DEM std, plus absolute-elevation
/// statistics (`config.elevation_input`) and context statistics (`config.context_input`) over the same spread
/// train crops.
pub fn input_normalisation(
    source: &dyn SampleSource,
    config: &FitConfig,
) -> Result<InputNormalisation> {
    let mut input = InputNormalisation::relief(source.manifest().dem_std_m);
    if !(config.elevation_input || config.context_input) {
        return Ok(input);
    }
    let mut samples = Vec::new();
    for_each_sample_group(
        source,
        Split::Train,
        Some(ELEVATION_NORMALISATION_SAMPLES),
        "input normalisation",
        |group| samples.extend(group.iter().cloned()),
    )?;
    let on_train = || format!("{}: train split", source.describe());
    if config.elevation_input {
        let crops: Vec<Vec<f64>> = samples.iter().map(crop_interior_m).collect();
        input.elevation = Some(
            ElevationNormalisation::of_crops(crops.iter().map(Vec::as_slice))
                .with_context(on_train)?,
        );
    }
    if config.context_input {
        let context = ContextNormalisation::of_samples(&samples).with_context(on_train)?;
        if config.context_absolute && !config.elevation_input {
            bail!("an absolute context is normalised as the elevation plane: the run needs --elevation-input");
        }
        let crater_rms_m = config
            .crater_input
            .then(|| ContextNormalisation::crater_rms_of_samples(&samples).with_context(on_train))
            .transpose()?;
        input.context = Some(ContextNormalisation {
            absolute: config.context_absolute,
            crater_rms_m,
            ..context
        });
    }
    Ok(input)
}

/// Train crops the uniform head initialisation is fitted on.
pub const UNIFORM_INIT_SAMPLES: usize = 256;

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

/// One optimisation step's loss (masked MSE through the renderer layer).
pub fn train_loss<B: TrainBackend>(
    net: &UNet<B>,
    model: BrdfModel,
    batch: &HostBatch,
    device: &B::Device,
) -> Tensor<B, 1> {
    train_loss_with_terms(net, batch, &HostTerms::evaluate(batch, model), device)
}

/// [`train_loss`] with the batch's scene terms evaluated ahead (a fit's loader thread does).
pub fn train_loss_with_terms<B: TrainBackend>(
    net: &UNet<B>,
    batch: &HostBatch,
    terms: &HostTerms,
    device: &B::Device,
) -> Tensor<B, 1> {
    let scene = SceneTerms::<B>::upload(terms, batch, device);
    let image = Tensor::<B, 4>::from_data(
        TensorData::new(batch.image.clone(), [batch.len(), 1, 128, 128]),
        device,
    );
    render_loss(net_outputs(net, batch, device), &scene, image)
}

/// Validation over (up to `max`, spread evenly over the split) val samples, in inference mode, one row group in memory at a time.
pub fn validate<B: TrainOps>(
    net: &UNet<B>,
    model: BrdfModel,
    input: &InputNormalisation,
    source: &dyn SampleSource,
    max: Option<usize>,
    batch_size: usize,
    device: &B::Device,
) -> Result<AggregateMetrics> {
    input.check_dataset(source)?;
    let mut metrics = MetricsAccumulator::default();
    for_each_sample_group(source, Split::Val, max, "validate", |samples| {
        for chunk in samples.chunks(batch_size) {
            let batch = HostBatch::from_samples(chunk, input);
            let rendered = predict_images(net, model, &batch, device);
            let px = CROP_PX * CROP_PX;
            for i in 0..batch.len() {
                let range = i * px..(i + 1) * px;
                let valid: Vec<bool> = batch.valid[range.clone()]
                    .iter()
                    .map(|&v| v > 0.0)
                    .collect();
                metrics.add(
                    &rendered[range.clone()],
                    &batch.image[range],
                    &valid,
                    CROP_PX,
                );
            }
        }
    })?;
    Ok(metrics.finish())
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
    let config_path = out.join("config.json");
    let last = out.join("last");
    let net_config = config.net_config();
    let recorder = Rec::new();
    let seed = config.stream.seed;

    let (net, cursor, history, input, average) = if resume {
        let saved: FitConfig = read_json(&config_path)?;
        if saved.model != config.model {
            bail!(
                "{}: checkpoint is for BRDF model {} but --model {} was given: resume with --model {} or use a new --out",
                config_path.display(),
                saved.model.name(),
                config.model.name(),
                saved.model.name()
            );
        }
        if saved != *config {
            bail!(
                "{}: the run was started with other settings ({}); resume with the same flags or use a new --out",
                config_path.display(),
                saved.differences(config).join(", ")
            );
        }
        let cursor: Cursor = read_json(&last.join("cursor.json"))?;
        let net = net_config
            .init::<B>(device)
            .load_file(last.join("model"), &recorder, device)
            .with_context(|| format!("{}: cannot load the model checkpoint", last.display()))?;
        let history = read_history(&out.join("metrics.jsonl"))?;
        // Checked against the config: a resumed run must feed the network the planes it started with.
        let input = run_input(out, config)?;
        let average = match config.ema_decay {
            None => None,
            Some(_) => Some(
                net_config
                    .init::<B::InnerBackend>(device)
                    .load_file(last.join("ema"), &recorder, device)
                    .with_context(|| {
                        format!("{}: cannot load the weight average", last.display())
                    })?,
            ),
        };
        (net, cursor, history, input, average)
    } else {
        if last.exists() {
            bail!(
                "{}: already holds a run: pass --resume to continue it, or choose a new --out",
                out.display()
            );
        }
        // What evaluation and inference on a new DEM need from the training data: the input normalisation (a
        // pure function of the data, so every rank computes the same).
        let input = input_normalisation(&*source, config)?;
        if ranks.leads() {
            // Leftovers of a run that died before its first checkpoint would mix into this one's history.
            let _ = std::fs::remove_file(out.join("metrics.jsonl"));
            let _ = std::fs::remove_dir_all(out.join("best"));
            let _ = std::fs::remove_dir_all(out.join("ema-best"));
            write_json(&config_path, config)?;
            if let Some(e) = input.elevation {
                tracing::info!(mean_m = e.mean_m, std_m = e.std_m, "elevation input plane");
            }
            if let Some(c) = input.context {
                tracing::info!(gsd_m = c.gsd_m, std_m = c.std_m, "context input");
            }
            write_json(
                &out.join("normalisation.json"),
                &RunNormalisation {
                    input,
                    dataset: source.manifest().name.clone(),
                },
            )?;
        }
        B::seed(device, keyed_u64(seed, "init", 0));
        let net = net_config.init::<B>(device);
        let _ = net.num_params(); // materialise the lazily initialised weights now, in a fixed order
        let fit = crate::uniform_fit::calibrate(&*source, UNIFORM_INIT_SAMPLES, config.model)?;
        let start = if config.nonnegative_start {
            &fit.model_uniform_nonnegative
        } else {
            &fit.model_uniform
        };
        tracing::info!(coefficients = ?start, nonnegative = config.nonnegative_start, samples = fit.samples, "head = uniform fit");
        let raw: Vec<f64> = start
            .iter()
            .map(|&c| dataset::science::brdf::inverse_leaky_relu(c))
            .collect();
        let net = net.with_uniform_head(&raw, device);
        let average = config.ema_decay.map(|_| net.valid());
        (net, Cursor::start(), Vec::new(), input, average)
    };
    input.check_dataset(&*source)?;
    let trainable = trainable_params(&net, &net_config);
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

/// Give the rank its optimiser (its saved state when resuming) and train.
fn launch<B: TrainBackend, O: FitOptimizer<B>>(
    run: RunContext,
    state: ReplicaState<B, ()>,
    optim: O,
    resume: bool,
    device: &B::Device,
    ranks: &Ranks,
) -> Result<FitOutcome> {
    let optim = if resume {
        let last = run.out.join("last");
        optim.load_record(
            Rec::new()
                .load(last.join("optim"), device)
                .with_context(|| format!("{}: cannot load the optimizer state", last.display()))?,
        )
    } else {
        optim
    };
    let state = ReplicaState {
        net: state.net,
        optim,
        cursor: state.cursor,
        history: state.history,
        average: state.average,
    };
    train_rank::<B, O>(&run, state, ranks, device)
}

/// What a fit steps with: Adam, or AdamW for a run with weight decay.
trait FitOptimizer<B: TrainBackend>: Optimizer<UNet<B>, B> + Clone + Send + 'static {}
impl<B: TrainBackend, O: Optimizer<UNet<B>, B> + Clone + Send + 'static> FitOptimizer<B> for O {}

/// What every replica of a fit shares.
struct RunContext {
    source: Arc<dyn SampleSource>,
    config: FitConfig,
    out: std::path::PathBuf,
    input: InputNormalisation,
    row_weights: Option<Arc<[f64]>>,
    stop_after_steps: Option<u64>,
    show_progress: bool,
    trainable: usize,
}

/// What each replica starts from: the same network, optimiser state and cursor on every one.
#[derive(Clone)]
struct ReplicaState<B: TrainBackend, O> {
    net: UNet<B>,
    optim: O,
    cursor: Cursor,
    history: Vec<EpochMetrics>,
    average: Option<UNet<B::InnerBackend>>,
}

/// One rank's epochs (the whole fit when it is the only one).
fn train_rank<B: TrainBackend, O: FitOptimizer<B>>(
    run: &RunContext,
    state: ReplicaState<B, O>,
    ranks: &Ranks,
    device: &B::Device,
) -> Result<FitOutcome> {
    let replica = ranks.replica();
    let RunContext {
        source,
        config,
        out,
        input,
        row_weights,
        stop_after_steps,
        show_progress,
        trainable,
    } = run;
    let (out, input, stop_after_steps, trainable) =
        (out.as_path(), *input, *stop_after_steps, *trainable);
    let show_progress = *show_progress && replica.leads();
    let ReplicaState {
        mut net,
        mut optim,
        mut cursor,
        mut history,
        mut average,
    } = state;
    let recorder = Rec::new();
    let seed = config.stream.seed;
    let last = out.join("last");
    // Time in optimiser steps only (not data waits, validation or checkpoints), for s/step figures.
    let mut step_time = StepTime::default();
    // The run's steps: a bar on a terminal, structured lines naming the rank in a scheduler's log file.
    let progress = if show_progress {
        let context = format!("rank={} world={}", replica.rank, replica.world);
        dataset::progress::Progress::start_in("fit", "steps", 0, &context)
    } else {
        dataset::progress::Progress::hidden()
    };
    progress.resume_at(cursor.step);
    while cursor.epoch < config.epochs {
        let epoch = cursor.epoch;
        let model = config.model;
        let stream = EpochStream::start(
            source.clone(),
            Split::Train,
            // Each replica takes its share of every step's crops.
            StreamConfig {
                batch_size: config.stream.batch_size / replica.world,
                ..config.stream
            },
            input,
            row_weights.clone(),
            epoch as u64,
            cursor.next_batch,
            replica,
            move |batch| {
                let terms = HostTerms::evaluate_serial(&batch, model);
                (batch, terms)
            },
        )?;
        let stream_batches = stream.batches;
        // Every epoch has the same batch count, so the run's length is known from the first stream.
        let total_steps = (config.epochs * stream_batches) as u64;
        progress.set_length(total_steps);
        for prepared in stream {
            let (batch, terms) = prepared?;
            // Dropout masks from (seed, step, rank): a resumed run draws exactly what an uninterrupted one would,
            // and each rank its own masks (rank 0 the masks of a one-rank run).
            B::seed(
                device,
                keyed_u64(seed, "dropout", cursor.step) ^ replica.rank as u64,
            );
            let step_started = Instant::now();
            let loss = train_loss_with_terms(&net, &batch, &terms, device);
            let loss_value: f64 = loss
                .clone()
                .into_data()
                .convert::<f64>()
                .to_vec::<f64>()
                .expect("f64")[0];
            // Every replica checks (and the lead logs) the mean over the replicas, so all stop together.
            let loss_value = ranks.mean_scalar(loss_value, "loss", cursor.step);
            if !loss_value.is_finite() {
                bail!(
                    "non-finite training loss at step {} (epoch {epoch}); lower --lr",
                    cursor.step
                );
            }
            let grads = ranks.mean_gradients(
                &net,
                GradientsParams::from_grads(loss.backward(), &net),
                cursor.step,
            )?;
            let rate = config
                .lr_schedule
                .rate(config.learning_rate, cursor.step, total_steps);
            net = optim.step(rate, net, grads);
            if let (Some(decay), Some(avg)) = (config.ema_decay, average.take()) {
                average = Some(crate::weight_average::ema_update(
                    avg,
                    &net.valid(),
                    crate::weight_average::ema_decay_at(decay, cursor.step),
                ));
            }
            step_time.add(step_started);
            cursor.step += 1;
            cursor.next_batch += 1;
            cursor.epoch_loss_sum += loss_value;
            cursor.epoch_batches += 1;
            progress.inc(1);
            let epoch_loss = cursor.epoch_loss_sum / cursor.epoch_batches as f64;
            progress.set_message(format!(
                "epoch {}/{} loss {epoch_loss:.3e}",
                epoch + 1,
                config.epochs
            ));
            if stop_after_steps.is_some_and(|s| cursor.step >= s) {
                let (net, average) = mean_running_stats(ranks, net, average, cursor.step);
                if replica.leads() {
                    save_last(&net, &optim, average.as_ref(), &cursor, &last, &recorder)?;
                }
                progress.set_message(format!("stopped at step {} (resumable)", cursor.step));
                ranks.barrier(EPOCH_END, cursor.step);
                return Ok(outcome(cursor, history, trainable, step_time));
            }
        }
        // Every rank's BatchNorm statistics averaged before validation; the lead alone validates and writes,
        // while the others wait for it.
        (net, average) = mean_running_stats(ranks, net, average, cursor.step);
        if !replica.leads() {
            cursor.next_epoch();
            ranks.barrier(EPOCH_END, cursor.step);
            continue;
        }
        let validate_net = |network: &UNet<B::InnerBackend>| {
            validate(
                network,
                config.model,
                &input,
                source.as_ref(),
                config.max_val_samples,
                config.stream.batch_size,
                device,
            )
        };
        let val = validate_net(&net.valid())?;
        let ema_val = average.as_ref().map(validate_net).transpose()?;
        let metrics = EpochMetrics {
            epoch,
            steps: cursor.step,
            train_loss: cursor.epoch_loss_sum / cursor.epoch_batches.max(1) as f64,
            val_loss: val.pixel_mse_pooled,
            val_pixel_mse: val.pixel_mse,
            val_psnr_db: val.psnr_db,
            val_ssim: val.ssim,
            val_images: val.images,
            ema_val: ema_val.as_ref().map(ValMetrics::from),
        };
        tracing::info!(?metrics, "epoch done");
        append_jsonl(&out.join("metrics.jsonl"), &metrics)?;
        history.push(metrics.clone());
        if cursor
            .best_val_loss
            .is_none_or(|b| val.pixel_mse_pooled < b)
        {
            cursor.best_val_loss = Some(val.pixel_mse_pooled);
            save_model(&net, &Checkpoint::Best.path(out), &recorder)?;
        }
        if let (Some(avg), Some(val)) = (&average, &ema_val) {
            if cursor
                .best_ema_val_loss
                .is_none_or(|b| val.pixel_mse_pooled < b)
            {
                cursor.best_ema_val_loss = Some(val.pixel_mse_pooled);
                save_model(avg, &Checkpoint::EmaBest.path(out), &recorder)?;
            }
        }
        cursor.next_epoch();
        save_last(&net, &optim, average.as_ref(), &cursor, &last, &recorder)?;
        ranks.barrier(EPOCH_END, cursor.step);
    }
    progress.finish();
    Ok(outcome(cursor, history, trainable, step_time))
}

/// The collective at which the other ranks wait for the lead's validation and checkpoint.
const EPOCH_END: &str = "epoch end (the lead validates and writes)";

/// The network's and the weight average's BatchNorm statistics averaged over the ranks (unchanged alone).
fn mean_running_stats<B: TrainBackend>(
    ranks: &Ranks,
    net: UNet<B>,
    average: Option<UNet<B::InnerBackend>>,
    step: u64,
) -> (UNet<B>, Option<UNet<B::InnerBackend>>) {
    if ranks.world() == 1 {
        return (net, average);
    }
    // Taking a record folds the last update into the statistics (Burn holds it apart until then).
    let _ = net.clone().into_record();
    let _ = average.clone().map(Module::into_record);
    let net = ranks.mean_running_stats(net, step);
    let average = average.map(|a| ranks.mean_running_stats(a, step));
    (net, average)
}

#[derive(Default)]
struct StepTime {
    seconds: f64,
    steps: u64,
}

impl StepTime {
    fn add(&mut self, started: Instant) {
        self.seconds += started.elapsed().as_secs_f64();
        self.steps += 1;
    }
}

fn outcome(
    cursor: Cursor,
    history: Vec<EpochMetrics>,
    trainable: usize,
    time: StepTime,
) -> FitOutcome {
    FitOutcome {
        cursor,
        history,
        trainable_params: trainable,
        seconds_per_step: time.seconds / time.steps.max(1) as f64,
    }
}

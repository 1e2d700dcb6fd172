//! The fit loop: Adam on the masked MSE through the renderer layer, metrics JSONL per epoch, best-val and last
//! checkpoints, and exact resume.
//!
//! Exact resume rests on three things: (1) batches are a pure function of (seed, epoch, position)
//! ([`crate::data`]); (2) the backend RNG, which drives dropout, is re-seeded before every step from
//! (seed, step), so no RNG state needs saving; (3) the last checkpoint holds the model (with BatchNorm running
//! stats and parameter ids), the Adam state keyed by those ids, and the cursor (epoch, next batch, step).

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use burn::module::AutodiffModule;
use burn::optim::{AdamConfig, GradientsParams, Optimizer};
use burn::prelude::*;
use burn::record::{FullPrecisionSettings, NamedMpkFileRecorder, Recorder};
use burn::tensor::backend::AutodiffBackend;
use dataset::brdf::BrdfModel;
use dataset::rng::keyed_u64;
use indicatif::{ProgressBar, ProgressStyle};

use crate::augment::Dihedral;
use crate::data::for_each_sample_group;
use crate::data::{
    crop_interior_m, ContextNormalisation, ElevationNormalisation, EpochStream, HostBatch,
    InputNormalisation, SampleSource, StreamConfig, CONTEXT_CHANNELS,
};
use crate::kernels::{TrainBackend, TrainOps};
use crate::metrics::{AggregateMetrics, MetricsAccumulator};
use crate::model::{UNet, UNetConfig};
use crate::render::{masked_mse, render, SceneTerms};
use dataset::schema::{Sample, CONTEXT_PX, CROP_PX};

/// Everything that defines a run (saved as `config.json`; a resume must match it).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FitConfig {
    pub model: BrdfModel,
    pub epochs: usize,
    pub learning_rate: f64,
    pub base_width: usize,
    pub dropout: bool,
    pub stream: StreamConfig,
    /// Cap on validation samples per epoch (`None` = the whole split).
    pub max_val_samples: Option<usize>,
    /// Learning rate over the run; runs written before this field existed were constant.
    #[serde(default)]
    pub lr_schedule: LrSchedule,
    /// How the head starts; runs written before this field existed started at zero.
    #[serde(default)]
    pub head_init: HeadInit,
    /// Feed absolute elevation as a second input plane ([`InputNormalisation`]); runs written before this field
    /// existed had relief only.
    #[serde(default)]
    pub elevation_input: bool,
    /// Feed each sample's wide context window through a context encoder ([`InputNormalisation`]); runs written
    /// before this field existed had none.
    #[serde(default)]
    pub context_input: bool,
    /// Keep an exponential moving average of the weights with this decay ([`crate::averaging`]), validated and
    /// checkpointed beside the raw network; `None` (and runs written before this field existed): no average.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ema_decay: Option<f64>,
}

impl FitConfig {
    /// The network this run trains.
    pub fn net_config(&self) -> UNetConfig {
        UNetConfig::new(self.model.param_count())
            .with_in_channels(1 + usize::from(self.elevation_input))
            .with_context_channels(if self.context_input {
                CONTEXT_CHANNELS
            } else {
                0
            })
            .with_base_width(self.base_width)
            .with_dropout(self.dropout)
    }
}

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
        "train",
        Some(ELEVATION_NORMALISATION_SAMPLES),
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
        input.context = Some(ContextNormalisation::of_samples(&samples).with_context(on_train)?);
    }
    Ok(input)
}

/// Where the network's output starts.
#[derive(
    Debug,
    Clone,
    Copy,
    Default,
    PartialEq,
    Eq,
    serde::Serialize,
    serde::Deserialize,
    clap::ValueEnum,
)]
#[serde(rename_all = "lowercase")]
pub enum HeadInit {
    /// Zero head: every parameter map starts at 0 (black renderings).
    #[default]
    Zero,
    /// Zero head weights, bias = the model's uniform least-squares fit on train crops: step 0 renders the honest
    /// uniform baseline, and training spends its steps on the spatial variation alone.
    Uniform,
}

/// Train crops the uniform head initialisation is fitted on.
pub const UNIFORM_INIT_SAMPLES: usize = 256;

/// How the learning rate changes over a run's optimiser steps.
#[derive(
    Debug,
    Clone,
    Copy,
    Default,
    PartialEq,
    Eq,
    serde::Serialize,
    serde::Deserialize,
    clap::ValueEnum,
)]
#[serde(rename_all = "lowercase")]
pub enum LrSchedule {
    /// `--lr` at every step.
    #[default]
    Constant,
    /// Half a cosine from `--lr` at step 0 to 0 at the last step.
    Cosine,
}

impl LrSchedule {
    /// The rate at optimiser step `step` of `total`.
    pub fn rate(self, base: f64, step: u64, total: u64) -> f64 {
        match self {
            Self::Constant => base,
            Self::Cosine => {
                let t = step.min(total) as f64 / total.max(1) as f64;
                base * 0.5 * (1.0 + (std::f64::consts::PI * t).cos())
            }
        }
    }
}

/// One line of `metrics.jsonl`.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EpochMetrics {
    pub epoch: usize,
    pub steps: u64,
    pub train_loss: f64,
    pub val_loss: f64,
    pub val_pixel_mse: f64,
    pub val_psnr_db: f64,
    /// `None` when no validation image has a fully valid 7×7 window.
    pub val_ssim: Option<f64>,
    pub val_images: usize,
    /// The weight average's validation (runs with `ema_decay`), same crops and metrics as the raw network's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ema_val: Option<ValMetrics>,
}

/// Validation metrics of one network at the end of an epoch.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ValMetrics {
    /// Pooled per-pixel MSE over all valid pixels (what `best` checkpoints are chosen on).
    pub loss: f64,
    pub pixel_mse: f64,
    pub psnr_db: f64,
    pub ssim: Option<f64>,
}

impl From<&AggregateMetrics> for ValMetrics {
    fn from(val: &AggregateMetrics) -> Self {
        Self {
            loss: val.pixel_mse_pooled,
            pixel_mse: val.pixel_mse,
            psnr_db: val.psnr_db,
            ssim: val.ssim,
        }
    }
}

/// Where the next step starts (saved with the last checkpoint).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Cursor {
    pub epoch: usize,
    pub next_batch: usize,
    pub step: u64,
    /// Sum and count of train losses so far in the current epoch (for its mean).
    pub epoch_loss_sum: f64,
    pub epoch_batches: usize,
    pub best_val_loss: Option<f64>,
    /// Best validation loss of the weight average so far (runs with `ema_decay`).
    #[serde(default)]
    pub best_ema_val_loss: Option<f64>,
}

impl Cursor {
    fn start() -> Self {
        Self {
            epoch: 0,
            next_batch: 0,
            step: 0,
            epoch_loss_sum: 0.0,
            epoch_batches: 0,
            best_val_loss: None,
            best_ema_val_loss: None,
        }
    }
}

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

type Rec = NamedMpkFileRecorder<FullPrecisionSettings>;

/// Trainable weights (Burn's `num_params` also counts BatchNorm running stats).
pub fn trainable_params<B: Backend>(net: &UNet<B>, config: &UNetConfig) -> usize {
    net.num_params() - config.running_stat_count()
}

/// The network's raw parameter maps for one host batch: `[N, P, 128, 128]` (the renderer applies the activation).
fn net_outputs<B: TrainOps>(net: &UNet<B>, batch: &HostBatch, device: &B::Device) -> Tensor<B, 4> {
    let input = Tensor::<B, 4>::from_data(
        TensorData::new(
            batch.net_input.clone(),
            [batch.len(), batch.input_channels, 128, 128],
        ),
        device,
    );
    let context = (!batch.context_input.is_empty()).then(|| {
        Tensor::<B, 4>::from_data(
            TensorData::new(
                batch.context_input.clone(),
                [batch.len(), CONTEXT_CHANNELS, CONTEXT_PX, CONTEXT_PX],
            ),
            device,
        )
    });
    net.forward(input, context)
}

/// Network → renderer for one host batch: the rendered image `[N, 1, 128, 128]` and the batch's scene terms.
fn render_batch<B: TrainOps>(
    net: &UNet<B>,
    model: BrdfModel,
    batch: &HostBatch,
    device: &B::Device,
) -> (Tensor<B, 4>, SceneTerms<B>) {
    let scene = SceneTerms::<B>::from_host(batch, model, device);
    (render(net_outputs(net, batch, device), &scene), scene)
}

/// One optimisation step's loss (masked MSE through the renderer layer).
pub fn train_loss<B: TrainBackend>(
    net: &UNet<B>,
    model: BrdfModel,
    batch: &HostBatch,
    device: &B::Device,
) -> Tensor<B, 1> {
    let (rendered, scene) = render_batch(net, model, batch, device);
    let image = Tensor::<B, 4>::from_data(
        TensorData::new(batch.image.clone(), [batch.len(), 1, 128, 128]),
        device,
    );
    masked_mse(rendered, image, scene.valid)
}

/// Render a batch with the network in inference mode (running BatchNorm stats, no dropout): `N × 128²` f64.
pub fn predict_images<B: TrainOps>(
    net: &UNet<B>,
    model: BrdfModel,
    batch: &HostBatch,
    device: &B::Device,
) -> Vec<f64> {
    render_batch(net, model, batch, device)
        .0
        .into_data()
        .convert::<f64>()
        .into_vec::<f64>()
        .expect("f64 after convert")
}

/// Render samples as the mean of the network's 8 dihedral views (test-time augmentation): the network sees each
/// turn and mirror of the terrain and context (with the geometry turned alike, as in training), its parameter maps
/// are turned back and rendered with the samples' own geometry, and the 8 renderings are averaged. The mean of
/// the renderings (not of the raw maps, which the activation would bend) makes this exactly an 8-member ensemble:
/// its squared error is at most the members' mean squared error, and the averaged predictor is equivariant under
/// the 8 symmetries, which a single pass of a trained network is only approximately. Cost: 8 network passes and 8
/// renders. `N × 128²` f64, as [`predict_images`].
pub fn predict_images_symmetry_mean<B: TrainOps>(
    net: &UNet<B>,
    model: BrdfModel,
    samples: &[Sample],
    input: &InputNormalisation,
    device: &B::Device,
) -> Vec<f64> {
    let batch = HostBatch::from_samples(samples, input);
    let scene = SceneTerms::<B>::from_host(&batch, model, device);
    let npx = CROP_PX * CROP_PX;
    let shape = [samples.len(), model.param_count(), CROP_PX, CROP_PX];
    let mut sum: Option<Tensor<B, 4>> = None;
    for d in Dihedral::all() {
        let turned: Vec<Sample> = samples.iter().map(|s| d.apply(s)).collect();
        let raw = net_outputs(net, &HostBatch::from_samples(&turned, input), device)
            .into_data()
            .convert::<f32>()
            .into_vec::<f32>()
            .expect("f32 after convert");
        let back = d.inverse();
        let raw_back: Vec<f32> = raw
            .chunks(npx)
            .flat_map(|plane| back.apply_raster(plane, CROP_PX))
            .collect();
        let raw_back = Tensor::<B, 4>::from_data(TensorData::new(raw_back, shape), device);
        let rendered = render(raw_back, &scene);
        sum = Some(match sum {
            None => rendered,
            Some(total) => total + rendered,
        });
    }
    (sum.expect("8 symmetries") / 8.0)
        .into_data()
        .convert::<f64>()
        .into_vec::<f64>()
        .expect("f64 after convert")
}

/// One trained run's renderings of `samples` in inference mode (`N × 128²` f64): a single pass, or with
/// `symmetry_mean` the mean of its 8 dihedral views ([`predict_images_symmetry_mean`]). Each run uses its own input
/// normalisation, so runs trained with different input planes can be compared or averaged.
pub fn predict_run<B: TrainOps>(
    run: &TrainedRun<B>,
    samples: &[Sample],
    symmetry_mean: bool,
    device: &B::Device,
) -> Vec<f64> {
    if symmetry_mean {
        predict_images_symmetry_mean(&run.net, run.config.model, samples, &run.input, device)
    } else {
        let batch = HostBatch::from_samples(samples, &run.input);
        predict_images(&run.net, run.config.model, &batch, device)
    }
}

/// The mean of several runs' renderings (a seed ensemble; one run returns its own rendering unchanged). Averaging
/// renderings, not parameters, makes this valid for any mix of BRDF models and input planes, and by convexity its
/// squared error on every image is at most the members' mean squared error. Cost: one network pass and one
/// render per member.
pub fn predict_ensemble<B: TrainOps>(
    runs: &[TrainedRun<B>],
    samples: &[Sample],
    symmetry_mean: bool,
    device: &B::Device,
) -> Vec<f64> {
    let mut runs = runs.iter();
    let first = runs.next().expect("an ensemble has at least one run");
    let mut sum = predict_run(first, samples, symmetry_mean, device);
    let mut members = 1.0;
    for run in runs {
        for (total, x) in sum
            .iter_mut()
            .zip(predict_run(run, samples, symmetry_mean, device))
        {
            *total += x;
        }
        members += 1.0;
    }
    if members > 1.0 {
        sum.iter_mut().for_each(|x| *x /= members);
    }
    sum
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
    for_each_sample_group(source, "val", max, |samples| {
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
/// (used by the resume test and for wall-clock-bounded jobs).
pub fn fit<B: TrainBackend>(
    source: Arc<dyn SampleSource>,
    config: &FitConfig,
    out: &Path,
    resume: bool,
    stop_after_steps: Option<u64>,
    device: &B::Device,
    show_progress: bool,
) -> Result<FitOutcome> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let config_path = out.join("config.json");
    let last = out.join("last");
    let net_config = config.net_config();
    let recorder = Rec::new();
    let seed = config.stream.seed;

    let (mut net, mut optim, mut cursor, mut history, input, mut average) = if resume {
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
                "{}: the run was started with different settings ({saved:?}); resume with the same flags or use a new --out",
                config_path.display()
            );
        }
        let cursor: Cursor = read_json(&last.join("cursor.json"))?;
        let net = net_config
            .init::<B>(device)
            .load_file(last.join("model"), &recorder, device)
            .with_context(|| format!("{}: cannot load the model checkpoint", last.display()))?;
        let optim =
            AdamConfig::new()
                .with_epsilon(1e-8)
                .init::<B, UNet<B>>()
                .load_record(recorder.load(last.join("optim"), device).with_context(|| {
                    format!("{}: cannot load the optimizer state", last.display())
                })?);
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
        (net, optim, cursor, history, input, average)
    } else {
        if last.exists() {
            bail!(
                "{}: already holds a run: pass --resume to continue it, or choose a new --out",
                out.display()
            );
        }
        // Leftovers of a run that died before its first checkpoint would mix into this one's history.
        let _ = std::fs::remove_file(out.join("metrics.jsonl"));
        let _ = std::fs::remove_dir_all(out.join("best"));
        let _ = std::fs::remove_dir_all(out.join("ema-best"));
        write_json(&config_path, config)?;
        // What evaluation and inference on a new DEM need from the training data: the input normalisation.
        let input = input_normalisation(&*source, config)?;
        if let Some(e) = input.elevation {
            tracing::info!(mean_m = e.mean_m, std_m = e.std_m, "elevation input plane");
        }
        if let Some(c) = input.context {
            tracing::info!(gsd_m = c.gsd_m, std_m = c.std_m, "context input");
        }
        write_json(
            &out.join("normalisation.json"),
            &Normalisation {
                input,
                dataset: source.manifest().name.clone(),
            },
        )?;
        B::seed(device, keyed_u64(seed, "init", 0));
        let mut net = net_config.init::<B>(device);
        let _ = net.num_params(); // materialise the lazily initialised weights now, in a fixed order
        if config.head_init == HeadInit::Uniform {
            let fit = crate::evaluation::calibrate(&*source, UNIFORM_INIT_SAMPLES, config.model)?;
            tracing::info!(coefficients = ?fit.model_uniform, samples = fit.samples, "head bias = uniform fit");
            let raw: Vec<f64> = fit
                .model_uniform
                .iter()
                .map(|&c| dataset::brdf::inverse_leaky_relu(c))
                .collect();
            net = net.with_head_bias(&raw, device);
        }
        let optim = AdamConfig::new().with_epsilon(1e-8).init::<B, UNet<B>>();
        let average = config.ema_decay.map(|_| net.valid());
        (net, optim, Cursor::start(), Vec::new(), input, average)
    };
    input.check_dataset(&*source)?;
    let trainable = trainable_params(&net, &net_config);
    tracing::info!(
        model = config.model.name(),
        trainable_params = trainable,
        base_width = config.base_width,
        "U-Net ready"
    );

    // Time in optimiser steps only (not data waits, validation or checkpoints), for s/step figures.
    let mut step_time = StepTime::default();
    while cursor.epoch < config.epochs {
        let epoch = cursor.epoch;
        let stream = EpochStream::start(
            source.clone(),
            "train",
            config.stream,
            input,
            epoch as u64,
            cursor.next_batch,
        )?;
        let stream_batches = stream.batches;
        let bar = if show_progress {
            ProgressBar::new(stream.batches as u64)
        } else {
            ProgressBar::hidden()
        };
        bar.set_style(
            ProgressStyle::with_template("epoch {prefix} [{bar:30}] {pos}/{len} {msg} ({eta})")
                .expect("valid template")
                .progress_chars("=> "),
        );
        bar.set_prefix(format!("{}/{}", epoch + 1, config.epochs));
        bar.set_position(cursor.next_batch as u64);
        for batch in stream {
            let batch = batch?;
            // Dropout masks from (seed, step): a resumed run draws exactly what an uninterrupted one would.
            B::seed(device, keyed_u64(seed, "dropout", cursor.step));
            let step_started = Instant::now();
            let loss = train_loss(&net, config.model, &batch, device);
            let loss_value: f64 = loss
                .clone()
                .into_data()
                .convert::<f64>()
                .to_vec::<f64>()
                .expect("f64")[0];
            if !loss_value.is_finite() {
                bail!(
                    "non-finite training loss at step {} (epoch {epoch}); lower --lr",
                    cursor.step
                );
            }
            let grads = GradientsParams::from_grads(loss.backward(), &net);
            // Every epoch has the same batch count, so the run's length is known from the first stream.
            let total_steps = (config.epochs * stream_batches) as u64;
            let rate = config
                .lr_schedule
                .rate(config.learning_rate, cursor.step, total_steps);
            net = optim.step(rate, net, grads);
            if let (Some(decay), Some(avg)) = (config.ema_decay, average.take()) {
                average = Some(crate::averaging::ema_update(
                    avg,
                    &net.valid(),
                    crate::averaging::ema_decay_at(decay, cursor.step),
                ));
            }
            step_time.add(step_started);
            cursor.step += 1;
            cursor.next_batch += 1;
            cursor.epoch_loss_sum += loss_value;
            cursor.epoch_batches += 1;
            bar.inc(1);
            bar.set_message(format!(
                "loss {:.3e}",
                cursor.epoch_loss_sum / cursor.epoch_batches as f64
            ));
            if stop_after_steps.is_some_and(|s| cursor.step >= s) {
                save_last(&net, &optim, average.as_ref(), &cursor, &last, &recorder)?;
                bar.abandon_with_message(format!("stopped at step {} (resumable)", cursor.step));
                return Ok(outcome(cursor, history, trainable, step_time));
            }
        }
        bar.finish();
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
        cursor.epoch += 1;
        cursor.next_batch = 0;
        cursor.epoch_loss_sum = 0.0;
        cursor.epoch_batches = 0;
        save_last(&net, &optim, average.as_ref(), &cursor, &last, &recorder)?;
    }
    Ok(outcome(cursor, history, trainable, step_time))
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

/// Write the last checkpoint into a temp directory, then swap it in: a killed save leaves the previous one intact.
fn save_last<B: AutodiffBackend, O: Optimizer<UNet<B>, B>>(
    net: &UNet<B>,
    optim: &O,
    average: Option<&UNet<B::InnerBackend>>,
    cursor: &Cursor,
    last: &Path,
    recorder: &Rec,
) -> Result<()> {
    let tmp = last.with_file_name("last.partial");
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp)?;
    }
    std::fs::create_dir_all(&tmp)?;
    net.clone()
        .save_file(tmp.join("model"), recorder)
        .context("saving the model")?;
    if let Some(average) = average {
        average
            .clone()
            .save_file(tmp.join("ema"), recorder)
            .context("saving the weight average")?;
    }
    recorder
        .record(optim.to_record(), tmp.join("optim"))
        .context("saving the optimizer state")?;
    write_json(&tmp.join("cursor.json"), cursor)?;
    let old = last.with_file_name("last.old");
    if last.exists() {
        std::fs::rename(last, &old)?;
    }
    std::fs::rename(&tmp, last)?;
    if old.exists() {
        std::fs::remove_dir_all(&old)?;
    }
    Ok(())
}

/// Save a network to `path` (without extension; the recorder adds `.mpk`), replacing an older checkpoint there.
fn save_model<B: Backend>(net: &UNet<B>, path: &Path, recorder: &Rec) -> Result<()> {
    // Remove first: the recorder warns when it replaces a file, which is the normal case here.
    let _ = std::fs::remove_file(path.with_extension("mpk"));
    net.clone()
        .save_file(path.to_path_buf(), recorder)
        .with_context(|| format!("saving the checkpoint {}", path.display()))?;
    Ok(())
}

fn write_json<T: serde::Serialize>(path: &Path, value: &T) -> Result<()> {
    dataset::manifest::write_json_atomic(path, value)
        .with_context(|| format!("writing {}", path.display()))
}

fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path).with_context(|| {
        format!(
            "{}: missing: is this a g2r-train run directory?",
            path.display()
        )
    })?;
    serde_json::from_str(&text).with_context(|| {
        format!(
            "{}: not valid JSON for this g2r-train version",
            path.display()
        )
    })
}

fn append_jsonl<T: serde::Serialize>(path: &Path, value: &T) -> Result<()> {
    let mut file = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .with_context(|| format!("opening {}", path.display()))?;
    writeln!(file, "{}", serde_json::to_string(value)?)?;
    Ok(())
}

fn read_history(path: &Path) -> Result<Vec<EpochMetrics>> {
    if !path.exists() {
        return Ok(Vec::new());
    }
    std::fs::read_to_string(path)?
        .lines()
        .map(|l| serde_json::from_str(l).with_context(|| format!("{}: bad line", path.display())))
        .collect()
}

/// The training data's input normalisation, saved with a run (`normalisation.json`).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Normalisation {
    /// How heights became the network's input.
    #[serde(flatten)]
    pub input: InputNormalisation,
    pub dataset: String,
}

/// A run's `normalisation.json`.
pub fn load_normalisation(run: &Path) -> Result<Normalisation> {
    read_json(&run.join("normalisation.json"))
}

/// The input normalisation a run's network was trained with, checked against its config (planes it expects).
pub fn run_input(run: &Path, config: &FitConfig) -> Result<InputNormalisation> {
    let input = load_normalisation(run)?.input;
    let net = config.net_config();
    if input.channels() != net.in_channels || input.context_channels() != net.context_channels {
        bail!(
            "{}: normalisation.json describes {} input plane(s) and {} context plane(s) but config.json a network with {} and {}: the run directory is inconsistent",
            run.display(),
            input.channels(),
            input.context_channels(),
            net.in_channels,
            net.context_channels
        );
    }
    Ok(input)
}

/// Which of a run's networks to load.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum Checkpoint {
    /// The weight average at the last checkpoint when the run kept one (`last/ema`), else `best`, else `last`.
    /// Not the average's best-validation epoch: on the demo's 152 val crops that pick often lands on epoch 0. The
    /// final average scored better on the demo test split for 4 of 5 seeds, and on an unseen world better for 3 of 4
    /// and within 0.5 % for the fourth (docs/results.md, "Weight average, five seeds").
    #[default]
    Auto,
    /// The raw network at its best validation epoch (`best/`).
    Best,
    /// The raw network at the last checkpoint (`last/`).
    Last,
    /// The weight average at its best validation epoch (`ema-best/`; runs with `--ema`).
    EmaBest,
    /// The weight average at the last checkpoint (`last/ema`; runs with `--ema`).
    EmaLast,
}

impl Checkpoint {
    /// The checkpoint's path in `run` (without the `.mpk` extension). For `Auto` this is only its first choice,
    /// `last/ema`: [`Checkpoint::resolve`] says what a given run actually loads.
    pub fn path(self, run: &Path) -> PathBuf {
        match self {
            Self::EmaBest => run.join("ema-best").join("model"),
            Self::Best => run.join("best").join("model"),
            Self::Last => run.join("last").join("model"),
            Self::Auto | Self::EmaLast => run.join("last").join("ema"),
        }
    }

    /// The checkpoint file to load from `run`: the one asked for, or for `Auto` the first that exists of
    /// `ema-last`, `best`, `last`.
    pub fn resolve(self, run: &Path) -> Result<PathBuf> {
        let candidates = match self {
            Self::Auto => vec![Self::EmaLast, Self::Best, Self::Last],
            other => vec![other],
        };
        candidates
            .iter()
            .map(|c| c.path(run))
            .find(|p| p.with_extension("mpk").exists())
            .with_context(|| match self {
                Self::Auto => format!(
                    "{}: no last/ema, best/ or last/ checkpoint: train first (g2r-train fit)",
                    run.display()
                ),
                other => format!(
                    "{}: no {}.mpk: that run has no {} checkpoint (`--checkpoint ema-*` needs a run trained with --ema); omit --checkpoint to take what it has",
                    run.display(),
                    other.path(run).display(),
                    clap::ValueEnum::to_possible_value(&other)
                        .map(|v| v.get_name().to_owned())
                        .unwrap_or_default()
                ),
            })
    }
}

/// A trained run, loaded for evaluation or inference.
pub struct TrainedRun<B: Backend> {
    pub config: FitConfig,
    /// How heights become the network's input (`normalisation.json`).
    pub input: InputNormalisation,
    pub net: UNet<B>,
    /// The checkpoint file the network came from, relative to the run directory (e.g. `ema-best/model.mpk`).
    pub checkpoint: String,
}

/// A finished (or interrupted) run's config, input normalisation and network in inference mode, from the chosen
/// checkpoint ([`Checkpoint::Auto`]: the last weight average, else the best-val network, else the last one
/// when no validation has run yet).
pub fn load_trained<B: Backend>(
    run: &Path,
    checkpoint: Checkpoint,
    device: &B::Device,
) -> Result<TrainedRun<B>> {
    let config_path = run.join("config.json");
    if !config_path.exists() {
        bail!(
            "{}: no config.json: point --run (and --ensemble) at directories written by `g2r-train fit --out`",
            run.display()
        );
    }
    let config: FitConfig = read_json(&config_path)?;
    let checkpoint = checkpoint.resolve(run)?;
    let net = config
        .net_config()
        .init::<B>(device)
        .load_file(checkpoint.clone(), &Rec::new(), device)
        .with_context(|| format!("{}: cannot load the checkpoint", checkpoint.display()))?;
    let input = run_input(run, &config)?;
    let checkpoint = checkpoint
        .with_extension("mpk")
        .strip_prefix(run)
        .map(|p| p.display().to_string())
        .unwrap_or_else(|_| checkpoint.display().to_string());
    Ok(TrainedRun {
        config,
        input,
        net,
        checkpoint,
    })
}

/// Several runs loaded together (`--run` then each `--ensemble`), all before any work starts, so a mistyped member
/// or one of another BRDF model fails at once rather than after the earlier members' inference. Averaging
/// renderings (`eval`) works across models; averaging parameter maps (`infer`) needs `one_model`: the members'
/// maps must mean the same parameters.
pub fn load_ensemble<B: Backend>(
    runs: &[&Path],
    checkpoint: Checkpoint,
    one_model: bool,
    device: &B::Device,
) -> Result<Vec<TrainedRun<B>>> {
    let loaded = runs
        .iter()
        .map(|run| load_trained::<B>(run, checkpoint, device))
        .collect::<Result<Vec<_>>>()?;
    if one_model {
        let first = loaded
            .first()
            .context("an ensemble needs at least one run")?;
        for (run, member) in runs.iter().zip(&loaded).skip(1) {
            if member.config.model != first.config.model {
                bail!(
                    "{}: BRDF model {} but {} is {}: parameter maps average only within one BRDF model (eval --ensemble mixes models)",
                    run.display(),
                    member.config.model.name(),
                    runs[0].display(),
                    first.config.model.name()
                );
            }
        }
    }
    Ok(loaded)
}

#[cfg(test)]
mod schedule_tests {
    use super::*;

    #[test]
    fn cosine_decays_from_the_base_rate_to_zero_and_constant_stays() {
        let cosine = LrSchedule::Cosine;
        assert_eq!(cosine.rate(1e-3, 0, 100), 1e-3);
        assert!((cosine.rate(1e-3, 50, 100) - 5e-4).abs() < 1e-15);
        assert!(cosine.rate(1e-3, 100, 100).abs() < 1e-18);
        assert!(cosine.rate(1e-3, 25, 100) > cosine.rate(1e-3, 26, 100));
        assert_eq!(LrSchedule::Constant.rate(1e-3, 77, 100), 1e-3);
    }

    #[test]
    fn configs_written_before_the_schedule_existed_load_as_constant() {
        let json = r#"{"model":"m2","epochs":3,"learning_rate":0.001,"base_width":4,"dropout":true,
            "stream":{"seed":42,"batch_size":8,"window_groups":4,"augment":true,"max_samples":null},
            "max_val_samples":null}"#;
        let config: FitConfig = serde_json::from_str(json).unwrap();
        assert_eq!(config.lr_schedule, LrSchedule::Constant);
        assert_eq!(config.head_init, HeadInit::Zero);
    }
}

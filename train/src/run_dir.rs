//! A run directory: what defines a run (`config.json`: [`FitConfig`], versioned in [`crate::fit_config`]), its input normalisation
//! (`normalisation.json`) and range (`input_range.json`), its history (`metrics.jsonl`), its checkpoints
//! (`best/`, `ema-best/`, `last/` with the optimiser state and the resume [`Cursor`]), and loading trained runs for
//! `eval`, `infer` and `report`.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use burn::optim::Optimizer;
use burn::prelude::*;
use burn::record::{FullPrecisionSettings, NamedMpkFileRecorder, Recorder};
use burn::tensor::backend::AutodiffBackend;

use crate::data::{
    InputNormalisation, InputRange, SampleSource, INPUT_RANGE_FILE, INPUT_RANGE_SAMPLES,
};
use crate::fit_config::FitConfig;
use crate::metrics::AggregateMetrics;
use crate::model::UNet;

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
    /// Move to the first batch of the next epoch.
    pub(crate) fn next_epoch(&mut self) {
        self.epoch += 1;
        self.next_batch = 0;
        self.epoch_loss_sum = 0.0;
        self.epoch_batches = 0;
    }

    pub(crate) fn start() -> Self {
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

pub(crate) type Rec = NamedMpkFileRecorder<FullPrecisionSettings>;

/// Write the last checkpoint into a temp directory, then swap it in: a killed save leaves the previous one intact.
pub(crate) fn save_last<B: AutodiffBackend, O: Optimizer<UNet<B>, B>>(
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
pub(crate) fn save_model<B: Backend>(net: &UNet<B>, path: &Path, recorder: &Rec) -> Result<()> {
    // Remove first: the recorder warns when it replaces a file, which is the normal case here.
    let _ = std::fs::remove_file(path.with_extension("mpk"));
    net.clone()
        .save_file(path.to_path_buf(), recorder)
        .with_context(|| format!("saving the checkpoint {}", path.display()))?;
    Ok(())
}

pub(crate) fn write_json<T: serde::Serialize>(path: &Path, value: &T) -> Result<()> {
    dataset::files::write_json_atomic(path, value)
        .with_context(|| format!("writing {}", path.display()))
}

pub(crate) fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T> {
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

pub(crate) fn append_jsonl<T: serde::Serialize>(path: &Path, value: &T) -> Result<()> {
    let mut file = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .with_context(|| format!("opening {}", path.display()))?;
    writeln!(file, "{}", serde_json::to_string(value)?)?;
    Ok(())
}

pub(crate) fn read_history(path: &Path) -> Result<Vec<EpochMetrics>> {
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
pub struct RunNormalisation {
    /// How heights became the network's input.
    #[serde(flatten)]
    pub input: InputNormalisation,
    pub dataset: String,
    /// What framed the training crops (the dataset manifest's `crater_frame`): `infer` and `report` default the
    /// minimum diameter to it and check a catalogue against it. Absent for runs on unframed data (and runs
    /// trained before it was recorded).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crater_frame: Option<dataset::contract::manifest::CraterFrameSource>,
}

/// A run's `normalisation.json`.
pub fn load_normalisation(run: &Path) -> Result<RunNormalisation> {
    read_json(&run.join("normalisation.json"))
}

/// A run's input range (`input_range.json`), `None` when it keeps none (trained before ranges were kept:
/// [`record_input_range`] measures one).
pub fn load_input_range(run: &Path) -> Result<Option<InputRange>> {
    let path = run.join(INPUT_RANGE_FILE);
    if !path.exists() {
        return Ok(None);
    }
    read_json(&path).map(Some)
}

/// Measure the range of a run's inputs over the train split of `source`, the publications `datasets` (in the pool's
/// order), and keep it in the run (`input_range.json`). They must be the ones the run trained on, in its order
/// (its normalisation's dataset, then its config's `also_train_on`): a range over other data would count the wrong
/// crops as outside.
pub fn record_input_range(
    run: &Path,
    source: &dyn SampleSource,
    datasets: Vec<String>,
) -> Result<InputRange> {
    let config: FitConfig = read_json(&run.join("config.json"))?;
    let trained_on: Vec<String> = std::iter::once(load_normalisation(run)?.dataset)
        .chain(config.also_train_on)
        .collect();
    if datasets != trained_on {
        bail!(
            "{}: the run trained on {trained_on:?}, but the data given holds {datasets:?}: give the same publications \
             in the same order (--data, then each --also-train-on)",
            run.display()
        );
    }
    let range = InputRange::of_source(source, datasets, INPUT_RANGE_SAMPLES)?;
    write_json(&run.join(INPUT_RANGE_FILE), &range)?;
    Ok(range)
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
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
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
                    other.name()
                ),
            })
    }
}

named_enum!(Checkpoint {
    Auto => "auto",
    Best => "best",
    Last => "last",
    EmaBest => "ema-best",
    EmaLast => "ema-last",
});

/// A trained run, loaded for evaluation or inference.
pub struct TrainedRun<B: Backend> {
    pub config: FitConfig,
    /// How heights become the network's input (`normalisation.json`).
    pub input: InputNormalisation,
    pub net: UNet<B>,
    /// The checkpoint file the network came from, relative to the run directory (e.g. `ema-best/model.mpk`).
    pub checkpoint: String,
    /// The crater level kept beside the network (`crater_level.json`, written by `g2r-train crater-level`):
    /// `eval` and `infer` set each crater crop's level with it.
    pub crater_level: Option<crate::crater_level::CraterLevel>,
    /// The range its inputs spanned over its train crops (`input_range.json`), against which `eval` and `infer`
    /// count the crops they are given; `None` for runs trained before it was kept.
    pub input_range: Option<crate::data::InputRange>,
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
    let crater_level = crate::crater_level::load(run, config.model)?;
    let input_range = load_input_range(run)?;
    Ok(TrainedRun {
        config,
        input,
        net,
        checkpoint,
        crater_level,
        input_range,
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

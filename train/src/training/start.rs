//! Where a fit starts: a new run, or the saved state of the run in its directory.

use std::path::Path;

use anyhow::{bail, Context, Result};
use burn::module::AutodiffModule;
use burn::prelude::*;
use dataset::contract::rng::keyed_u64;
use dataset::contract::schema::Split;

use crate::data::{
    crop_interior_m, for_each_sample_group, ContextNormalisation, ElevationNormalisation,
    InputNormalisation, SampleSource,
};
use crate::data_parallel::Ranks;
use crate::fit_config::FitConfig;
use crate::kernels::TrainBackend;
use crate::model::UNet;
use crate::run_dir::{
    read_history, read_json, record_input_range, run_input, write_json, Cursor, EpochMetrics, Rec,
    RunNormalisation,
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
        if config.crater_frame_input && !config.crater_input {
            bail!("the crater frame input is the crater input fed as a frame: the run needs --crater-input");
        }
        let crater_rms_m = config
            .crater_input
            .then(|| {
                ContextNormalisation::crater_rms_of_samples(&samples, config.crater_frame_input)
                    .with_context(on_train)
            })
            .transpose()?;
        if config.crater_relief_input && !config.crater_frame_input {
            bail!("the crater relief input is one more plane of the crater frame: the run needs --crater-frame-input");
        }
        let crater_relief = config
            .crater_relief_input
            .then(|| {
                ContextNormalisation::crater_relief_of_samples(&samples).with_context(on_train)
            })
            .transpose()?;
        if config.unit_input {
            ContextNormalisation::check_units_mapped(&samples).with_context(on_train)?;
        }
        input.context = Some(ContextNormalisation {
            absolute: config.context_absolute,
            crater_rms_m,
            crater_frame: config.crater_frame_input,
            crater_relief,
            units: config.unit_input,
            ..context
        });
    } else if config.unit_input {
        bail!("the unit map is fed beside the context window: the run needs --context-input");
    }
    Ok(input)
}

/// Train crops the uniform head initialisation is fitted on.
pub const UNIFORM_INIT_SAMPLES: usize = 256;

/// What a replica's epochs start from.
pub(super) struct Start<B: TrainBackend> {
    pub net: UNet<B>,
    pub cursor: Cursor,
    pub history: Vec<EpochMetrics>,
    pub input: InputNormalisation,
    pub average: Option<UNet<B::InnerBackend>>,
}

/// A new run (its input normalisation computed and, by the lead, written with its config; the network
/// initialised from `(seed, "init")` with the uniform fit as its head), or with `resume` the saved state of the run in
/// `out`, refused when its settings differ from `config`.
pub(super) fn start_or_resume<B: TrainBackend>(
    source: &dyn SampleSource,
    config: &FitConfig,
    out: &Path,
    resume: bool,
    device: &B::Device,
    ranks: &Ranks,
) -> Result<Start<B>> {
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
        let input = input_normalisation(source, config)?;
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
                    crater_frame: source.manifest().crater_frame.clone(),
                },
            )?;
            // The range the inputs span over the train crops, against which `eval` and `infer` count a new site's.
            let datasets = std::iter::once(source.manifest().name.clone())
                .chain(config.also_train_on.iter().cloned())
                .collect();
            record_input_range(out, source, datasets)?;
        }
        B::seed(device, keyed_u64(seed, "init", 0));
        let net = net_config.init::<B>(device);
        let _ = net.num_params(); // materialise the lazily initialised weights now, in a fixed order
        let fit = crate::uniform_fit::calibrate(source, UNIFORM_INIT_SAMPLES, config.model)?;
        let start = if config.nonnegative_start {
            &fit.model_uniform_nonnegative
        } else {
            &fit.model_uniform
        };
        tracing::info!(coefficients = ?start, nonnegative = config.nonnegative_start, samples = fit.samples, "head = uniform fit");
        let raw: Vec<f64> = if config.log_coefficients {
            if let Some(c) = start.iter().find(|&&c| c <= 0.0) {
                bail!("--log-coefficients needs every coefficient of the uniform start above 0, and the {} uniform fit has {c}: drop --log-coefficients (a model whose fit needs a coefficient at or below 0 keeps the linear output)", config.model.name());
            }
            start.iter().map(|c| c.ln()).collect()
        } else {
            start
                .iter()
                .map(|&c| dataset::science::brdf::inverse_leaky_relu(c))
                .collect()
        };
        let net = net.with_uniform_head(&raw, device);
        let average = config.ema_decay.map(|_| net.valid());
        (net, Cursor::start(), Vec::new(), input, average)
    };
    Ok(Start {
        net,
        cursor,
        history,
        input,
        average,
    })
}

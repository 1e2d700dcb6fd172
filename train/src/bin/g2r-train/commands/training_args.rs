//! The training flags `fit` and `compare-models` share, the run's [`FitConfig`] they give, and the data they
//! train on.

use std::sync::Arc;

use anyhow::Result;
use clap::Args;
use dataset::science::brdf::BrdfModel;
use train::backend::BackendKind;
use train::data::{open_source, PooledSource, SampleSource, StreamConfig};
use train::fit_config::FitConfig;

use super::named;

#[derive(Args, Debug, Clone)]
pub struct TrainArgs {
    /// BRDF model: m1..m6 (the paper's), l2..l4 (Lommel–Seeliger), h1 (per-pixel scale on Moon-wide Hapke) or h3 (Moon-wide Hapke split into two single-scattering lobes and multiple scattering); see `g2r-train models`.
    #[arg(long, default_value = "m2")]
    pub model: BrdfModel,
    #[arg(long, default_value_t = 20)]
    pub epochs: usize,
    #[arg(long, default_value_t = 64)]
    pub batch: usize,
    /// Adam learning rate.
    #[arg(long, default_value_t = 1e-4)]
    pub lr: f64,
    #[arg(long, default_value_t = 42)]
    pub seed: u64,
    /// U-Net width of the first stage (16 = the paper's ~2.16 M weights; 4 or 8 for CPU budgets).
    #[arg(long, default_value_t = 16)]
    pub width: usize,
    /// Row groups shuffled together (memory ~ window x 55 MB). Shards are written ortho by ortho, so a wider
    /// window mixes more orthos into each stretch of batches (8 covers all of the demo's train row groups).
    #[arg(long, default_value_t = 8)]
    pub window: usize,
    /// Disable rot90/flip augmentation.
    #[arg(long)]
    pub no_augment: bool,
    /// Disable dropout.
    #[arg(long)]
    pub no_dropout: bool,
    /// Train samples per epoch (default: the whole train split).
    #[arg(long)]
    pub max_train_samples: Option<usize>,
    /// Validation samples per epoch, spread evenly over the val split (default: all of it).
    #[arg(long)]
    pub max_val_samples: Option<usize>,
    #[arg(long, value_enum, default_value = "flex")]
    pub backend: BackendKind,
    /// Learning-rate schedule: constant, or cosine decay from --lr to 0 over the run.
    #[arg(long, default_value = "constant", value_parser = named::<train::fit_config::LrSchedule>(train::fit_config::LrSchedule::NAMES))]
    pub lr_schedule: train::fit_config::LrSchedule,
    /// Add absolute elevation as a second input plane (normalised by the mean and std of 256 spread train
    /// crops). The paper's input is relief only (crop mean removed), which hides whether a crop lies on a crater
    /// floor, a mare plain or a highland rim; at the crop scale that explains much of the albedo. Meaningful
    /// within one region: a DEM from elsewhere on the Moon has other absolute heights.
    #[arg(long)]
    pub elevation_input: bool,
    /// Feed each sample's context window (32 × 32 cells of the dataset's context_gsd_m, 16 km at the default
    /// 512 m: dataset schema 1.2) through a small encoder into the U-Net's bottleneck and head. A 640 m crop cannot tell a
    /// crater floor or wall from a plain; kilometres of surrounding terrain can.
    #[arg(long)]
    pub context_input: bool,
    /// Feed the context window's absolute heights too (normalised as --elevation-input's plane, beside the
    /// heights relative to the crop): how high the terrain around stands, not only its shape. On a crater wall
    /// the crater's own profile hides the unit under it; the rim and plains around show it by their level.
    #[arg(long, requires_all = ["context_input", "elevation_input"])]
    pub context_absolute: bool,
    /// Feed each crop's height relative to the nearest large catalogued crater's median profile (the dataset's
    /// crater_relative_height_m: publish it with inputs.crater_catalogue in the pipeline manifest) as one more
    /// context plane. On a complex crater's wall the crater's relief hides the few hundred metres by which mare
    /// lies below highland; against the crater's own profile they show again.
    #[arg(long, requires = "context_input")]
    pub crater_input: bool,
    /// Feed the crater input as a frame: the height against the profile, the crop's distance from the crater's
    /// centre in radii, and whether a listed crater lies within 3 radii at all. Crops past that, or on a site
    /// with no catalogue, are fed as unframed, so one model runs with a catalogue or without; train it on a
    /// dataset framed with project.crater_catalogue_error to learn a real catalogue's errors.
    #[arg(long, requires = "crater_input")]
    pub crater_frame_input: bool,
    /// Feed the framing crater's relief over its diameter as one more frame plane (the dataset's
    /// crater_relief_to_diameter, schema 1.4: the crater's rim crest minus its floor along rays from the catalogued
    /// centre, read from the DEM). A fresh crater is deep for its size and its wall and ejecta are bright;
    /// the crop's own context window sees only part of the crater.
    #[arg(long, requires = "crater_frame_input")]
    pub crater_relief_input: bool,
    /// Feed the context window's mare/highland units from the site's unit map (the dataset's context_highland,
    /// schema 1.6: publish it with inputs.unit_map in the pipeline manifest; `infer --unit-map` at inference) and
    /// where the map has them. A crater's wall is fresh material of the ground it cuts, and with heights relative
    /// to the crop nothing in a crop says whether that ground is mare or highland; a geologic or FeO map does.
    /// Crops without a map are fed as unmapped, so one model runs with a map or without.
    #[arg(long, requires = "context_input")]
    pub unit_input: bool,
    /// Also keep an exponential moving average of the weights with this decay (e.g. 0.995; the first steps
    /// average over about a ninth of the steps taken). It is validated beside the raw network every epoch
    /// (metrics.jsonl `ema_val`) and checkpointed as ema-best/ and last/ema; eval, infer and report load
    /// last/ema (the final average) by default.
    #[arg(long, value_name = "DECAY", value_parser = parse_ema_decay)]
    pub ema: Option<f64>,
    /// Draw crops whose delivered-DEM mean slope is at least 20° this many times as often as the others (needs
    /// --max-train-samples: each epoch draws that many crops in proportion to these weights, without
    /// replacement). Steep crops (crater walls and rims) hold most of the error at publication scale, and a
    /// network that sees few of them does not learn what sets their brightness. 1: every crop equally likely.
    #[arg(long, value_name = "W", default_value_t = 1.0, value_parser = parse_steep_weight)]
    pub steep_weight: f64,
    /// Put a per-pixel hidden layer of this many channels (1×1 conv → LeakyReLU) between the joined decoder and
    /// context features and the head; 0: the paper's linear head. A linear head can only add what the crop's
    /// terrain says to what the context says; a hidden layer lets one change the meaning of the other (on a
    /// crater wall the same elevation means another unit than on the plains).
    #[arg(long, value_name = "CHANNELS", default_value_t = 0)]
    pub head_hidden: usize,
    /// Add a per-crop level branch: a small MLP from the crop's mean absolute elevation and the context
    /// features to one offset per BRDF parameter, added at every pixel. The convolutions see the elevation as
    /// normalised per-pixel features; this branch takes the crop's level as one number beside what the context
    /// says of its surroundings (which unit lies under a crater wall depends on both). Needs --elevation-input.
    #[arg(long, requires = "elevation_input")]
    pub crop_level: bool,
    /// Modulate the decoder by the context: after every up stage each channel is scaled and shifted by amounts
    /// computed from the context features (and, with --elevation-input, the crop's mean elevation), starting at
    /// no change. Joined context channels can only add to what the crop says; a scale lets the context change
    /// how the crop's own terrain is read. Needs --context-input.
    #[arg(long, requires = "context_input")]
    pub film: bool,
    /// Start the head at the best uniform fit with every coefficient ≥ 0 (non-negative least squares) rather
    /// than the unconstrained one. The parameters pass through a LeakyReLU, so a negative start sits where
    /// gradients are 100× smaller; H3's three nearly collinear terms fit as large cancelling coefficients
    /// (two negative) when unconstrained.
    #[arg(long)]
    pub nonnegative_start: bool,
    /// The head gives each coefficient's logarithm and the network outputs its exponential, so what the context
    /// says (the unit under the crop) and what the crop's terrain says (a fresh wall) multiply, as albedo factors
    /// do, where a linear output adds them. Every coefficient of the uniform start must be above 0 (H1's is).
    #[arg(long)]
    pub log_coefficients: bool,
    /// Decoupled weight decay (AdamW): every step first shrinks each weight by the step's learning rate times
    /// this, then takes Adam's step (0.01 is PyTorch's AdamW default: with --lr 1e-3 a weight no gradient holds
    /// up shrinks by 1e-5 a step). A regulariser: it pulls toward zero the weights the gradients do not hold up
    /// (at the shipped recipe 0.05 made held-out tiles worse: docs/results.md). Default: plain Adam, no decay.
    #[arg(long, value_name = "DECAY", value_parser = parse_weight_decay)]
    pub weight_decay: Option<f64>,
    /// Data-parallel ranks (`mpirun -np N g2r-train fit ...`, `srun --mpi=pmix`; a binary built with the `mpi`
    /// feature): the longest a rank waits in one all-reduce, in seconds, before it decides a peer is hung or
    /// unreachable, logs which all-reduce at which step, and exits (status 124) so that the launcher ends the job.
    /// Ranks other than 0 wait for rank 0's validation and checkpoint at every epoch's end, so this must cover
    /// those. Resume from the last checkpoint.
    #[arg(long, value_name = "SECONDS", default_value_t = 1800, value_parser = clap::value_parser!(u64).range(1..))]
    pub collective_timeout: u64,
    /// Also train on this publication's train split (repeat the flag for more): a directory, server URL or
    /// object-storage prefix, as for --data. Validation and the run's choice stay on --data's held-out tiles.
    /// Another world of the same preset (`g2r-pipeline synth --seed`) shows the network the same kinds of terrain
    /// over other units: on a crater wall, one world's training tiles let it learn where that world's units lie,
    /// and more worlds make it read them from the terrain instead. Each dataset needs its own [dataset] name.
    #[arg(long, value_name = "DATA")]
    pub also_train_on: Vec<String>,
    /// Also validate on this publication's validation split (repeat the flag for more), pooled with --data's:
    /// a held-out world, none of whose rows is trained on, so the run is chosen on how it carries to another
    /// world as well as to held-out tiles. test stays --data's. Each dataset needs its own [dataset] name.
    #[arg(long, value_name = "DATA")]
    pub also_validate_on: Vec<String>,
}

fn parse_ema_decay(text: &str) -> Result<f64, String> {
    let decay: f64 = text
        .parse()
        .map_err(|e| format!("{text:?} is not a number: {e}"))?;
    if (0.0..1.0).contains(&decay) {
        Ok(decay)
    } else {
        Err(format!(
            "{decay} is outside [0, 1): the decay weights the old average (0.99-0.999 is usual)"
        ))
    }
}

fn parse_weight_decay(text: &str) -> Result<f64, String> {
    let decay: f64 = text
        .parse()
        .map_err(|e| format!("{text:?} is not a number: {e}"))?;
    if decay.is_finite() && decay > 0.0 {
        Ok(decay)
    } else {
        Err(format!(
            "{decay} is not a positive decay: each step shrinks the weights by the learning rate times it (leave the flag out for none)"
        ))
    }
}

fn parse_steep_weight(text: &str) -> Result<f64, String> {
    let weight: f64 = text
        .parse()
        .map_err(|e| format!("{text:?} is not a number: {e}"))?;
    if weight.is_finite() && weight >= 1.0 {
        Ok(weight)
    } else {
        Err(format!(
            "{weight} is not a weight of at least 1: steep crops are drawn this many times as often (1 = uniform)"
        ))
    }
}

impl TrainArgs {
    pub fn fit_config(&self) -> FitConfig {
        FitConfig {
            version: train::fit_config::FIT_CONFIG_VERSION,
            model: self.model,
            epochs: self.epochs,
            learning_rate: self.lr,
            base_width: self.width,
            dropout: !self.no_dropout,
            stream: StreamConfig {
                seed: self.seed,
                batch_size: self.batch,
                window_groups: self.window,
                augment: !self.no_augment,
                max_samples: self.max_train_samples,
            },
            max_val_samples: self.max_val_samples,
            lr_schedule: self.lr_schedule,
            elevation_input: self.elevation_input,
            context_input: self.context_input,
            context_absolute: self.context_absolute,
            crater_input: self.crater_input,
            crater_frame_input: self.crater_frame_input,
            crater_relief_input: self.crater_relief_input,
            unit_input: self.unit_input,
            ema_decay: self.ema,
            steep_weight: self.steep_weight,
            head_hidden: self.head_hidden,
            crop_level: self.crop_level,
            film: self.film,
            nonnegative_start: self.nonnegative_start,
            log_coefficients: self.log_coefficients,
            weight_decay: self.weight_decay,
            // Named once the datasets are open ([`training_source`]).
            also_train_on: Vec::new(),
            also_validate_on: Vec::new(),
        }
    }
}

/// `--data`, pooled with `--also-train-on`'s and `--also-validate-on`'s publications when there are any, and the
/// run's config, which names them.
pub fn training_source(data: &str, args: &TrainArgs) -> Result<(Arc<dyn SampleSource>, FitConfig)> {
    let (first, mut config) = (open_source(data)?, args.fit_config());
    if args.also_train_on.is_empty() && args.also_validate_on.is_empty() {
        return Ok((first, config));
    }
    let open_all = |all: &[String]| {
        all.iter()
            .map(|data| open_source(data))
            .collect::<Result<Vec<_>>>()
    };
    let pool = PooledSource::new(first, open_all(&args.also_train_on)?)?
        .also_validating_on(open_all(&args.also_validate_on)?)?;
    config.also_train_on = pool.further_names();
    config.also_validate_on = pool.validation_names();
    Ok((Arc::new(pool), config))
}

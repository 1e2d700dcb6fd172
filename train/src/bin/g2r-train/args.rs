//! `g2r-train`'s command line: every subcommand, its flags and their help, and the flag parsers. Parsing only;
//! `main.rs` hands the parsed values to the library's jobs.

use std::path::{Path, PathBuf};

use clap::{Args, Parser, Subcommand};
use dataset::science::brdf::BrdfModel;
use train::backend::BackendKind;
use train::data::StreamConfig;
use train::fit_config::FitConfig;
use train::kernels::cubecl::ConvBackward;

#[derive(Parser)]
#[command(
    name = "g2r-train",
    version,
    about = "Train a U-Net that maps 128x128 DEM crops to per-pixel BRDF parameters (M1-M6, L2-L4, H1, H3) through a differentiable renderer",
    long_about = "Train a U-Net that maps 128x128 DEM crops (5 m/px) to per-pixel parameters of a small \
cosine-polynomial BRDF, supervised by rendering through a differentiable renderer layer and comparing with the \
orthoimage (MSE over valid pixels).\n\nData: a dataset directory published by `g2r-pipeline run` (manifest.json + \
shards). CPU training is slow (the paper-size U-Net costs ~6 GFLOP per sample): use --width 4 or 8 and \
--max-train-samples for CPU budgets, the cuda backend on a GPU machine for full runs."
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

/// The crater catalogue a run's crops are framed with, as the project stage framed its training crops: `infer`
/// (and `report`'s overlap rows) need it for a run with a crater input, and apply a run's crater level with it.
#[derive(Args, Debug, Clone)]
pub struct CraterCatalogueArgs {
    /// The crater catalogue CSV the run's dataset was published with (inputs.crater_catalogue): needed by runs
    /// trained with --crater-input, and what sets the level of crater crops for a run that keeps a crater level.
    #[arg(long = "crater-catalogue", value_name = "CRATER_CATALOGUE")]
    pub catalogue: Option<PathBuf>,
    /// Craters at least this wide frame the crops (the pipeline's project.crater_min_diameter_m).
    #[arg(long = "crater-min-diameter-m", value_name = "CRATER_MIN_DIAMETER_M", default_value_t = dataset::contract::crater_frame::DEFAULT_MIN_DIAMETER_M, requires = "catalogue")]
    pub min_diameter_m: f64,
}

/// The trained network(s) a command loads: one run, or a seed ensemble.
#[derive(Args, Debug, Clone)]
pub struct RunsArgs {
    /// Run directory written by `fit` (config.json, normalisation.json and checkpoints).
    #[arg(long)]
    pub run: PathBuf,
    /// Further run directories (repeat the flag): a seed ensemble. `eval` scores the mean of all the runs'
    /// renderings (its squared error on each image is at most the members' mean; runs may differ in model and input
    /// planes); `infer` writes the mean of their maps (runs of one BRDF model), which renders exactly as that mean.
    #[arg(long, value_name = "RUN")]
    pub ensemble: Vec<PathBuf>,
    /// Which checkpoint of each run: auto (ema-last when the run kept a weight average, else best, else last),
    /// best, last, ema-best or ema-last.
    #[arg(long, default_value = "auto", value_parser = named::<train::run_dir::Checkpoint>(train::run_dir::Checkpoint::NAMES))]
    pub checkpoint: train::run_dir::Checkpoint,
    #[arg(long, value_enum, default_value = "flex")]
    pub backend: BackendKind,
}

impl RunsArgs {
    pub fn paths(&self) -> Vec<&Path> {
        std::iter::once(self.run.as_path())
            .chain(self.ensemble.iter().map(PathBuf::as_path))
            .collect()
    }
}

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
}

/// A parser for a library enum chosen by name: its names are the possible values `--help` lists, parsed with its
/// `FromStr`. Library types carry no clap, except `BackendKind`, a `ValueEnum` so that `--help` shows what each
/// backend needs.
fn named<T>(names: &'static [&'static str]) -> impl clap::builder::TypedValueParser<Value = T>
where
    T: std::str::FromStr + Clone + Send + Sync + 'static,
    T::Err: std::fmt::Debug,
{
    use clap::builder::TypedValueParser;
    clap::builder::PossibleValuesParser::new(names)
        .map(|name| name.parse::<T>().expect("every listed name parses"))
}

/// `X,Y,Z` (body-fixed metres) as a vector.
fn parse_body_vector(text: &str) -> Result<glam::DVec3, String> {
    let parts: Vec<f64> = text
        .split(',')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("'{text}': {e}; expected X,Y,Z in body-fixed metres"))?;
    match parts[..] {
        [x, y, z] => Ok(glam::DVec3::new(x, y, z)),
        _ => Err(format!(
            "'{text}' has {} numbers; expected three, X,Y,Z in body-fixed metres",
            parts.len()
        )),
    }
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
            ema_decay: self.ema,
            steep_weight: self.steep_weight,
            head_hidden: self.head_hidden,
            crop_level: self.crop_level,
            film: self.film,
            nonnegative_start: self.nonnegative_start,
            weight_decay: self.weight_decay,
            // Named once the datasets are open (`main.rs`, `training_source`).
            also_train_on: Vec::new(),
        }
    }
}

#[derive(Subcommand)]
pub enum Command {
    /// List the BRDF models (M1-M6, L2-L4, H1, H3) with their parameter order (the band order of parameter GeoTIFFs).
    Models,
    /// Train one model; writes config.json, metrics.jsonl (one line per epoch), best/ and last/ checkpoints.
    Fit {
        /// Published dataset directory (contains manifest.json), the URL of `g2r-dataset serve`
        /// (http://127.0.0.1:8080), or an object-storage prefix it was uploaded to (s3://bucket/prefix, with AWS_*
        /// settings from the environment; `g2r-dataset upload`): all give the same batches.
        #[arg(long)]
        data: String,
        /// Run directory.
        #[arg(long)]
        out: PathBuf,
        /// Continue the run in --out exactly where its last checkpoint stopped (same flags required).
        #[arg(long)]
        resume: bool,
        /// Stop after this many optimiser steps in total, leaving a resumable checkpoint.
        #[arg(long)]
        stop_after_steps: Option<u64>,
        /// When training has finished, fit the run's crater level on the same data, as `g2r-train crater-level
        /// --run OUT --data DATA` does (H1 runs on a dataset published with inputs.crater_catalogue): one command
        /// makes the whole shipped model.
        #[arg(long)]
        crater_level: bool,
        #[command(flatten)]
        train: TrainArgs,
    },
    /// Train every BRDF model (M1-M6, L2-L4, H1, H3) under the same budget and write a comparison table (val MSE, parameters, step time).
    CompareModels {
        /// Dataset directory or server URL, as for `fit`.
        #[arg(long)]
        data: String,
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        train: TrainArgs,
    },
    /// Evaluate a run on held-out tiles against the Hapke baselines, Lunar-Lambert and (with --world) the oracle;
    /// writes metrics.json, metrics.md and PNG panels (GT | each method | |learned - GT|).
    Eval {
        #[command(flatten)]
        runs: RunsArgs,
        /// Dataset directory or server URL.
        #[arg(long)]
        data: String,
        #[arg(long, default_value = "test")]
        split: dataset::contract::schema::Split,
        /// Synthetic world directory: adds the oracle (its true Hapke maps). Only evaluation reads truth/.
        #[arg(long)]
        world: Option<PathBuf>,
        /// Output directory (default RUN/eval-SPLIT).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Images to evaluate, spread evenly over the split so every ortho and tile is represented (default: all).
        #[arg(long)]
        max_samples: Option<usize>,
        #[arg(long, default_value_t = 8)]
        batch: usize,
        /// Train crops (spread evenly over the split) used to fit the honest Hapke scale and Lunar-Lambert albedo.
        #[arg(long, default_value_t = 256)]
        calibration_samples: usize,
        /// PNG panels for the first N images.
        #[arg(long, default_value_t = 8)]
        panels: usize,
        /// Render "learned" as the mean of the network's 8 dihedral views: the terrain (and context window) turned
        /// and mirrored with its geometry, each parameter map turned back, the 8 renderings averaged. An 8-member
        /// ensemble from one network: its error is at most the members' mean; costs 8× network and renderer time.
        #[arg(long)]
        symmetry_mean: bool,
    },
    /// Can two evaluations of the same crops be told apart? Pairs them crop by crop and bootstraps the candidate's
    /// learned SSE over the base's by whole orthos (the crops of one ortho share sun, view and ground, so the ortho
    /// is what varies between held-out tiles): prints the ratio, its 95 % interval and whether it holds 1; with
    /// --out, writes comparison.json, comparison.md and provenance.json.
    CompareEvals {
        /// The base: an `eval --out` directory (or its metrics.json).
        base: PathBuf,
        /// The candidate, evaluated on the same split with the same --max-samples.
        candidate: PathBuf,
        /// Ortho resamples.
        #[arg(long, default_value_t = 4000)]
        resamples: usize,
        /// Seed of the resampling stream.
        #[arg(long, default_value_t = 42)]
        seed: u64,
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Which BRDF model each kind of ground needs, with no network in the way: per crop, each candidate's
    /// model-form oracle (the best geometry-blind coefficients for the true material at every pixel: what its form
    /// attains) and its uniform fit, grouped by terrain class and unit; per ground, the cheapest candidate whose
    /// form error is within --tolerance of the best. Needs a synthetic world (--world). Writes model-choice.json
    /// and model-choice.md.
    ModelChoice {
        /// Dataset directory or server URL.
        #[arg(long)]
        data: String,
        /// Choose on validation; score test once, after.
        #[arg(long, default_value = "val")]
        split: dataset::contract::schema::Split,
        /// Synthetic world directory (its truth/ maps).
        #[arg(long)]
        world: PathBuf,
        /// Candidate models, comma-separated (default: two cosine polynomials, the Lommel-Seeliger family's best
        /// and the one-scale Hapke the trainer ships). Cost: parameter maps, then whether it evaluates Hapke.
        #[arg(long, value_delimiter = ',', default_value = "m1,m2,l3,h1")]
        models: Vec<BrdfModel>,
        /// How far above the best form error a cheaper model may be and still be chosen (0.05 = 5 %).
        #[arg(long, default_value_t = 0.05)]
        tolerance: f64,
        /// Images, spread evenly over the split (default: all).
        #[arg(long)]
        max_samples: Option<usize>,
        /// Train crops (spread evenly) for each candidate's uniform fit.
        #[arg(long, default_value_t = 256)]
        calibration_samples: usize,
        #[arg(long)]
        out: PathBuf,
    },
    /// Fit a crater level beside an H1 run and keep it in the run directory (crater_level.json), where `eval` and
    /// `infer` apply it: each crop near a large catalogued crater gets the brightness level a small regression
    /// gives it from its height against the crater's median profile, its slope and its radius, while the network's
    /// pattern inside the crop stays. The regression is fitted on train crops (no network); which band of crater
    /// radii it covers and how far it moves the network's level are chosen on the validation split, by the run's
    /// summed squared error. Needs a dataset published with inputs.crater_catalogue (schema 1.3).
    CraterLevel {
        #[command(flatten)]
        runs: RunsArgs,
        /// Dataset directory or server URL.
        #[arg(long)]
        data: String,
        /// Train crops read, spread evenly over the split (those within 3 radii of a crater are fitted on).
        #[arg(long)]
        max_train_samples: Option<usize>,
        /// Validation crops the choice is scored on, spread evenly (default: all).
        #[arg(long)]
        max_val_samples: Option<usize>,
        #[arg(long, default_value_t = 8)]
        batch: usize,
        /// Where to write it (default RUN/crater_level.json, which eval and infer load with the run).
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// BRDF parameter maps for a whole DEM: overlapping crops blended seamlessly, written as a GeoTIFF on the
    /// DEM's exact grid (same CRS and geotransform; one band per parameter, LeakyReLU applied; NaN nodata).
    Infer {
        #[command(flatten)]
        runs: RunsArgs,
        /// DEM GeoTIFF with a lunar CRS (any size; 5 m/px like the training crops).
        #[arg(long)]
        dem: PathBuf,
        /// Output GeoTIFF.
        #[arg(long)]
        out: PathBuf,
        /// Overlap between neighbouring 128-px crops, pixels (< 64).
        #[arg(long, default_value_t = train::inference::DEFAULT_OVERLAP)]
        overlap: usize,
        #[arg(long, default_value_t = 8)]
        batch: usize,
        /// Override the relief plane's DEM std (default: the run's normalisation.json).
        #[arg(long)]
        dem_std_m: Option<f64>,
        #[command(flatten)]
        craters: CraterCatalogueArgs,
    },
    /// Speed against error, measured in one run: BRDF models (M1-M6, L2-L4, H1 and H3 uniform fits, Hapke, Lunar-Lambert: pixel
    /// MSE vs ns/pixel); with --dem the renderer (rays/pixel, shadows); with --run and --dem inference overlap
    /// (seconds vs seam score); with --ortho and --dem the projection resampling kernel (ms/crop vs error against the
    /// exact area average). Writes report.md/json and one PNG plot per section.
    Report {
        /// Dataset directory or server URL.
        #[arg(long)]
        data: String,
        #[arg(long)]
        out: PathBuf,
        #[arg(long, default_value = "test")]
        split: dataset::contract::schema::Split,
        #[arg(long)]
        max_samples: Option<usize>,
        #[arg(long, default_value_t = 256)]
        calibration_samples: usize,
        /// A trained run, for the inference-overlap section (needs --dem).
        #[arg(long, requires = "dem")]
        run: Option<PathBuf>,
        /// Which checkpoint of --run: auto (ema-last when the run kept a weight average, else best, else last),
        /// best, last, ema-best or ema-last.
        #[arg(long, default_value = "auto", value_parser = named::<train::run_dir::Checkpoint>(train::run_dir::Checkpoint::NAMES))]
        checkpoint: train::run_dir::Checkpoint,
        /// DEM GeoTIFF for the renderer section (and, with --run, the inference-overlap section).
        #[arg(long)]
        dem: Option<PathBuf>,
        /// Overlaps to time, pixels.
        #[arg(long, value_delimiter = ',', default_value = "0,16,32,48")]
        overlaps: Vec<usize>,
        #[command(flatten)]
        craters: CraterCatalogueArgs,
        /// An orthoimage GeoTIFF on the DEM's CRS, for the resampling-kernel section (needs --dem).
        #[arg(long, requires = "dem")]
        ortho: Option<PathBuf>,
        /// Crops cut from --ortho for the resampling-kernel section.
        #[arg(long, default_value_t = 64)]
        resampling_crops: usize,
        #[arg(long, value_enum, default_value = "flex")]
        backend: BackendKind,
    },
    /// Novel views by ray marching the DEM (max-mipmap, cast shadows, N rays/pixel, optional Gaussian PSF) along
    /// a trajectory; with --params renders the learned BRDF and uniform Hapke side by side on one scale.
    /// Writes view_NNNN_{hapke,learned}.png (16-bit, I/F = value / 65535 x scale) and views.json.
    Render {
        /// DEM GeoTIFF (lunar CRS, no nodata holes).
        #[arg(long)]
        dem: PathBuf,
        /// Parameter GeoTIFF from `infer` on the same DEM grid (omit for uniform Hapke only).
        #[arg(long)]
        params: Option<PathBuf>,
        /// CSV with header `x,y,z,q0,qx,qy,qz` (body-fixed m, camera->body quaternion) or
        /// `lon,lat,alt,yaw,pitch,roll` (deg, m above the sphere, deg; all angles 0 = nadir, north up).
        #[arg(long)]
        trajectory: PathBuf,
        /// Sun position in body-fixed metres, X,Y,Z (only its direction matters).
        #[arg(long, allow_hyphen_values = true, value_parser = parse_body_vector)]
        sun: glam::DVec3,
        #[arg(long)]
        out: PathBuf,
        #[arg(long, default_value_t = 256)]
        width: usize,
        #[arg(long, default_value_t = 256)]
        height: usize,
        /// Horizontal field of view, degrees.
        #[arg(long, default_value_t = 45.0)]
        fov: f64,
        /// Jittered rays per pixel (1 = through pixel centres).
        #[arg(long, default_value_t = 4)]
        rays: usize,
        #[arg(long)]
        no_shadows: bool,
        /// Gaussian PSF sigma, pixels (0 = none).
        #[arg(long, default_value_t = 0.0)]
        psf_sigma: f64,
        #[arg(long, default_value_t = 0)]
        seed: u64,
    },
    /// Samples/s of the train step (U-Net + renderer layer, forward + backward + Adam) and of the layer alone,
    /// with the step's phases and per-kernel times; with --torch, alternately against the PyTorch peer.
    #[command(
        long_about = "Samples/s of the train step (U-Net + renderer layer, forward + backward + Adam) on synthetic \
crops, its forward/backward/optimizer phases and the time inside each CPU kernel, and the renderer layer alone \
(scene terms + render + loss + backward). Prints JSON.\n\nWith --torch PYTHON, runs the PyTorch peer of the same \
step (carried in the binary; needs torch in that Python) and this step alternately for --rounds rounds, at the \
same width, batch and thread count, and prints each round's ratio and the median (g2r / PyTorch samples/s). \
Measure on an idle machine; compare only figures from the same sitting."
    )]
    Bench {
        #[arg(long, default_value_t = 8)]
        batch: usize,
        #[arg(long, default_value_t = 16)]
        width: usize,
        #[arg(long, default_value = "m2")]
        model: BrdfModel,
        /// Timed steps per measurement (after one warm-up step).
        #[arg(long, default_value_t = 3)]
        iters: usize,
        #[arg(long, value_enum, default_value = "flex")]
        backend: BackendKind,
        /// A Python interpreter with torch: run the PyTorch peer alternately with this step (model m2).
        #[arg(long, value_name = "PYTHON", conflicts_with = "compare_conv_backward")]
        torch: Option<PathBuf>,
        /// The CubeCL backends' (cuda, wgpu) convolution gradients: `gemm`, weight gradients as im2col and batched
        /// matrix products over pieces of the reduction and input gradients as forward convolutions, or `stock`,
        /// Burn's own (direct kernels, the slow path this project replaced). Flex runs its own kernels either way.
        #[arg(long, value_enum, default_value = "gemm")]
        conv_backward: ConvBackward,
        /// Alternate `--conv-backward stock` and `gemm` in one process and report each round's samples/s and
        /// their ratio: the before and after of the rewritten gradients on this machine.
        #[arg(long)]
        compare_conv_backward: bool,
        /// Alternating rounds with --torch or --compare-conv-backward.
        #[arg(long, default_value_t = 3)]
        rounds: usize,
    },
    /// Write docs/results.md from the JSON result records in docs/results/ (one file per section, in file-name
    /// order) and refill the README's generated tables from them; with --check, write nothing and fail when the
    /// page or a generated table differs from what the records give.
    ResultsPage {
        /// Directory of result records (`NN-name.json`).
        #[arg(long, default_value = "docs/results")]
        records: PathBuf,
        /// The Markdown page written (or, with --check, compared).
        #[arg(long, default_value = "docs/results.md")]
        out: PathBuf,
        /// Documents whose generated blocks (`<!-- generated: results-page NN-name.json -->` … `<!-- end
        /// generated -->`) hold a record's table, refilled (or, with --check, compared) too.
        #[arg(long = "embed-in", default_value = "README.md")]
        embed_in: Vec<PathBuf>,
        /// Compare instead of writing: exit non-zero when --out is not exactly the generated page.
        #[arg(long)]
        check: bool,
    },
}

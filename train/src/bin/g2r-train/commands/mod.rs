//! One file per subcommand, each with its flags and its call into the library (cargo's `commands/` layout), and
//! the flag groups several commands share.

pub mod bench;
pub mod compare_evals;
pub mod compare_models;
pub mod crater_level;
pub mod eval;
pub mod fit;
pub mod infer;
pub mod input_range;
pub mod model_choice;
pub mod models;
pub mod render;
pub mod report;
pub mod training_args;

use std::path::{Path, PathBuf};

use clap::Args;
use train::backend::BackendKind;

/// The crater catalogue a run's crops are framed with, as the project stage framed its training crops: `infer`
/// (and `report`'s overlap rows) need it for a run with a crater input, and apply a run's crater level with it.
#[derive(Args, Debug, Clone)]
pub struct CraterCatalogueArgs {
    /// The crater catalogue CSV the run's dataset was published with (inputs.crater_catalogue): needed by runs
    /// trained with --crater-input, and what sets the level of crater crops for a run that keeps a crater level.
    #[arg(long = "crater-catalogue", value_name = "CRATER_CATALOGUE")]
    pub catalogue: Option<PathBuf>,
    /// Craters at least this wide frame the crops. Default: what the run was trained with (its dataset's
    /// manifest; another value is refused), else the pipeline's project.crater_frame_min_diameter_m default (15000).
    #[arg(
        long = "crater-frame-min-diameter-m",
        alias = "crater-min-diameter-m",
        value_name = "CRATER_FRAME_MIN_DIAMETER_M",
        requires = "catalogue"
    )]
    pub min_diameter_m: Option<f64>,
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

/// A parser for a library enum chosen by name: its names are the possible values `--help` lists, parsed with its
/// `FromStr`. Library types carry no clap, except `BackendKind`, a `ValueEnum` so that `--help` shows what each
/// backend needs.
pub fn named<T>(names: &'static [&'static str]) -> impl clap::builder::TypedValueParser<Value = T>
where
    T: std::str::FromStr + Clone + Send + Sync + 'static,
    T::Err: std::fmt::Debug,
{
    use clap::builder::TypedValueParser;
    clap::builder::PossibleValuesParser::new(names)
        .map(|name| name.parse::<T>().expect("every listed name parses"))
}

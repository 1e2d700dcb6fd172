//! `g2r-train report`.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use train::backend::{BackendKind, Inner};
use train::data::open_source;
use train::with_backend;

use super::{named, CraterCatalogueArgs};

/// Speed against error, measured in one run: BRDF models (M1-M6, L2-L4, H1 and H3 uniform fits, Hapke, Lunar-Lambert: pixel
/// MSE vs ns/pixel); with --dem the renderer (rays/pixel, shadows); with --run and --dem inference overlap
/// (seconds vs seam score); with --ortho and --dem the projection resampling kernel (ms/crop vs error against the
/// exact area average). Writes report.md/json and one PNG plot per section.
#[derive(Args, Debug)]
pub struct ReportArgs {
    /// Dataset directory or server URL.
    #[arg(long)]
    pub data: String,
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, default_value = "test")]
    pub split: dataset::contract::schema::Split,
    #[arg(long)]
    pub max_samples: Option<usize>,
    #[arg(long, default_value_t = 256)]
    pub calibration_samples: usize,
    /// A trained run, for the inference-overlap section (needs --dem).
    #[arg(long, requires = "dem")]
    pub run: Option<PathBuf>,
    /// Which checkpoint of --run: auto (ema-last when the run kept a weight average, else best, else last),
    /// best, last, ema-best or ema-last.
    #[arg(long, default_value = "auto", value_parser = named::<train::run_dir::Checkpoint>(train::run_dir::Checkpoint::NAMES))]
    pub checkpoint: train::run_dir::Checkpoint,
    /// DEM GeoTIFF for the renderer section (and, with --run, the inference-overlap section).
    #[arg(long)]
    pub dem: Option<PathBuf>,
    /// Overlaps to time, pixels.
    #[arg(long, value_delimiter = ',', default_value = "0,16,32,48")]
    pub overlaps: Vec<usize>,
    #[command(flatten)]
    pub craters: CraterCatalogueArgs,
    /// An orthoimage GeoTIFF on the DEM's CRS, for the resampling-kernel section (needs --dem).
    #[arg(long, requires = "dem")]
    pub ortho: Option<PathBuf>,
    /// Crops cut from --ortho for the resampling-kernel section.
    #[arg(long, default_value_t = 64)]
    pub resampling_crops: usize,
    #[arg(long, value_enum, default_value = "flex")]
    pub backend: BackendKind,
}

pub fn run(args: ReportArgs) -> Result<()> {
    let ReportArgs {
        data,
        out,
        split,
        max_samples,
        calibration_samples,
        run,
        checkpoint,
        dem,
        overlaps,
        craters,
        ortho,
        resampling_crops,
        backend,
    } = args;
    if craters.catalogue.is_some() && run.is_none() {
        anyhow::bail!("--crater-catalogue frames the crops of --run's overlap rows: give --run RUN_DIR (and --dem), or drop --crater-catalogue");
    }
    let source = open_source(&data)?;
    let job = train::report::ReportJob {
        source: source.as_ref(),
        split,
        max_samples,
        calibration_samples,
        run: run.as_deref().map(|run| (run, checkpoint)),
        dem: dem.as_deref(),
        overlaps: &overlaps,
        crater_catalogue: craters
            .catalogue
            .as_deref()
            .map(|path| (path, craters.min_diameter_m)),
        ortho: ortho.as_deref(),
        resampling_crops,
    };
    let report = with_backend!(backend, B => {
        train::report::run_job::<Inner<B>>(&job, &Default::default())
    })?;
    train::report::write(&report, &out)?;
    dataset::out!("{}", train::report::markdown(&report));
    Ok(())
}

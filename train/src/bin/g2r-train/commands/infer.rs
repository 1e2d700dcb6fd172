//! `g2r-train infer`.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use train::backend::Inner;
use train::with_backend;

use super::{CraterCatalogueArgs, RunsArgs};

/// BRDF parameter maps for a whole DEM: overlapping crops blended seamlessly, written as a GeoTIFF on the
/// DEM's exact grid (same CRS and geotransform; one band per parameter, LeakyReLU applied; NaN nodata). Crops
/// whose inputs lie outside the run's training range (input_range.json) are counted and logged.
#[derive(Args, Debug)]
pub struct InferArgs {
    #[command(flatten)]
    pub runs: RunsArgs,
    /// DEM GeoTIFF with a lunar CRS (any size; 5 m/px like the training crops).
    #[arg(long)]
    pub dem: PathBuf,
    /// Output GeoTIFF.
    #[arg(long)]
    pub out: PathBuf,
    /// Overlap between neighbouring 128-px crops, pixels (< 64).
    #[arg(long, default_value_t = train::inference::DEFAULT_OVERLAP)]
    pub overlap: usize,
    #[arg(long, default_value_t = 8)]
    pub batch: usize,
    /// Override the relief plane's DEM std (default: the run's normalisation.json).
    #[arg(long)]
    pub dem_std_m: Option<f64>,
    #[command(flatten)]
    pub craters: CraterCatalogueArgs,
    /// The site's mare/highland unit map, for a run trained with --unit-input: a GDAL raster in the DEM's CRS, 0
    /// mare, 1 highland, nodata unmapped (a geologic map through gdal_rasterize, or a thresholded FeO map).
    /// Without it such a run treats every crop as unmapped.
    #[arg(long, value_name = "RASTER")]
    pub unit_map: Option<PathBuf>,
    /// Feed each framed crop its crater's relief over diameter clamped into the run's training range
    /// (input_range.json): a crater fresher than any the run trained on is fed as the freshest it saw, rather than
    /// extrapolated from. Crops outside the range are counted and logged either way.
    #[arg(long, requires = "catalogue")]
    pub clamp_crater_relief: bool,
}

pub fn run(args: InferArgs) -> Result<()> {
    let InferArgs {
        runs,
        dem,
        out,
        overlap,
        batch,
        dem_std_m,
        craters,
        unit_map,
        clamp_crater_relief,
    } = args;
    let progress = dataset::progress::Progress::start("infer", "batches", 0);
    let raster = dataset::science::raster::read_raster(&dem)?;
    let paths = runs.paths();
    let crater_frames = craters
        .catalogue
        .map(|path| {
            train::inference::crater_frames_for_runs(&paths, &raster, &path, craters.min_diameter_m)
                .map(std::sync::Arc::new)
        })
        .transpose()?;
    let unit_map = unit_map
        .map(|path| {
            dataset::contract::context::read_unit_map(&path, &raster).map(std::sync::Arc::new)
        })
        .transpose()?;
    let job = train::inference::InferJob {
        runs: &paths,
        checkpoint: runs.checkpoint,
        dem: &raster,
        dem_path: &dem,
        overlap,
        batch_size: batch,
        dem_std_m,
        crater_frames,
        unit_map,
        clamp_crater_relief,
    };
    let maps = with_backend!(runs.backend, B => {
        train::inference::run_job::<Inner<B>>(&job, &Default::default(), |member, done, total| {
            progress.set_message(member.display().to_string());
            progress.set_length(total as u64);
            progress.set_position(done as u64);
        })
    })?;
    progress.finish();
    match maps.crater_level_crops {
        Some(crops) => tracing::info!(crops, "crater level applied"),
        None if std::fs::exists(runs.run.join(train::crater_level::CRATER_LEVEL_FILE))? => {
            tracing::warn!(
                "the run keeps a crater level, left out: give --crater-catalogue to set the level of the crops around its large craters"
            )
        }
        None => {}
    }
    train::data::RangeReport::log(maps.inputs_outside_training_range.as_ref());
    train::inference::write_params_geotiff(&maps, &raster, overlap, &out)?;
    dataset::outln!(
        "{}: {} x {} px, {} bands ({}), {} crops at overlap {overlap}",
        out.display(),
        maps.width,
        maps.height,
        maps.bands.len(),
        maps.model.name(),
        maps.crops
    );
    Ok(())
}

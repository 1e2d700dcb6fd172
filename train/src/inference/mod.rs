//! `g2r-train infer`: BRDF parameter maps for a whole DEM, without the reference implementation's two defects.
//!
//! - **Seams**: crops overlap by `overlap` pixels and are blended with a smooth taper (sin² ramps over the overlap,
//!   1 inside) normalised by the weight sum, so the weights form a partition of unity and no crop edge shows.
//!   [`seam_score`] measures what is left.
//! - **Georeferencing**: output pixel (c, r) *is* DEM pixel (c, r): the output GeoTIFF carries the DEM's own
//!   geotransform and CRS, crops are placed by integer pixel offsets (no half-crop shift), and borders are
//!   reflect-padded so the first and last rows and columns get full crops.
//!
//! Files: this one runs the network over the crops (and frames a new DEM's craters as the run was trained);
//! `tiling` places and blends the crops, `geotiff` writes the maps, `seams` measures what is left of the
//! crop edges.

mod geotiff;
mod seams;
mod tiling;

pub use geotiff::write_params_geotiff;
pub use seams::{render_maps, seam_score, SEAM_BORDER_PX};
use tiling::reflect;
pub use tiling::{crop_origins, crop_starts, taper, DEFAULT_OVERLAP};

use std::path::Path;

use anyhow::{bail, Context, Result};
use burn::prelude::*;
use dataset::contract::crater_frame::CraterFrames;
use dataset::contract::manifest::CraterFrameSource;
use dataset::contract::schema::{CONTEXT_PX, CROP_PX};
use dataset::science::brdf::{leaky_relu, BrdfModel};
use dataset::science::raster::Raster;

use crate::crater_level::CraterLevel;
use crate::data::{
    grid_mean_slope_deg, CropInputs, InputNormalisation, InputRange, RangeCheck, RangeReport,
};
use crate::kernels::TrainOps;
use crate::model::UNet;
use crate::run_dir::{load_ensemble, Checkpoint};

#[derive(Debug, Clone)]
pub struct InferOptions {
    pub overlap: usize,
    pub batch_size: usize,
    /// The run's network input normalisation (`run_dir::run_input`).
    pub input: InputNormalisation,
    /// The DEM's crater frames, for a run that feeds a crater input (`--crater-input`): built from the catalogue
    /// the training data was published with.
    pub crater_frames: Option<std::sync::Arc<CraterFrames>>,
    /// The site's unit map (`dataset::contract::context::read_unit_map`), for a run that feeds one
    /// (`--unit-input`); without it such a run sees every crop as unmapped, as it was trained to.
    pub unit_map: Option<std::sync::Arc<Raster>>,
    /// The run's crater level ([`crate::crater_level`]): it sets the level of the crops in its band of a crater's
    /// frame (needs `crater_frames`; without them the maps are the network's alone, and [`ParamMaps`] says so).
    pub crater_level: Option<CraterLevel>,
    /// The run's training range of inputs (`input_range.json`): crops outside it are counted ([`ParamMaps`]).
    pub input_range: Option<InputRange>,
    /// Feed each framed crop its crater's relief over diameter clamped into `input_range`.
    pub clamp_crater_relief: bool,
}

/// Parameter maps on the DEM grid: one band per BRDF parameter, LeakyReLU applied, NaN where the DEM has no data.
pub struct ParamMaps {
    pub width: usize,
    pub height: usize,
    pub model: BrdfModel,
    pub bands: Vec<Vec<f32>>,
    pub crops: usize,
    /// Crops whose level the run's crater level set; `None` when it was not applied (no crater level, or no
    /// crater frames to place the crops with).
    pub crater_level_crops: Option<usize>,
    /// The crops whose inputs lay outside the run's training range (the first member's, for an ensemble); `None`
    /// when the run keeps none.
    pub inputs_outside_training_range: Option<RangeReport>,
}

impl ParamMaps {
    /// The pixelwise mean of several runs' maps over the same DEM (a seed ensemble). Every model here is linear in
    /// its activated parameters, so rendering the mean maps gives exactly the mean of the members' renderings, which
    /// is what `eval --ensemble` scores; that holds only when the members share one BRDF model, so mixing models is
    /// an error. The blend weights depend on the overlap alone, so blending then averaging equals averaging then
    /// blending.
    pub fn mean(members: Vec<ParamMaps>) -> Result<ParamMaps> {
        let mut members = members.into_iter();
        let mut total = members
            .next()
            .context("an ensemble needs at least one run")?;
        let mut count = 1usize;
        for m in members {
            if (m.model, m.width, m.height) != (total.model, total.width, total.height) {
                bail!(
                    "ensemble members disagree: model {} on {} x {} px against {} on {} x {} px; average runs of one BRDF model",
                    m.model.name(), m.width, m.height, total.model.name(), total.width, total.height
                );
            }
            for (sum, band) in total.bands.iter_mut().zip(&m.bands) {
                for (s, v) in sum.iter_mut().zip(band) {
                    *s += v;
                }
            }
            count += 1;
        }
        let scale = 1.0 / count as f32;
        total.bands.iter_mut().flatten().for_each(|v| *v *= scale);
        Ok(total)
    }
}

/// Run the network over overlapping crops of `dem` and blend.
pub fn infer_params<B: TrainOps>(
    net: &UNet<B>,
    model: BrdfModel,
    dem: &Raster,
    options: &InferOptions,
    device: &B::Device,
    mut on_batch: impl FnMut(usize, usize),
) -> Result<ParamMaps> {
    if options.overlap >= CROP_PX / 2 {
        bail!(
            "--overlap must be below {} pixels (half a crop)",
            CROP_PX / 2
        );
    }
    let (w, h) = (dem.width, dem.height);
    if !dem.data.iter().any(|v| v.is_finite()) {
        bail!("the DEM has no valid heights");
    }
    // Crops start at DEM offsets that may be negative: beyond the DEM, heights are reflected.
    let height_at = |c: isize, r: isize| dem.data[reflect(r, h) * w + reflect(c, w)] as f64;
    let columns = crop_starts(w, options.overlap);
    let origins: Vec<(isize, isize)> = crop_starts(h, options.overlap)
        .into_iter()
        .flat_map(|r| columns.iter().map(move |&c| (c, r)))
        .collect();
    let p = model.param_count();
    let mut sums = vec![vec![0f64; w * h]; p];
    let mut weights = vec![0f64; w * h];
    let window: Vec<f64> = (0..CROP_PX)
        .map(|i| taper(i, CROP_PX, options.overlap))
        .collect();
    let npx = CROP_PX * CROP_PX;
    let crater_frames = match (options.input.crater_rms_m(), &options.crater_frames) {
        (None, _) => None,
        (Some(_), Some(frames)) if !frames.is_empty() => Some(frames),
        // A frame input was trained on unframed crops too: without a catalogue every crop is one.
        (Some(_), None) if options.input.crater_frame_input() => {
            tracing::info!("no crater catalogue: every crop is fed as unframed");
            None
        }
        (Some(_), _) => bail!(
            "the run feeds each crop's height against its crater's profile (--crater-input): give --crater-catalogue, the crater catalogue its dataset was published with, with a crater on this DEM"
        ),
    };
    // The crater level places crops with the same frames; without them it is left out, and said so.
    let level = match (&options.crater_level, &options.crater_frames) {
        (Some(level), Some(frames)) if !frames.is_empty() => {
            if model != BrdfModel::H1 {
                bail!(
                    "a crater level scales H1's one scale, but the run's model is {}",
                    model.name()
                );
            }
            Some((level, frames))
        }
        _ => None,
    };
    let mut crater_level_crops = 0usize;
    let clamp = options
        .clamp_crater_relief
        .then(|| InputRange::for_clamping(options.input_range.as_ref(), &options.input))
        .transpose()?;
    let mut range_check = options.input_range.as_ref().map(InputRange::check);
    let gsd_m = dem.transform.gsd_m();
    // The context windows are cut from the whole DEM, as the project stage cut the training samples'.
    let context = options
        .input
        .context
        .map(|c| dataset::contract::context::ContextSampler::new(dem, c.gsd_m));
    // The unit map's windows, on the same cells, for a run that feeds them.
    let units = match (&options.input.context, &options.unit_map) {
        (Some(c), Some(map)) if c.units => Some(dataset::contract::context::ContextSampler::new(
            map, c.gsd_m,
        )),
        (Some(c), None) if c.units => {
            tracing::info!("no unit map: every crop is fed as unmapped");
            None
        }
        _ => None,
    };
    for (b, batch) in origins.chunks(options.batch_size.max(1)).enumerate() {
        let mut input = Vec::with_capacity(batch.len() * options.input.channels() * npx);
        let mut context_input = Vec::new();
        // The crops the crater level applies to: each one's place in its crater's frame and its mean slope.
        let mut placed = Vec::with_capacity(batch.len());
        for &(c0, r0) in batch {
            let crop: Vec<f64> = (0..npx)
                .map(|k| height_at(c0 + (k % CROP_PX) as isize, r0 + (k / CROP_PX) as isize))
                .collect();
            // Holes are fed at the crop's mean height (see `push_planes`); their outputs become NaN below.
            options.input.push_planes(&crop, &mut input);
            // The crop centre is the corner shared by its four middle pixels, as in the project stage; its place in
            // the crater's frame from the crop's mean over its finite heights, as the project stage's (holes are
            // not published): one for the crater input and the crater level.
            let half = (CROP_PX / 2) as f64;
            let (x, y) = dem.transform.pixel_edge(c0 as f64 + half, r0 as f64 + half);
            let framed = options.crater_frames.as_deref().filter(|f| !f.is_empty());
            let crater = framed.and_then(|f| f.position(x, y, crate::data::crop_mean(&crop)));
            if let Some((level, _)) = level {
                // The slope over the crop and a one-pixel apron, as a published sample's (`mean_slope_deg`);
                // only where the level applies.
                placed.push(crater.filter(|at| level.applies(Some(at))).map(|at| {
                    let slope = grid_mean_slope_deg(
                        |c, r| height_at(c0 - 1 + c as isize, r0 - 1 + r as isize),
                        CROP_PX + 2,
                        gsd_m,
                    );
                    (at, slope)
                }));
            }
            // Only a run that feeds the crater input gets it.
            let crater_input = crater_frames.and(crater);
            let context_window = context.as_ref().map(|sampler| sampler.window(x, y));
            if let Some(check) = range_check.as_mut() {
                check.add(&CropInputs::of(
                    &crop,
                    context_window.as_deref(),
                    crater_input.as_ref(),
                ));
            }
            if let Some(window) = &context_window {
                let crater_input = match clamp {
                    Some(range) => crater_input.map(|c| range.clamp_crater_relief(&c)),
                    None => crater_input,
                };
                let highland = units.as_ref().map(|u| u.window(x, y));
                options.input.push_context(
                    &crop,
                    window,
                    crater_input.as_ref(),
                    highland.as_deref(),
                    &mut context_input,
                );
            }
        }
        let context_tensor = context.is_some().then(|| {
            Tensor::<B, 4>::from_data(
                TensorData::new(
                    context_input,
                    [
                        batch.len(),
                        options.input.context_channels(),
                        CONTEXT_PX,
                        CONTEXT_PX,
                    ],
                ),
                device,
            )
        });
        let raw = net
            .forward(
                Tensor::<B, 4>::from_data(
                    TensorData::new(
                        input,
                        [batch.len(), options.input.channels(), CROP_PX, CROP_PX],
                    ),
                    device,
                ),
                context_tensor,
            )
            .into_data()
            .convert::<f64>()
            .into_vec::<f64>()
            .expect("f64 after convert");
        for (i, &(c0, r0)) in batch.iter().enumerate() {
            // The crater level's factor on this crop's H1 scale (1 outside its band): the network's mean scale
            // over the crop's finite heights moved toward the regression's.
            let factor = match (level, placed.get(i).copied().flatten()) {
                (Some((level, _)), Some((at, slope))) => {
                    let (sum, n) = (0..npx)
                        .filter(|&k| {
                            height_at(c0 + (k % CROP_PX) as isize, r0 + (k / CROP_PX) as isize)
                                .is_finite()
                        })
                        .fold((0.0, 0usize), |(s, n), k| {
                            (s + leaky_relu(raw[i * p * npx + k]), n + 1)
                        });
                    crater_level_crops += 1;
                    level.factor(Some(&at), slope, sum / n.max(1) as f64)
                }
                _ => 1.0,
            };
            for k in 0..npx {
                let (c, r) = (c0 + (k % CROP_PX) as isize, r0 + (k / CROP_PX) as isize);
                if c < 0 || r < 0 || c >= w as isize || r >= h as isize {
                    continue; // reflect padding
                }
                let (c, r) = (c as usize, r as usize);
                let weight = window[k % CROP_PX] * window[k / CROP_PX];
                if weight == 0.0 {
                    continue;
                }
                weights[r * w + c] += weight;
                for (j, band) in sums.iter_mut().enumerate() {
                    band[r * w + c] += weight * factor * leaky_relu(raw[(i * p + j) * npx + k]);
                }
            }
        }
        on_batch(b + 1, origins.len().div_ceil(options.batch_size.max(1)));
    }
    let bands = sums
        .into_iter()
        .map(|band| {
            band.iter()
                .zip(&weights)
                .zip(&dem.data)
                .map(|((s, wsum), z)| {
                    if z.is_finite() {
                        (s / wsum) as f32
                    } else {
                        f32::NAN
                    }
                })
                .collect()
        })
        .collect();
    Ok(ParamMaps {
        width: w,
        height: h,
        model,
        bands,
        crops: origins.len(),
        crater_level_crops: level.map(|_| crater_level_crops),
        inputs_outside_training_range: range_check.map(RangeCheck::finish),
    })
}

/// The crater frames of a new DEM for `runs`, from a catalogue, checked against what the runs were trained with
/// (each run's `normalisation.json` records its dataset's crater frame):
/// - the minimum diameter defaults to the runs' own; another one is refused, since the network learned the frames
///   of craters at least that wide (runs recorded with different ones are refused as an ensemble too);
/// - the catalogue may differ from the training one (a new site has its own), and the log says which it is.
///
/// Runs with no record (unframed data, or trained before it was recorded) take `min_diameter_m` or the pipeline's
/// default.
pub fn crater_frames_for_runs(
    runs: &[&Path],
    dem: &Raster,
    catalogue: &Path,
    min_diameter_m: Option<f64>,
) -> Result<CraterFrames> {
    let mut trained_with: Option<(&Path, CraterFrameSource)> = None;
    for &run in runs {
        let Some(source) = crate::run_dir::load_normalisation(run)?.crater_frame else {
            continue;
        };
        if let Some((first, known)) = &trained_with {
            if known.min_diameter_m != source.min_diameter_m {
                bail!(
                    "{}: trained on crater frames of craters at least {} m wide, but {} on {} m: ensemble runs framed alike",
                    run.display(),
                    source.min_diameter_m,
                    first.display(),
                    known.min_diameter_m
                );
            }
        } else {
            trained_with = Some((run, source));
        }
    }
    let min_diameter_m = match (&trained_with, min_diameter_m) {
        (Some((run, known)), Some(given)) if given != known.min_diameter_m => bail!(
            "{}: the run learned the frames of craters at least {} m wide (its dataset's manifest), and \
             --crater-frame-min-diameter-m {given} frames others: drop the flag, or pass {}",
            run.display(),
            known.min_diameter_m,
            known.min_diameter_m
        ),
        (Some((_, known)), _) => known.min_diameter_m,
        (None, given) => given.unwrap_or(dataset::contract::crater_frame::DEFAULT_MIN_DIAMETER_M),
    };
    if let Some((_, known)) = &trained_with {
        let blake3 = dataset::files::hash_file(catalogue)
            .with_context(|| format!("{}: cannot read the catalogue", catalogue.display()))?;
        if blake3 == known.catalogue_blake3 {
            tracing::info!(catalogue = %catalogue.display(), "the catalogue the run was trained with");
        } else {
            tracing::info!(
                catalogue = %catalogue.display(),
                trained_with = %known.catalogue,
                trained_with_blake3 = %known.catalogue_blake3,
                "a catalogue other than the training one (a new site's)"
            );
        }
    }
    CraterFrames::from_catalogue(dem, catalogue, min_diameter_m)
}

/// `g2r-train infer` as data.
pub struct InferJob<'a> {
    /// The run, then the further members of an ensemble (one BRDF model: their maps are averaged).
    pub runs: &'a [&'a Path],
    pub checkpoint: Checkpoint,
    pub dem: &'a Raster,
    /// The DEM's file, named in errors about it.
    pub dem_path: &'a Path,
    pub overlap: usize,
    pub batch_size: usize,
    /// Overrides the relief plane's DEM std of every run (default: each run's `normalisation.json`).
    pub dem_std_m: Option<f64>,
    /// The DEM's crater frames, for runs that feed a crater input.
    pub crater_frames: Option<std::sync::Arc<CraterFrames>>,
    /// The site's unit map, for runs that feed one.
    pub unit_map: Option<std::sync::Arc<Raster>>,
    /// Feed each framed crop its crater's relief over diameter clamped into the run's training range.
    pub clamp_crater_relief: bool,
}

/// Every member's parameter maps over the whole DEM, averaged. `progress(member, done, total)` reports batches.
pub fn run_job<B: TrainOps>(
    job: &InferJob,
    device: &B::Device,
    mut progress: impl FnMut(&Path, usize, usize),
) -> Result<ParamMaps> {
    let runs = load_ensemble::<B>(job.runs, job.checkpoint, true, device)?;
    let mut members = Vec::new();
    for (member, trained) in job.runs.iter().zip(runs) {
        let mut input = trained.input;
        if let Some(dem_std_m) = job.dem_std_m {
            input.dem_std_m = dem_std_m;
        }
        let options = InferOptions {
            overlap: job.overlap,
            batch_size: job.batch_size,
            input,
            crater_frames: job.crater_frames.clone(),
            unit_map: job.unit_map.clone(),
            crater_level: trained.crater_level.clone(),
            input_range: trained.input_range.clone(),
            clamp_crater_relief: job.clamp_crater_relief,
        };
        members.push(
            infer_params::<B>(
                &trained.net,
                trained.config.model,
                job.dem,
                &options,
                device,
                |done, total| progress(member, done, total),
            )
            .map_err(|e| anyhow::anyhow!("{}: {e:#}", job.dem_path.display()))?,
        );
    }
    ParamMaps::mean(members)
}

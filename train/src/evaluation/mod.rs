//! `g2r-train eval`: the learned BRDF against the baselines and the oracle on held-out tiles (docs/design.md, Trainer and evaluation).
//!
//! Every method renders the same crops with the same geometry and lit fraction; only the reflectance model differs:
//! - **learned**: the run's U-Net → parameter maps → the renderer layer (inference mode);
//! - **hapke_paper**: uniform Moon-wide Hapke, then the paper's per-image affine normalisation to the ground
//!   truth's mean and range. It *peeks at the ground truth*; it is reported because the paper's claim is against it;
//! - **hapke_scaled**: uniform Hapke times one scale fitted by least squares on train crops: an honest baseline;
//! - **lunar_lambert**: McEwen's Lunar-Lambert with one albedo fitted the same way;
//! - **oracle** (with `--world`): the world's true Hapke maps sampled at each pixel, on the delivered DEM: the floor
//!   any BRDF rendered from this DEM can reach (the orthos were rendered from the finer true DEM);
//! - **oracle_morphology** (with `--world`, worlds that carry `truth/w_morphology.tif`): the same without the
//!   albedo component no terrain can predict (docs/design.md, Synthetic world): about as far as a model that reads the terrain perfectly
//!   could go, so the gap to it is the part of the error a DEM-driven model can still remove.
//!
//! These are the headline's; `methods::METHODS` lists every method an evaluation scores (with the per-image
//! normalised learned model, the run's model with uniform coefficients, and the oracles on the true DEM and of
//! the model's form).

mod comparison;
mod methods;
mod model_choice;
mod model_form;
mod panels;
mod tables;
mod truth;

pub use comparison::*;
pub use methods::*;
pub use model_choice::*;
pub use model_form::*;
pub use panels::*;
pub use tables::*;
pub use truth::*;

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{bail, Context, Result};
use dataset::contract::schema::{Sample, Split, CROP_PX};
use rayon::prelude::*;

use crate::baseline::truth_and_valid;
use crate::data::{
    for_each_sample_group, mean_slope_deg, CropInputs, InputRange, RangeCheck, RangeReport,
    SampleSource,
};
use crate::feature_matching::{FeatureMatcher, MatchStats};
use crate::kernels::TrainOps;
use crate::metrics::{image_metrics, MetricsAccumulator};
use crate::prediction::predict_ensemble;
use crate::run_dir::{load_ensemble, Checkpoint, TrainedRun};
use crate::uniform_fit::{calibrate, Calibration};

#[derive(Debug, Clone)]
pub struct EvalOptions {
    pub split: Split,
    pub max_samples: Option<usize>,
    pub batch_size: usize,
    /// Train crops used to fit the honest scales.
    pub calibration_samples: usize,
    /// PNG panels written for the first images.
    pub panels: usize,
    /// Render "learned" (in every ensemble member) as the mean of the network's 8 dihedral views
    /// ([`crate::prediction::predict_images_symmetry_mean`]): 8× the network and renderer time.
    pub symmetry_mean: bool,
    /// Feed every crop as if the dataset had no crater catalogue: a crater frame input unframed, no crater
    /// level. Scores what a frame-input run does on a site with no catalogue, against what the catalogue adds.
    pub without_crater_frames: bool,
    /// Feed each framed crop its crater's relief over diameter clamped into the run's training range
    /// ([`crate::data::InputRange::clamp_crater_relief`]): what the run renders when a crater fresher than any it
    /// trained on is fed as the freshest one it saw.
    pub clamp_crater_relief: bool,
}

/// Evaluate trained `runs` on a split; writes nothing (see [`write_report`]). One run is the usual case; with
/// several, "learned" is the mean of their renderings ([`predict_ensemble`]) and the first run names the model.
/// `on_image` sees every image's renderings (for panels).
pub fn evaluate<B: TrainOps>(
    runs: &[TrainedRun<B>],
    source: &dyn SampleSource,
    options: &EvalOptions,
    calibration: Calibration,
    truth_maps: Option<&TruthMaps>,
    device: &B::Device,
    mut on_image: impl FnMut(usize, &Sample, &[(&'static str, Vec<f64>)]) -> Result<()>,
) -> Result<EvalReport> {
    let config = &runs
        .first()
        .context("evaluate needs at least one trained run")?
        .config;
    for run in runs {
        run.input.check_dataset(source)?;
        if options.without_crater_frames
            && run.input.crater_rms_m().is_some()
            && !run.input.crater_frame_input()
        {
            bail!(
                "{}: the run feeds each crop's height against its crater's profile, which needs a frame: evaluate it \
                 without --without-crater-frames, or train with --crater-frame-input",
                run.checkpoint
            );
        }
    }
    // The first run names the model, and its training range is the one crops are counted against.
    let range = runs[0].input_range.as_ref();
    let clamp = options
        .clamp_crater_relief
        .then(|| InputRange::for_clamping(range, &runs[0].input))
        .transpose()
        .with_context(|| runs[0].checkpoint.clone())?;
    let mut range_check = range.map(InputRange::check);
    let mut accumulators: BTreeMap<String, MetricsAccumulator> = BTreeMap::new();
    let matcher = FeatureMatcher::default();
    let mut matches: BTreeMap<&str, MatchStats> = BTreeMap::new();
    let mut per_image = Vec::new();
    let mut failure: Option<anyhow::Error> = None;
    let crater_level = match runs {
        _ if options.without_crater_frames => None,
        [run] => run.crater_level.as_ref(),
        _ if runs.iter().any(|r| r.crater_level.is_some()) => bail!(
            "a crater level (crater_level.json) belongs to one run: evaluate the ensemble's members one by one, or \
             the ensemble from run directories without one"
        ),
        _ => None,
    };
    let (mut crater_level_crops, mut framed_crops) = (0usize, 0usize);
    let model_form = truth_maps
        .and_then(TruthMaps::fixed_material)
        .and_then(|fixed| ModelFormTable::new(config.model, fixed));
    for_each_sample_group(
        source,
        options.split,
        options.max_samples,
        "eval",
        |samples| {
            for chunk in samples.chunks(options.batch_size) {
                let changed: Vec<Sample>;
                let fed = if options.without_crater_frames {
                    changed = chunk
                        .iter()
                        .map(|s| Sample {
                            crater: None,
                            ..s.clone()
                        })
                        .collect();
                    changed.as_slice()
                } else if let Some(range) = clamp {
                    changed = chunk
                        .iter()
                        .map(|s| Sample {
                            crater: s.crater.as_ref().map(|c| range.clamp_crater_relief(c)),
                            ..s.clone()
                        })
                        .collect();
                    changed.as_slice()
                } else {
                    chunk
                };
                let learned = predict_ensemble(runs, fed, options.symmetry_mean, device);
                // Each crop's renderings, metrics and matches in parallel; then added up in crop order, so every
                // sum (and so every reported bit) is the same whatever the thread count.
                let scored: Vec<ScoredImage> = chunk
                    .par_iter()
                    .enumerate()
                    .map(|(i, sample)| {
                        let px = CROP_PX * CROP_PX;
                        let renderings = method_renderings(
                            sample,
                            &learned[i * px..(i + 1) * px],
                            crater_level,
                            &calibration,
                            truth_maps,
                            model_form.as_ref(),
                        );
                        score_image(sample, renderings, &matcher, truth_maps)
                    })
                    .collect();
                for (sample, mut scored) in chunk.iter().zip(scored) {
                    if let Some(check) = range_check.as_mut() {
                        // The site's own inputs, before any clamping; unframed as fed without frames.
                        let mut inputs = CropInputs::of_sample(sample);
                        if options.without_crater_frames {
                            inputs.crater_relative_height_m = None;
                            inputs.crater_relief_to_diameter = None;
                        }
                        scored.image.within_training_range = Some(!check.add(&inputs));
                    }
                    framed_crops +=
                        usize::from(sample.crater.is_some() && !options.without_crater_frames);
                    crater_level_crops += usize::from(
                        crater_level.is_some_and(|level| level.applies(sample.crater.as_ref())),
                    );
                    for (name, distances) in &scored.match_distances {
                        matches.entry(name).or_default().add_distances(distances);
                    }
                    for (name, m) in &scored.image.metrics {
                        accumulators.entry(name.clone()).or_default().add_metrics(m);
                    }
                    if failure.is_none() {
                        if let Err(e) = on_image(per_image.len(), sample, &scored.renderings) {
                            failure = Some(e);
                        }
                    }
                    per_image.push(scored.image);
                }
            }
        },
    )?;
    if let Some(e) = failure {
        return Err(e);
    }
    if per_image.is_empty() {
        bail!(
            "{}: split '{}' has no samples to evaluate",
            source.describe(),
            options.split
        );
    }
    let methods: Vec<MethodResult> = METHODS
        .iter()
        .filter_map(|(name, description)| {
            accumulators.get(*name).map(|a| MethodResult {
                name: name.to_string(),
                description: description.to_string(),
                aggregate: a.finish(),
            })
        })
        .collect();
    let sse = |name: &str| {
        methods
            .iter()
            .find(|m| m.name == name)
            .map(|m| m.aggregate.sse)
    };
    let inputs_outside_training_range = range_check.map(RangeCheck::finish);
    RangeReport::log(inputs_outside_training_range.as_ref());
    let learned = sse("learned").context("no learned metrics")?;
    let paper = sse("hapke_paper").context("no Hapke metrics")?;
    let scaled = sse("hapke_scaled").context("no Hapke metrics")?;
    Ok(EvalReport {
        split: options.split,
        run_model: config.model.name().to_string(),
        images: per_image.len(),
        learned_symmetry_mean: options.symmetry_mean,
        learned_ensemble_runs: runs.len(),
        learned_checkpoints: runs.iter().map(|r| r.checkpoint.clone()).collect(),
        learned_crater_relief_clamped: options.clamp_crater_relief,
        inputs_outside_training_range,
        calibration: calibration.clone(),
        methods: methods.clone(),
        learned_over_hapke_paper_sse: learned / paper,
        learned_over_hapke_scaled_sse: learned / scaled,
        learned_over_hapke_both_paper_norm_sse: sse("learned_paper_norm")
            .context("no normalised learned metrics")?
            / paper,
        hapke_to_oracle_gap_closed: sse("oracle")
            .map(|oracle| (paper - learned) / (paper - oracle)),
        hapke_to_morphology_oracle_gap_closed: sse("oracle_morphology")
            .map(|oracle| (paper - learned) / (paper - oracle)),
        feature_matching: matches
            .iter()
            .map(|(name, stats)| (name.to_string(), stats.summary()))
            .collect(),
        crater_level: crater_level.map(|level| CraterLevelUse {
            bands: level.weights(),
            crops_with_frame: framed_crops,
            crops_in_band: crater_level_crops,
        }),
        per_ortho: per_ortho(&per_image),
        breakdowns: breakdowns(&per_image),
        per_image,
    })
}

/// Mean visible fraction of the sun disk over the valid pixels (0 when none is valid).
pub fn lit_fraction(sample: &Sample, valid: &[bool]) -> f64 {
    let (sum, count) = sample
        .sun_lit
        .iter()
        .zip(valid)
        .filter(|(_, &v)| v)
        .fold((0.0, 0usize), |(s, k), (&lit, _)| (s + lit as f64, k + 1));
    if count == 0 {
        0.0
    } else {
        sum / count as f64
    }
}

/// One crop's renderings and what evaluation keeps of them.
struct ScoredImage {
    renderings: Vec<(&'static str, Vec<f64>)>,
    /// Feature-match distances per method, in rendering order.
    match_distances: Vec<(&'static str, Vec<f64>)>,
    image: PerImage,
}

/// Score one crop's renderings against its ground truth ([`image_scores`]) and match its features.
fn score_image(
    sample: &Sample,
    renderings: Vec<(&'static str, Vec<f64>)>,
    matcher: &FeatureMatcher,
    truth_maps: Option<&TruthMaps>,
) -> ScoredImage {
    let (image, truth, valid) = image_scores(sample, &renderings, truth_maps);
    let match_distances = renderings
        .iter()
        .map(|(name, rendered)| {
            (
                *name,
                matcher.match_distances(&truth, rendered, &valid, CROP_PX),
            )
        })
        .collect();
    ScoredImage {
        renderings,
        match_distances,
        image,
    }
}

/// One crop's metrics and brightness level under every rendering, all on the same pixels (where the ground truth
/// and every rendering are defined), with the crop's ground and light. Returns the ground truth and that shared
/// mask too.
pub(crate) fn image_scores<N: AsRef<str>>(
    sample: &Sample,
    renderings: &[(N, Vec<f64>)],
    truth_maps: Option<&TruthMaps>,
) -> (PerImage, Vec<f64>, Vec<bool>) {
    let (truth, mut valid) = truth_and_valid(sample);
    for (_, r) in renderings {
        for (v, x) in valid.iter_mut().zip(r) {
            *v &= x.is_finite();
        }
    }
    let mut metrics = BTreeMap::new();
    let mut level = BTreeMap::new();
    let mean_over_valid = |x: &[f64]| {
        let (sum, n) = x
            .iter()
            .zip(&valid)
            .filter(|(_, &v)| v)
            .fold((0.0, 0usize), |(s, n), (x, _)| (s + x, n + 1));
        sum / n.max(1) as f64
    };
    let truth_mean = mean_over_valid(&truth);
    for (name, rendered) in renderings {
        let name = name.as_ref();
        if truth_mean > 0.0 {
            level.insert(name.to_string(), mean_over_valid(rendered) / truth_mean);
        }
        if let Some(m) = image_metrics(rendered, &truth, &valid, CROP_PX) {
            metrics.insert(name.to_string(), m);
        }
    }
    let ground = truth_maps.and_then(|t| t.ground_at(sample.center_x_m, sample.center_y_m));
    let image = PerImage {
        sample_id: sample.sample_id.clone(),
        ortho_id: sample.ortho_id.clone(),
        incidence_deg: sample.incidence_deg,
        phase_deg: sample.phase_deg,
        terrain_class: ground.map(|g| g.class.name()),
        highland: ground.map(|g| g.highland),
        mean_slope_deg: mean_slope_deg(sample),
        lit_fraction: lit_fraction(sample, &valid),
        within_training_range: None,
        level,
        metrics,
    };
    (image, truth, valid)
}

/// `g2r-train eval` as data: which runs, on which data, with which options, into which directory.
pub struct EvalJob<'a> {
    /// The run, then the further members of a seed ensemble.
    pub runs: &'a [&'a Path],
    pub checkpoint: Checkpoint,
    pub source: &'a dyn SampleSource,
    /// The synthetic world, for the oracle rows (only evaluation reads `truth/`).
    pub world: Option<&'a Path>,
    pub out: &'a Path,
    pub options: EvalOptions,
}

/// Load every run (before anything is written: a mistyped run directory leaves no empty output), fit the uniform
/// baselines on train crops, evaluate, and write `metrics.json`, `metrics.md`, `panels/` and the run's
/// `provenance.json` into `job.out`.
pub fn run_job<B: TrainOps>(job: &EvalJob, device: &B::Device) -> Result<EvalReport> {
    let truth = job.world.map(TruthMaps::open).transpose()?;
    let runs = load_ensemble::<B>(job.runs, job.checkpoint, false, device)?;
    let panel_dir = job.out.join("panels");
    std::fs::create_dir_all(&panel_dir)?;
    let calibration = calibrate(
        job.source,
        job.options.calibration_samples,
        runs[0].config.model,
    )?;
    let panels = job.options.panels;
    let report = evaluate::<B>(
        &runs,
        job.source,
        &job.options,
        calibration,
        truth.as_ref(),
        device,
        |i, sample, renderings| {
            if i < panels {
                let name = format!("{i:03}_{}.png", sample.sample_id.replace(':', "_"));
                panel_png(sample, renderings, &panel_dir.join(name))?;
            }
            Ok(())
        },
    )?;
    write_report(&report, job.out)?;
    dataset::provenance::Provenance::capture().write(&job.out.join("provenance.json"))?;
    Ok(report)
}

/// Write `metrics.json` and `metrics.md` into `out` (atomically).
pub fn write_report(report: &EvalReport, out: &Path) -> Result<()> {
    std::fs::create_dir_all(out)?;
    dataset::files::write_json_atomic(&out.join("metrics.json"), report)?;
    dataset::files::write_text_atomic(&out.join("metrics.md"), &markdown(report))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metrics::ImageMetrics;
    use crate::uniform_fit::{lunar_lambert_render, ScaleFit};
    use dataset::contract::world::TerrainClass;
    use dataset::science::crs::LunarCrs;
    use dataset::science::hapke::lunar_lambert_i_over_f;
    use dataset::science::raster::{
        write_geotiff, BandOut, BandValues, GeoTransform, RasterLayout,
    };

    /// A 4 × 4 truth/ folder: constant Hapke bands, and (optionally) a morphology albedo on `morphology_gsd_m`.
    fn tiny_world(dir: &Path, morphology_gsd_m: Option<f64>) {
        std::fs::create_dir_all(dir.join("truth")).unwrap();
        let crs = LunarCrs::equirectangular(0.0, 0.0);
        let layout = |gsd_m| RasterLayout {
            width: 4,
            height: 4,
            transform: GeoTransform::north_up(1000.0, 2000.0, gsd_m),
            crs: &crs,
            nodata: -1.0,
        };
        let bands: Vec<BandOut> = [0.31f32, 0.25, 0.6, 2.0, 0.07, 23.0]
            .iter()
            .map(|&v| BandOut {
                values: BandValues::Constant(v),
                description: "band",
            })
            .collect();
        write_geotiff(
            &dir.join("truth/hapke_params.tif"),
            &layout(5.0),
            &bands,
            &[],
        )
        .unwrap();
        if let Some(gsd_m) = morphology_gsd_m {
            let w = [0.28f32; 16];
            let band = BandOut {
                values: BandValues::Grid(&w),
                description: "w",
            };
            write_geotiff(
                &dir.join("truth/w_morphology.tif"),
                &layout(gsd_m),
                &[band],
                &[],
            )
            .unwrap();
        }
    }

    #[test]
    fn the_morphology_oracle_swaps_only_the_albedo_and_needs_its_map_on_the_same_grid() {
        let tmp = tempfile::tempdir().unwrap();
        let (x, y) = (1010.0, 1990.0); // inside the 20 m × 20 m maps
        let with = tmp.path().join("with");
        tiny_world(&with, Some(5.0));
        let maps = TruthMaps::open(&with).unwrap();
        assert!(maps.has_morphology());
        let full = maps.params_at(x, y, TrueAlbedo::Full).unwrap();
        let morphology = maps.params_at(x, y, TrueAlbedo::Morphology).unwrap();
        assert!((full.w - 0.31).abs() < 1e-6 && (morphology.w - 0.28).abs() < 1e-6);
        assert_eq!(
            (full.b, full.c, full.b_s0, full.h_s, full.theta_bar_rad),
            (
                morphology.b,
                morphology.c,
                morphology.b_s0,
                morphology.h_s,
                morphology.theta_bar_rad
            )
        );

        // A world generated before the map existed: the full oracle only.
        let without = tmp.path().join("without");
        tiny_world(&without, None);
        let maps = TruthMaps::open(&without).unwrap();
        assert!(!maps.has_morphology());
        assert!(maps.params_at(x, y, TrueAlbedo::Full).is_some());
        assert!(maps.params_at(x, y, TrueAlbedo::Morphology).is_none());

        // On another grid it would sample the wrong ground: refused, naming the file.
        let shifted = tmp.path().join("shifted");
        tiny_world(&shifted, Some(2.5));
        let err = format!("{:#}", TruthMaps::open(&shifted).err().expect("refused"));
        assert!(
            err.contains("w_morphology.tif") && err.contains("regenerate"),
            "{err}"
        );
    }

    /// The oracle on the true DEM reads the true heights at the crop's own 5 m cells: on a tilted plane (which
    /// bilinear sampling reproduces exactly) every cell gets the plane's height at its map position, and the
    /// terrain class and unit come from the class map's cell under the centre.
    #[test]
    fn the_true_dem_replaces_the_crop_heights_cell_by_cell_and_the_class_map_names_the_ground() {
        use dataset::contract::schema::DEM_PX;
        let tmp = tempfile::tempdir().unwrap();
        tiny_world(tmp.path(), None);
        let mut sample = crate::testing::synthetic_samples(1, 5).remove(0);
        sample.center_x_m = 5000.0;
        sample.center_y_m = -3000.0;
        sample.map_to_en = [1.0, 0.0, 0.0, 1.0];
        let crs = LunarCrs::equirectangular(0.0, 0.0);
        // A 2.5 m true DEM around the crop: z = 0.1 x − 0.05 y.
        let (gsd, n) = (2.5, 400);
        let (x0, y0) = (sample.center_x_m - 500.0, sample.center_y_m + 500.0);
        let plane = |x: f64, y: f64| 0.1 * x - 0.05 * y;
        let transform = GeoTransform::north_up(x0, y0, gsd);
        let heights: Vec<f32> = (0..n * n)
            .map(|k| {
                let (x, y) = transform.pixel_center((k % n) as f64, (k / n) as f64);
                plane(x, y) as f32
            })
            .collect();
        let layout = RasterLayout {
            width: n,
            height: n,
            transform,
            crs: &crs,
            nodata: -32768.0,
        };
        let band = |values, description| BandOut {
            values: BandValues::Grid(values),
            description,
        };
        write_geotiff(
            &tmp.path().join(dataset::contract::world::TRUE_DEM),
            &layout,
            &[band(&heights, "h")],
            &[],
        )
        .unwrap();
        // Class map on a 5 m grid: wall west of the centre, rim east; mare north, highland south.
        let class_transform = GeoTransform::north_up(x0, y0, 5.0);
        let (class, highland): (Vec<f32>, Vec<f32>) = (0..200 * 200)
            .map(|k| {
                let (x, y) = class_transform.pixel_center((k % 200) as f64, (k / 200) as f64);
                let class = if x < sample.center_x_m { 2.0 } else { 3.0 };
                (class, if y > sample.center_y_m { 0.1 } else { 0.9 })
            })
            .unzip();
        write_geotiff(
            &tmp.path()
                .join(dataset::contract::world::TRUE_TERRAIN_CLASS),
            &RasterLayout {
                width: 200,
                height: 200,
                transform: class_transform,
                crs: &crs,
                nodata: -1.0,
            },
            &[band(&class, "class"), band(&highland, "highland")],
            &[],
        )
        .unwrap();

        let maps = TruthMaps::open(tmp.path()).unwrap();
        let on_true = maps.on_true_dem(&sample).expect("inside the true DEM");
        let grid = sample.crop_grid();
        for (col, row) in [(0, 0), (64, 65), (DEM_PX - 1, 17), (DEM_PX - 1, DEM_PX - 1)] {
            let (dx, dy) = grid.map_offset(col, row, DEM_PX);
            let expected = plane(sample.center_x_m + dx, sample.center_y_m + dy);
            let got = on_true.dem_m[row * DEM_PX + col] as f64;
            assert!(
                (got - expected).abs() < 1e-3,
                "({col}, {row}): {got} vs {expected}"
            );
        }
        assert_eq!(on_true.image, sample.image, "only the heights change");
        // A crop reaching past the true DEM has no such rendering.
        let mut outside = sample.clone();
        outside.center_x_m += 600.0;
        assert!(maps.on_true_dem(&outside).is_none());

        let ground = |dx: f64, dy: f64| {
            maps.ground_at(sample.center_x_m + dx, sample.center_y_m + dy)
                .unwrap()
        };
        assert_eq!(ground(-20.0, 20.0).class, TerrainClass::TerracedWall);
        assert_eq!(ground(20.0, -20.0).class, TerrainClass::Rim);
        assert!((ground(-20.0, 20.0).highland - 0.1).abs() < 1e-6);
        assert!((ground(20.0, -20.0).highland - 0.9).abs() < 1e-6);
        assert!(maps.ground_at(x0 - 100.0, y0).is_none());
    }

    #[test]
    fn breakdowns_group_by_class_and_bins_and_sum_sse_within_groups() {
        let image =
            |class: &'static str, highland: f64, incidence: f64, learned: f64, paper: f64| {
                let metrics = [("learned", learned), ("hapke_paper", paper)]
                    .into_iter()
                    .map(|(name, sse)| {
                        let m = crate::metrics::ImageMetrics {
                            valid_pixels: 2,
                            sse,
                            mse: sse / 2.0,
                            psnr_db: 0.0,
                            ssim: None,
                        };
                        (name.to_string(), m)
                    })
                    .collect();
                PerImage {
                    sample_id: "M1:0:0".into(),
                    ortho_id: "M1".into(),
                    incidence_deg: incidence,
                    phase_deg: incidence,
                    terrain_class: Some(class),
                    highland: Some(highland),
                    mean_slope_deg: 12.0,
                    lit_fraction: 0.97,
                    within_training_range: None,
                    level: [("learned".to_string(), learned / paper)].into(),
                    metrics,
                }
            };
        let images = [
            image("plains", 0.2, 30.0, 1.0, 2.0),
            image("terraced_wall", 0.8, 70.0, 6.0, 2.0),
            image("plains", 0.9, 40.0, 3.0, 2.0),
            image("terraced_wall", 0.8, 80.0, 2.0, 2.0),
        ];
        let all = breakdowns(&images);
        let by = |name: &str| all.iter().find(|b| b.by == name).unwrap();
        let classes = by("terrain_class");
        // In the data flow's order (floor → plains), not alphabetically.
        let names: Vec<&str> = classes.groups.iter().map(|g| g.group.as_str()).collect();
        assert_eq!(names, ["terraced_wall", "plains"]);
        assert_eq!(classes.groups[0].images, 2);
        assert_eq!(classes.groups[0].sse["learned"], 8.0);
        assert_eq!(classes.groups[0].sse["hapke_paper"], 4.0);
        assert_eq!(classes.groups[1].mean_pixel_mse["learned"], 1.0);
        // Levels average per image: (6/2 + 2/2) / 2 on the wall.
        assert_eq!(classes.groups[0].mean_level["learned"], 2.0);
        let units = by("unit");
        assert_eq!(
            units
                .groups
                .iter()
                .map(|g| (g.group.as_str(), g.images))
                .collect::<Vec<_>>(),
            [("highland", 3), ("mare", 1)]
        );
        let incidence = by("incidence_deg");
        let labels: Vec<(&str, usize)> = incidence
            .groups
            .iter()
            .map(|g| (g.group.as_str(), g.images))
            .collect();
        assert_eq!(
            labels,
            [("0–35", 1), ("35–50", 1), ("65–75", 1), ("≥ 75", 1)]
        );
        assert_eq!(by("mean_slope_deg").groups[0].group, "10–15");
        assert_eq!(by("lit_fraction").groups[0].group, "0.95–0.99");
        // Images without a class map give no class breakdowns, only the geometric ones.
        let bare: Vec<PerImage> = images
            .iter()
            .cloned()
            .map(|mut i| {
                i.terrain_class = None;
                i.highland = None;
                i
            })
            .collect();
        let kinds: Vec<String> = breakdowns(&bare).into_iter().map(|b| b.by).collect();
        assert_eq!(
            kinds,
            [
                "incidence_deg",
                "phase_deg",
                "mean_slope_deg",
                "lit_fraction"
            ]
        );
    }

    #[test]
    fn mean_slope_of_a_tilted_plane_is_its_angle() {
        let mut sample = crate::testing::synthetic_samples(1, 3).remove(0);
        let n = dataset::contract::schema::DEM_PX;
        // 5 m cells rising 5 m per cell eastwards: 45°.
        sample.gsd_m = 5.0;
        sample.dem_m = (0..n * n).map(|k| (k % n) as f32 * 5.0).collect();
        assert!((mean_slope_deg(&sample) - 45.0).abs() < 1e-9);
        let valid = vec![true; sample.sun_lit.len()];
        sample
            .sun_lit
            .iter_mut()
            .enumerate()
            .for_each(|(k, l)| *l = if k % 2 == 0 { 1.0 } else { 0.5 });
        assert!((lit_fraction(&sample, &valid) - 0.75).abs() < 1e-12);
    }

    #[test]
    fn per_ortho_means_group_images_by_their_ortho() {
        let image = |ortho: &str, incidence: f64, learned: f64, scaled: f64| PerImage {
            sample_id: format!("{ortho}:0:0"),
            ortho_id: ortho.into(),
            incidence_deg: incidence,
            phase_deg: incidence,
            terrain_class: None,
            highland: None,
            mean_slope_deg: 0.0,
            lit_fraction: 1.0,
            within_training_range: None,
            level: BTreeMap::new(),
            metrics: [("learned", learned), ("hapke_scaled", scaled)]
                .into_iter()
                .map(|(name, mse)| {
                    let m = ImageMetrics {
                        valid_pixels: 1,
                        sse: mse,
                        mse,
                        psnr_db: 0.0,
                        ssim: None,
                    };
                    (name.to_string(), m)
                })
                .collect(),
        };
        // Interleaved on purpose: grouping must not depend on file order.
        let images = [
            image("M2", 30.0, 1.0, 4.0),
            image("M1", 60.0, 2.0, 2.0),
            image("M2", 50.0, 3.0, 8.0),
        ];
        let groups = per_ortho(&images);
        assert_eq!(groups.len(), 2);
        assert_eq!((groups[0].ortho_id.as_str(), groups[0].images), ("M1", 1));
        assert_eq!((groups[1].ortho_id.as_str(), groups[1].images), ("M2", 2));
        assert_eq!(groups[1].mean_incidence_deg, 40.0);
        assert_eq!(groups[1].mean_pixel_mse["learned"], 2.0);
        assert_eq!(groups[1].mean_pixel_mse["hapke_scaled"], 6.0);
        assert_eq!(groups[0].mean_pixel_mse["hapke_scaled"], 2.0);
    }

    #[test]
    fn scale_fit_recovers_a_known_scale_and_ignores_invalid_pixels() {
        let x = [1.0, 2.0, 3.0, 4.0];
        let t = [0.5, 1.0, 1.5, 99.0];
        let mut fit = ScaleFit::default();
        fit.add(&x, &t, &[true, true, true, false]);
        assert!((fit.scale() - 0.5).abs() < 1e-15);
        assert_eq!(ScaleFit::default().scale(), 0.0);
    }

    #[test]
    fn lunar_lambert_render_is_lit_fraction_times_ll() {
        let sample = crate::testing::synthetic_samples(1, 4).remove(0);
        let rendered = lunar_lambert_render(&sample);
        let geometry = sample.pixel_geometry();
        for k in [0, 777, 16_383] {
            let c = &geometry[k].cosines;
            let expected =
                sample.sun_lit[k] as f64 * lunar_lambert_i_over_f(1.0, c.cos_i, c.cos_e, c.cos_g);
            assert_eq!(rendered[k], expected);
        }
    }
}

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

mod methods;
mod panels;
mod tables;
mod truth;

pub use methods::*;
pub use panels::*;
pub use tables::*;
pub use truth::*;

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{bail, Context, Result};
use dataset::schema::{Sample, Split, CROP_PX};

use crate::baseline::truth_and_valid;
use crate::calibration::{calibrate, Calibration};
use crate::data::{for_each_sample_group, SampleSource};
use crate::features::{FeatureMatcher, MatchStats};
use crate::kernels::TrainOps;
use crate::metrics::{image_metrics, MetricsAccumulator};
use crate::prediction::predict_ensemble;
use crate::run::{load_ensemble, Checkpoint, TrainedRun};

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
    }
    let mut accumulators: BTreeMap<&str, MetricsAccumulator> = BTreeMap::new();
    let matcher = FeatureMatcher::default();
    let mut matches: BTreeMap<&str, MatchStats> = BTreeMap::new();
    let mut per_image = Vec::new();
    let mut failure: Option<anyhow::Error> = None;
    for_each_sample_group(source, options.split, options.max_samples, |samples| {
        for chunk in samples.chunks(options.batch_size) {
            let learned = predict_ensemble(runs, chunk, options.symmetry_mean, device);
            for (i, sample) in chunk.iter().enumerate() {
                let px = CROP_PX * CROP_PX;
                let renderings = method_renderings(
                    sample,
                    &learned[i * px..(i + 1) * px],
                    &calibration,
                    truth_maps,
                );
                let (truth, mut valid) = truth_and_valid(sample);
                // Compare every method on the same pixels: where all of them are defined.
                for (_, r) in &renderings {
                    for (v, x) in valid.iter_mut().zip(r) {
                        *v &= x.is_finite();
                    }
                }
                let mut metrics = BTreeMap::new();
                for (name, rendered) in &renderings {
                    matches
                        .entry(name)
                        .or_default()
                        .add_distances(&matcher.match_distances(&truth, rendered, &valid, CROP_PX));
                    if let Some(m) = image_metrics(rendered, &truth, &valid, CROP_PX) {
                        accumulators
                            .entry(name)
                            .or_default()
                            .add(rendered, &truth, &valid, CROP_PX);
                        metrics.insert(name.to_string(), m);
                    }
                }
                if failure.is_none() {
                    if let Err(e) = on_image(per_image.len(), sample, &renderings) {
                        failure = Some(e);
                    }
                }
                per_image.push(PerImage {
                    sample_id: sample.sample_id.clone(),
                    ortho_id: sample.ortho_id.clone(),
                    incidence_deg: sample.incidence_deg,
                    metrics,
                });
            }
        }
    })?;
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
            accumulators.get(name).map(|a| MethodResult {
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
        per_ortho: per_ortho(&per_image),
        per_image,
    })
}

/// Write `metrics.json` and `metrics.md` into `out` (atomically).
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
/// baselines on train crops, evaluate, and write `metrics.json`, `metrics.md` and `panels/` into `job.out`.
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
    Ok(report)
}

pub fn write_report(report: &EvalReport, out: &Path) -> Result<()> {
    std::fs::create_dir_all(out)?;
    dataset::manifest::write_json_atomic(&out.join("metrics.json"), report)?;
    dataset::manifest::write_text_atomic(&out.join("metrics.md"), &markdown(report))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calibration::{lunar_lambert_render, ScaleFit};
    use crate::metrics::ImageMetrics;
    use dataset::crs::LunarCrs;
    use dataset::hapke::lunar_lambert_i_over_f;
    use dataset::raster::{write_geotiff, BandOut, BandValues, GeoTransform, RasterLayout};

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

    #[test]
    fn per_ortho_means_group_images_by_their_ortho() {
        let image = |ortho: &str, incidence: f64, learned: f64, scaled: f64| PerImage {
            sample_id: format!("{ortho}:0:0"),
            ortho_id: ortho.into(),
            incidence_deg: incidence,
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

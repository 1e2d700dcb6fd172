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

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{bail, Context, Result};
use dataset::brdf::BrdfModel;
use dataset::geometry::PixelGeometry;
use dataset::hapke::{hapke_i_over_f, lunar_lambert_i_over_f, HFunction, HapkeParams};
use dataset::raster::{read_bands, Raster};
use dataset::schema::{Sample, CROP_PX};

use crate::baseline::{hapke_render, normalise_like_paper, truth_and_valid};
use crate::data::{for_each_sample_group, SampleSource};
use crate::features::{FeatureMatcher, MatchStats, MatchSummary};
use crate::kernels::TrainOps;
use crate::metrics::{image_metrics, AggregateMetrics, ImageMetrics, MetricsAccumulator};
use crate::training::{predict_ensemble, TrainedRun};

/// The methods, in report order.
pub const METHODS: [(&str, &str); 8] = [
    ("learned", "U-Net → SVBRDF parameters → renderer layer"),
    (
        "learned_paper_norm",
        "the learned rendering with the same per-image affine normalisation as hapke_paper (peeks at the GT; \
         compares the two on equal terms: spatial pattern only, no per-image brightness level)",
    ),
    (
        "model_uniform",
        "the run's BRDF model with one parameter set for the whole Moon, least squares on train crops (what the \
         spatial variation has to beat)",
    ),
    (
        "hapke_paper",
        "uniform Hapke, affine-normalised per image to the GT's mean and range (peeks at the GT, as the paper did)",
    ),
    ("hapke_scaled", "uniform Hapke × one scale fitted on train crops (honest)"),
    ("lunar_lambert", "Lunar-Lambert with one albedo fitted on train crops (honest)"),
    ("oracle", "the world's true Hapke maps on the delivered DEM (needs --world)"),
    (
        "oracle_morphology",
        "the oracle without the world's independent albedo component, which no terrain predicts (units, \
         freshness, slope and melt only; needs --world)",
    ),
];

#[derive(Debug, Clone)]
pub struct EvalOptions {
    pub split: String,
    pub max_samples: Option<usize>,
    pub batch_size: usize,
    /// Train crops used to fit the honest scales.
    pub calibration_samples: usize,
    /// PNG panels written for the first images.
    pub panels: usize,
    /// Render "learned" (in every ensemble member) as the mean of the network's 8 dihedral views
    /// ([`crate::training::predict_images_symmetry_mean`]): 8× the network and renderer time.
    pub symmetry_mean: bool,
}

/// The world's true Hapke parameter maps (`truth/hapke_params.tif`: w, b, c, B_S0, h_S, θ̄ in degrees), and w
/// without its independent component (`truth/w_morphology.tif`, on the same grid) when the world has it.
pub struct TruthMaps {
    bands: Vec<Raster>,
    w_morphology: Option<Raster>,
}

/// Which true albedo an oracle rendering uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TrueAlbedo {
    /// The albedo the orthos were rendered with.
    Full,
    /// Without the independent component (`truth/w_morphology.tif`).
    Morphology,
}

impl TruthMaps {
    pub fn open(world: &Path) -> Result<Self> {
        let path = world.join("truth").join("hapke_params.tif");
        if !path.exists() {
            bail!(
                "{}: missing: --world must be a synthetic world directory (g2r-pipeline synth --out) with truth/",
                path.display()
            );
        }
        let bands = read_bands(&path)?;
        if bands.len() != 6 {
            bail!(
                "{}: {} bands, expected 6 (w, b, c, B_S0, h_S, theta_bar_deg); regenerate the world",
                path.display(),
                bands.len()
            );
        }
        // Worlds generated before the morphology map existed have only the full oracle.
        let morphology_path = world.join("truth").join("w_morphology.tif");
        let w_morphology = if morphology_path.exists() {
            let morphology = read_bands(&morphology_path)?.remove(0);
            let full = &bands[0];
            if (morphology.width, morphology.height) != (full.width, full.height)
                || morphology.transform != full.transform
            {
                bail!(
                    "{}: not on the grid of {}: regenerate the world",
                    morphology_path.display(),
                    path.display()
                );
            }
            Some(morphology)
        } else {
            None
        };
        Ok(Self {
            bands,
            w_morphology,
        })
    }

    /// Parameters at map point (x, y), bilinear; `None` outside the maps or on nodata (or when `albedo` asks
    /// for a map the world does not have).
    pub fn params_at(&self, x: f64, y: f64, albedo: TrueAlbedo) -> Option<HapkeParams> {
        let first = &self.bands[0];
        let (col, row) = first.transform.map_to_pixel(x, y);
        // Bilinear sampling clamps at the edges: points beyond the outer pixel edges are outside the maps.
        if col < -0.5
            || row < -0.5
            || col > first.width as f64 - 0.5
            || row > first.height as f64 - 0.5
        {
            return None;
        }
        let mut v: Vec<f64> = self
            .bands
            .iter()
            .map(|b| b.bilinear(col, row) as f64)
            .collect();
        if albedo == TrueAlbedo::Morphology {
            v[0] = self.w_morphology.as_ref()?.bilinear(col, row) as f64;
        }
        v.iter().all(|x| x.is_finite()).then(|| HapkeParams {
            w: v[0],
            b: v[1],
            c: v[2],
            b_s0: v[3],
            h_s: v[4],
            theta_bar_rad: v[5].to_radians(),
            porosity_k: 1.0,
        })
    }

    /// Whether the world carries the morphology albedo (the `oracle_morphology` method).
    pub fn has_morphology(&self) -> bool {
        self.w_morphology.is_some()
    }

    /// I/F of a crop under the true maps (lit fraction × Hapke); pixels outside the maps render NaN.
    pub fn render(&self, sample: &Sample, albedo: TrueAlbedo) -> Vec<f64> {
        let grid = sample.crop_grid();
        sample
            .pixel_geometry()
            .iter()
            .zip(&sample.sun_lit)
            .enumerate()
            .map(|(k, (g, &lit))| {
                let (dx, dy) = grid.map_offset(k % CROP_PX, k / CROP_PX, CROP_PX);
                let c = &g.cosines;
                self.params_at(sample.center_x_m + dx, sample.center_y_m + dy, albedo)
                    .map_or(f64::NAN, |p| {
                        lit as f64
                            * hapke_i_over_f(&p, c.cos_i, c.cos_e, c.cos_g, HFunction::Hapke2002)
                    })
            })
            .collect()
    }
}

/// Lunar-Lambert I/F with albedo 1 (lit fraction × LL): scale by the fitted albedo.
pub fn lunar_lambert_render(sample: &Sample) -> Vec<f64> {
    lunar_lambert_from_geometry(&sample.pixel_geometry(), &sample.sun_lit, 1.0)
}

/// Lunar-Lambert I/F with `albedo` on precomputed geometry.
pub fn lunar_lambert_from_geometry(
    geometry: &[PixelGeometry],
    sun_lit: &[f32],
    albedo: f64,
) -> Vec<f64> {
    geometry
        .iter()
        .zip(sun_lit)
        .map(|(g, &lit)| {
            let c = &g.cosines;
            lit as f64 * lunar_lambert_i_over_f(albedo, c.cos_i, c.cos_e, c.cos_g)
        })
        .collect()
}

/// Least-squares scale s minimising Σ (s·x − t)² over valid pixels: Σ x·t / Σ x².
#[derive(Debug, Default, Clone, Copy)]
pub struct ScaleFit {
    xt: f64,
    xx: f64,
}

impl ScaleFit {
    pub fn add(&mut self, rendered: &[f64], truth: &[f64], valid: &[bool]) {
        for ((&x, &t), &ok) in rendered.iter().zip(truth).zip(valid) {
            if ok && x.is_finite() {
                self.xt += x * t;
                self.xx += x * x;
            }
        }
    }
    pub fn scale(&self) -> f64 {
        if self.xx > 0.0 {
            self.xt / self.xx
        } else {
            0.0
        }
    }
}

/// Honest single scales fitted on train crops.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Calibration {
    pub samples: usize,
    pub hapke_scale: f64,
    pub lunar_lambert_albedo: f64,
    pub model: BrdfModel,
    /// One coefficient per term of `model` (no activation), least squares over the same crops.
    pub model_uniform: Vec<f64>,
}

/// Per-pixel design rows of `model`: lit × term_k where the pixel faces sun and camera, else 0.
fn model_terms(geometry: &[PixelGeometry], sun_lit: &[f32], model: BrdfModel) -> Vec<[f64; 4]> {
    geometry
        .iter()
        .zip(sun_lit)
        .map(|(g, &lit)| {
            if g.cosines.cos_i <= 0.0 || g.cosines.cos_e <= 0.0 {
                [0.0; 4]
            } else {
                model
                    .terms(&g.cosines, &g.half_diff)
                    .map(|t| t * lit as f64)
            }
        })
        .collect()
}

/// I/F from precomputed geometry with one coefficient set for `model` (see [`Calibration::model_uniform`]).
pub fn model_uniform_from_geometry(
    geometry: &[PixelGeometry],
    sun_lit: &[f32],
    model: BrdfModel,
    coefficients: &[f64],
) -> Vec<f64> {
    model_terms(geometry, sun_lit, model)
        .iter()
        .map(|t| t.iter().zip(coefficients).map(|(t, c)| t * c).sum())
        .collect()
}

/// A crop rendered with one coefficient set for `model`.
pub fn model_uniform_render(sample: &Sample, model: BrdfModel, coefficients: &[f64]) -> Vec<f64> {
    model_uniform_from_geometry(
        &sample.pixel_geometry(),
        &sample.sun_lit,
        model,
        coefficients,
    )
}

/// Solve the small symmetric system `a x = b` (Gaussian elimination with partial pivoting); singular directions
/// (a term that is zero on every pixel) get 0.
fn solve(mut a: Vec<Vec<f64>>, mut b: Vec<f64>) -> Vec<f64> {
    let n = b.len();
    for col in 0..n {
        let pivot = (col..n)
            .max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))
            .expect("non-empty");
        a.swap(col, pivot);
        b.swap(col, pivot);
        if a[col][col].abs() < 1e-300 {
            continue;
        }
        for row in col + 1..n {
            let f = a[row][col] / a[col][col];
            let (upper, lower) = a.split_at_mut(row);
            for (x, p) in lower[0][col..].iter_mut().zip(&upper[col][col..]) {
                *x -= f * p;
            }
            b[row] -= f * b[col];
        }
    }
    let mut x = vec![0.0; n];
    for row in (0..n).rev() {
        if a[row][row].abs() < 1e-300 {
            continue;
        }
        let rest: f64 = (row + 1..n).map(|k| a[row][k] * x[k]).sum();
        x[row] = (b[row] - rest) / a[row][row];
    }
    x
}

pub fn calibrate(
    source: &dyn SampleSource,
    samples: usize,
    model: BrdfModel,
) -> Result<Calibration> {
    let params = HapkeParams::lunar_typical();
    let (mut hapke, mut ll, mut seen) = (ScaleFit::default(), ScaleFit::default(), 0);
    let p = model.param_count();
    let (mut ata, mut atb) = (vec![vec![0.0; p]; p], vec![0.0; p]);
    for_each_sample_group(source, "train", Some(samples), |group| {
        for s in group {
            let (truth, valid) = truth_and_valid(s);
            hapke.add(&hapke_render(s, &params), &truth, &valid);
            ll.add(&lunar_lambert_render(s), &truth, &valid);
            let rows = model_terms(&s.pixel_geometry(), &s.sun_lit, model);
            for ((row, &t), &ok) in rows.iter().zip(&truth).zip(&valid) {
                if ok {
                    for i in 0..p {
                        atb[i] += row[i] * t;
                        for j in 0..p {
                            ata[i][j] += row[i] * row[j];
                        }
                    }
                }
            }
            seen += 1;
        }
    })?;
    if seen == 0 {
        bail!(
            "{}: no train crops to fit the honest baselines on: the train split is empty or --calibration-samples is 0",
            source.describe()
        );
    }
    Ok(Calibration {
        samples: seen,
        hapke_scale: hapke.scale(),
        lunar_lambert_albedo: ll.scale(),
        model,
        model_uniform: solve(ata, atb),
    })
}

/// One image's metrics per method.
#[derive(Debug, Clone, serde::Serialize)]
pub struct PerImage {
    pub sample_id: String,
    pub ortho_id: String,
    pub incidence_deg: f64,
    pub metrics: BTreeMap<String, ImageMetrics>,
}

/// One ortho's share of an evaluation: mean per-image pixel MSE per method over its images. Shards are written
/// ortho by ortho and each ortho has its own sun and view, so this shows whether a method's error is spread evenly
/// or sits in a few acquisitions (e.g. a brightness level a uniform model cannot match).
#[derive(Debug, Clone, serde::Serialize)]
pub struct PerOrtho {
    pub ortho_id: String,
    pub images: usize,
    pub mean_incidence_deg: f64,
    pub mean_pixel_mse: BTreeMap<String, f64>,
}

/// Group per-image results by ortho (sorted by ortho id; methods as they appear in the images).
pub fn per_ortho(per_image: &[PerImage]) -> Vec<PerOrtho> {
    let mut groups: BTreeMap<&str, Vec<&PerImage>> = BTreeMap::new();
    for image in per_image {
        groups.entry(&image.ortho_id).or_default().push(image);
    }
    groups
        .into_iter()
        .map(|(ortho_id, images)| {
            let n = images.len() as f64;
            let mut sums: BTreeMap<String, f64> = BTreeMap::new();
            for image in &images {
                for (method, m) in &image.metrics {
                    *sums.entry(method.clone()).or_default() += m.mse;
                }
            }
            PerOrtho {
                ortho_id: ortho_id.to_string(),
                images: images.len(),
                mean_incidence_deg: images.iter().map(|i| i.incidence_deg).sum::<f64>() / n,
                mean_pixel_mse: sums.into_iter().map(|(k, v)| (k, v / n)).collect(),
            }
        })
        .collect()
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct MethodResult {
    pub name: String,
    pub description: String,
    pub aggregate: AggregateMetrics,
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct EvalReport {
    pub split: String,
    pub run_model: String,
    pub images: usize,
    /// "learned" is the mean of the network's 8 dihedral views (`--symmetry-mean`).
    pub learned_symmetry_mean: bool,
    /// Runs whose renderings "learned" averages (1: a single run; more: `--ensemble`).
    pub learned_ensemble_runs: usize,
    /// The checkpoint each run's network came from, relative to its run directory (`--checkpoint`).
    pub learned_checkpoints: Vec<String>,
    pub calibration: Calibration,
    pub methods: Vec<MethodResult>,
    /// Mean per-image SSE of learned over hapke_paper (the paper's −38 % is 0.62).
    pub learned_over_hapke_paper_sse: f64,
    /// Same against the honest scaled Hapke.
    pub learned_over_hapke_scaled_sse: f64,
    /// learned_paper_norm over hapke_paper: both normalised per image with the GT, so this compares only the
    /// spatial pattern within each crop, not the per-image brightness level a DEM cannot always tell.
    pub learned_over_hapke_both_paper_norm_sse: f64,
    /// (SSE_hapke_paper − SSE_learned) / (SSE_hapke_paper − SSE_oracle), when the oracle ran.
    pub hapke_to_oracle_gap_closed: Option<f64>,
    /// The same against `oracle_morphology` (the oracle without the albedo no terrain predicts), when it ran.
    pub hapke_to_morphology_oracle_gap_closed: Option<f64>,
    /// FAST + BRIEF reciprocal matches between the ground truth and each method's rendering (see
    /// [`crate::features`]); the paper's Table 1 used a learned matcher.
    pub feature_matching: BTreeMap<String, MatchSummary>,
    pub per_ortho: Vec<PerOrtho>,
    pub per_image: Vec<PerImage>,
}

/// Renderings of one sample by every method that runs (learned supplied by the caller, batched).
fn method_renderings(
    sample: &Sample,
    learned: &[f64],
    calibration: &Calibration,
    truth_maps: Option<&TruthMaps>,
) -> Vec<(&'static str, Vec<f64>)> {
    let (truth, valid) = truth_and_valid(sample);
    let hapke = hapke_render(sample, &HapkeParams::lunar_typical());
    let mut out = vec![
        ("learned", learned.to_vec()),
        (
            "learned_paper_norm",
            normalise_like_paper(learned, &truth, &valid),
        ),
        (
            "model_uniform",
            model_uniform_render(sample, calibration.model, &calibration.model_uniform),
        ),
        ("hapke_paper", normalise_like_paper(&hapke, &truth, &valid)),
        (
            "hapke_scaled",
            hapke.iter().map(|x| x * calibration.hapke_scale).collect(),
        ),
        (
            "lunar_lambert",
            lunar_lambert_render(sample)
                .iter()
                .map(|x| x * calibration.lunar_lambert_albedo)
                .collect(),
        ),
    ];
    if let Some(maps) = truth_maps {
        out.push(("oracle", maps.render(sample, TrueAlbedo::Full)));
        if maps.has_morphology() {
            out.push((
                "oracle_morphology",
                maps.render(sample, TrueAlbedo::Morphology),
            ));
        }
    }
    out
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
    for_each_sample_group(source, &options.split, options.max_samples, |samples| {
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
        split: options.split.clone(),
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

/// The Markdown table of a report.
pub fn markdown(report: &EvalReport) -> String {
    let mut text = format!(
        "# Evaluation on the {} split ({} images, model {})\n\n",
        report.split, report.images, report.run_model
    );
    text.push_str(&format!(
        "learned: checkpoint {}.\n\n",
        report.learned_checkpoints.join(", ")
    ));
    if report.learned_ensemble_runs > 1 {
        text.push_str(&format!(
            "learned: mean of {} trained runs' renderings (--ensemble).\n\n",
            report.learned_ensemble_runs
        ));
    }
    if report.learned_symmetry_mean {
        text.push_str(
            "learned: mean of the network's 8 dihedral views (turns and mirrors of the terrain, maps turned back, \
             renderings averaged; --symmetry-mean).\n\n",
        );
    }
    // The notes above go before the table: a line between its header and rows would end it.
    text.push_str(
        "| method | per-image SSE (paper's \"MSE\") | pixel MSE | PSNR dB | SSIM | what it is |\n|---|---|---|---|---|---|\n",
    );
    for m in &report.methods {
        let a = &m.aggregate;
        text.push_str(&format!(
            "| {} | {:.4e} | {:.4e} | {:.2} | {} | {} |\n",
            m.name,
            a.sse,
            a.pixel_mse,
            a.psnr_db,
            a.ssim.map_or("—".into(), |s| format!("{s:.4}")),
            m.description
        ));
    }
    text.push_str(&format!(
        "\nLearned / paper-normalised Hapke SSE: **{:.3}** (the paper: 0.62). Learned / honest scaled Hapke: {:.3}.\n",
        report.learned_over_hapke_paper_sse, report.learned_over_hapke_scaled_sse
    ));
    text.push_str(&format!(
        "Both normalised per image like the paper (learned_paper_norm / hapke_paper): {:.3}.\n",
        report.learned_over_hapke_both_paper_norm_sse
    ));
    match report.hapke_to_oracle_gap_closed {
        Some(g) => text.push_str(&format!(
            "Share of the Hapke → oracle gap closed: **{:.1} %** (goal ≥ 75 %).\n",
            g * 100.0
        )),
        None => {
            text.push_str("No oracle (run with --world WORLD_DIR to compare with the true maps).\n")
        }
    }
    if let Some(g) = report.hapke_to_morphology_oracle_gap_closed {
        text.push_str(&format!(
            "Share of the Hapke → oracle_morphology gap closed: **{:.1} %** (the oracle without the albedo \
             component no terrain predicts).\n",
            g * 100.0
        ));
    }
    text.push_str(
        "\n## Feature-matching consistency\n\nFAST-9 corners + 256-bit BRIEF on the GT and on each rendering (both \
         stretched with the GT's 2–98 % range), reciprocal nearest neighbours within 64 bits; images are co-registered, \
         so a correct match lies at 0 px. (The paper's Table 1 used a learned matcher, not available here.)\n\n\
         | method | matches/image | ≤ 1 px | ≤ 3 px | ≤ 5 px | mean error px |\n|---|---|---|---|---|---|\n",
    );
    for m in &report.methods {
        if let Some(f) = report.feature_matching.get(&m.name) {
            text.push_str(&format!(
                "| {} | {:.1} | {:.1} % | {:.1} % | {:.1} % | {:.2} |\n",
                m.name,
                f.matches_per_image,
                100.0 * f.within_1px,
                100.0 * f.within_3px,
                100.0 * f.within_5px,
                f.mean_error_px
            ));
        }
    }
    text.push_str(&per_ortho_markdown(report));
    text.push_str(&format!(
        "\nUniform {} coefficients (least squares on the same crops): {:?}.\n",
        report.calibration.model.name(),
        report.calibration.model_uniform
    ));
    text.push_str(&format!(
        "\nHonest scales fitted on {} train crops: Hapke × {:.4}, Lunar-Lambert albedo {:.4}. SSIM: 7×7 uniform \
         window, K1 0.01, K2 0.03, data range = each image's GT range, fully valid windows only.\n",
        report.calibration.samples, report.calibration.hapke_scale, report.calibration.lunar_lambert_albedo
    ));
    text
}

/// The per-ortho table: mean per-image pixel MSE of each method, one row per ortho.
fn per_ortho_markdown(report: &EvalReport) -> String {
    let names: Vec<&str> = report.methods.iter().map(|m| m.name.as_str()).collect();
    let mut text = format!(
        "\n## Per ortho\n\nMean per-image pixel MSE over each ortho's images (a per-ortho mean, so it differs from the \
         pooled figures above).\n\n| ortho | images | mean incidence ° | {} |\n|---|---|---|{}\n",
        names.join(" | "),
        "---|".repeat(names.len())
    );
    for o in &report.per_ortho {
        let cells: Vec<String> = names
            .iter()
            .map(|n| {
                o.mean_pixel_mse
                    .get(*n)
                    .map_or("—".into(), |v| format!("{v:.3e}"))
            })
            .collect();
        text.push_str(&format!(
            "| {} | {} | {:.1} | {} |\n",
            o.ortho_id,
            o.images,
            o.mean_incidence_deg,
            cells.join(" | ")
        ));
    }
    text
}

/// A PNG panel: GT | each method | |learned − GT|, every tile stretched with the GT's 2–98 % range, invalid red.
pub fn panel_png(
    sample: &Sample,
    renderings: &[(&'static str, Vec<f64>)],
    path: &Path,
) -> Result<()> {
    let (truth, valid) = truth_and_valid(sample);
    let mut values: Vec<f64> = truth
        .iter()
        .zip(&valid)
        .filter(|(_, &ok)| ok)
        .map(|(&t, _)| t)
        .collect();
    values.sort_by(f64::total_cmp);
    let (lo, hi) = match values.len() {
        0 => (0.0, 1.0),
        n => (values[n * 2 / 100], values[(n - 1) * 98 / 100]),
    };
    let span = (hi - lo).max(1e-12);
    let learned = &renderings[0].1;
    let error: Vec<f64> = learned
        .iter()
        .zip(&truth)
        .map(|(x, t)| (x - t).abs() + lo)
        .collect();
    let mut tiles: Vec<&[f64]> = vec![&truth];
    tiles.extend(renderings.iter().map(|(_, r)| r.as_slice()));
    tiles.push(&error);
    let (edge, gap) = (CROP_PX as u32, 4u32);
    let width = tiles.len() as u32 * (edge + gap) - gap;
    let mut img = image::RgbImage::from_pixel(width, edge, image::Rgb([255, 255, 255]));
    for (t, tile) in tiles.iter().enumerate() {
        for k in 0..CROP_PX * CROP_PX {
            let (x, y) = (
                t as u32 * (edge + gap) + (k % CROP_PX) as u32,
                (k / CROP_PX) as u32,
            );
            let px = if !valid[k] || !tile[k].is_finite() {
                image::Rgb([120, 0, 0])
            } else {
                let v = (((tile[k] - lo) / span).clamp(0.0, 1.0) * 255.0).round() as u8;
                image::Rgb([v, v, v])
            };
            img.put_pixel(x, y, px);
        }
    }
    img.save_with_format(path, image::ImageFormat::Png)
        .with_context(|| format!("writing {}", path.display()))
}

/// Write `metrics.json` and `metrics.md` into `out` (atomically).
pub fn write_report(report: &EvalReport, out: &Path) -> Result<()> {
    std::fs::create_dir_all(out)?;
    dataset::manifest::write_json_atomic(&out.join("metrics.json"), report)?;
    dataset::manifest::write_text_atomic(&out.join("metrics.md"), &markdown(report))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use dataset::crs::LunarCrs;
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
        let sample = crate::bench::synthetic_samples(1, 4).remove(0);
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

//! The evaluation report: per-image and per-ortho results, aggregated tables, Markdown.

use dataset::schema::Split;
use std::collections::BTreeMap;

use crate::calibration::Calibration;
use crate::features::MatchSummary;
use crate::metrics::{AggregateMetrics, ImageMetrics};

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
    pub split: Split,
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

//! The evaluation report: per-image and per-ortho results, aggregated tables, Markdown.

use dataset::contract::schema::Split;
use std::collections::BTreeMap;

use crate::feature_matching::MatchSummary;
use crate::metrics::{AggregateMetrics, ImageMetrics};
use crate::uniform_fit::Calibration;

/// One image's metrics per method, with what is known of its ground and light (the breakdowns' keys).
#[derive(Debug, Clone, serde::Serialize)]
pub struct PerImage {
    pub sample_id: String,
    pub ortho_id: String,
    pub incidence_deg: f64,
    /// Phase angle at the crop centre, degrees.
    pub phase_deg: f64,
    /// Terrain class under the crop's centre (`truth/terrain_class.tif`; `None` without it).
    pub terrain_class: Option<&'static str>,
    /// Highland fraction under the crop's centre (0 mare, 1 highland; `None` without the class map).
    pub highland: Option<f64>,
    /// Mean slope of the delivered DEM over the crop, degrees.
    pub mean_slope_deg: f64,
    /// Mean visible fraction of the sun disk over the crop's valid pixels.
    pub lit_fraction: f64,
    /// Whether every input of the crop lay within the run's training range (`input_range.json`); `None` when the
    /// run keeps none.
    pub within_training_range: Option<bool>,
    /// Each method's mean over the compared pixels divided by the ground truth's: the brightness level it
    /// renders (1 = right on average; the paper's normalisation makes it 1 by construction).
    pub level: BTreeMap<String, f64>,
    pub metrics: BTreeMap<String, ImageMetrics>,
}

/// One group of images in a [`Breakdown`]: how many, each method's mean per-image pixel MSE, and each method's
/// summed per-image SSE (whose ratios are the headline's ratios restricted to the group).
#[derive(Debug, Clone, serde::Serialize)]
pub struct PerGroup {
    pub group: String,
    pub images: usize,
    /// Each method's mean per-image brightness level ([`PerImage::level`]).
    pub mean_level: BTreeMap<String, f64>,
    pub mean_pixel_mse: BTreeMap<String, f64>,
    pub sse: BTreeMap<String, f64>,
}

/// The images grouped by one property (terrain class, unit, incidence, slope, lit fraction, and whether their
/// inputs lay within the run's training range).
#[derive(Debug, Clone, serde::Serialize)]
pub struct Breakdown {
    pub by: String,
    pub groups: Vec<PerGroup>,
}

/// Group images by `key` (groups in key order; images with no key left out).
pub(super) fn group_images<K: Ord + ToString>(
    per_image: &[PerImage],
    key: impl Fn(&PerImage) -> Option<K>,
) -> Vec<PerGroup> {
    let mut groups: BTreeMap<K, Vec<&PerImage>> = BTreeMap::new();
    for image in per_image {
        if let Some(k) = key(image) {
            groups.entry(k).or_default().push(image);
        }
    }
    groups
        .into_iter()
        .map(|(k, images)| {
            let mut sse: BTreeMap<String, f64> = BTreeMap::new();
            let mut mse: BTreeMap<String, f64> = BTreeMap::new();
            let mut level: BTreeMap<String, f64> = BTreeMap::new();
            for image in &images {
                for (method, l) in &image.level {
                    *level.entry(method.clone()).or_default() += l;
                }
                for (method, m) in &image.metrics {
                    *sse.entry(method.clone()).or_default() += m.sse;
                    *mse.entry(method.clone()).or_default() += m.mse;
                }
            }
            let n = images.len() as f64;
            PerGroup {
                group: k.to_string(),
                images: images.len(),
                mean_level: level.into_iter().map(|(k, v)| (k, v / n)).collect(),
                mean_pixel_mse: mse.into_iter().map(|(k, v)| (k, v / n)).collect(),
                sse,
            }
        })
        .collect()
}

/// The label of the bin of `edges` (ascending) holding `x`: "a–b", with the last bin open ("≥ a").
fn bin_label(x: f64, edges: &[f64]) -> (usize, String) {
    let k = edges.iter().rposition(|&e| x >= e).unwrap_or(0);
    match edges.get(k + 1) {
        Some(next) => (k, format!("{}–{}", edges[k], next)),
        None => (k, format!("≥ {}", edges[k])),
    }
}

/// Sortable bin key: the bin's index, shown as its label.
#[derive(PartialEq, Eq, PartialOrd, Ord)]
struct Bin(usize, String);
impl std::fmt::Display for Bin {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.1)
    }
}

/// One number of an image's geometry, to bin by.
type ImageValue = fn(&PerImage) -> f64;

/// Incidence bins, degrees (the worlds' acquisitions span 20–80°).
pub const INCIDENCE_BINS_DEG: [f64; 5] = [0.0, 35.0, 50.0, 65.0, 75.0];
/// Phase-angle bins, degrees.
pub const PHASE_BINS_DEG: [f64; 5] = [0.0, 30.0, 50.0, 70.0, 90.0];
/// Mean-slope bins, degrees.
pub const SLOPE_BINS_DEG: [f64; 5] = [0.0, 5.0, 10.0, 15.0, 20.0];
/// Lit-fraction bins.
pub const LIT_BINS: [f64; 5] = [0.0, 0.5, 0.8, 0.95, 0.99];

/// Every breakdown the images support: by terrain class, by unit and by both (worlds with the class map), and
/// by incidence, mean slope and lit fraction.
pub fn breakdowns(per_image: &[PerImage]) -> Vec<Breakdown> {
    let unit = |i: &PerImage| i.highland.map(super::unit_name);
    let class_order = |name: &str| {
        dataset::contract::world::TerrainClass::ALL
            .iter()
            .position(|c| c.name() == name)
    };
    let binned = |x: f64, edges: &[f64]| {
        let (k, label) = bin_label(x, edges);
        Some(Bin(k, label))
    };
    let mut out = Vec::new();
    if per_image.iter().any(|i| i.terrain_class.is_some()) {
        out.push(Breakdown {
            by: "terrain_class".into(),
            groups: group_images(per_image, |i| {
                i.terrain_class
                    .map(|c| Bin(class_order(c).unwrap_or(usize::MAX), c.to_string()))
            }),
        });
        out.push(Breakdown {
            by: "unit".into(),
            groups: group_images(per_image, unit),
        });
        out.push(Breakdown {
            by: "terrain_class_and_unit".into(),
            groups: group_images(per_image, |i| {
                let c = i.terrain_class?;
                let highland = i.highland?;
                Some(Bin(
                    2 * class_order(c).unwrap_or(usize::MAX)
                        + usize::from(super::unit_name(highland) == "mare"),
                    super::ground_label(c, highland),
                ))
            }),
        });
    }
    let geometric: [(&str, ImageValue, &[f64]); 4] = [
        ("incidence_deg", |i| i.incidence_deg, &INCIDENCE_BINS_DEG),
        ("phase_deg", |i| i.phase_deg, &PHASE_BINS_DEG),
        ("mean_slope_deg", |i| i.mean_slope_deg, &SLOPE_BINS_DEG),
        ("lit_fraction", |i| i.lit_fraction, &LIT_BINS),
    ];
    for (by, value, edges) in geometric {
        out.push(Breakdown {
            by: by.into(),
            groups: group_images(per_image, |i| binned(value(i), edges)),
        });
    }
    if per_image.iter().any(|i| i.within_training_range.is_some()) {
        out.push(Breakdown {
            by: "training_range".into(),
            groups: group_images(per_image, |i| {
                i.within_training_range.map(|within| match within {
                    true => Bin(0, "inputs within".into()),
                    false => Bin(1, "an input outside".into()),
                })
            }),
        });
    }
    out
}

/// One ortho's share of an evaluation: mean per-image pixel MSE per method over its images. Shards are written
/// ortho by ortho and each ortho has its own sun and view, so this shows whether a method's error is spread evenly
/// or sits in a few acquisitions (e.g. a brightness level a uniform model cannot match).
#[derive(Debug, Clone, serde::Serialize)]
pub struct PerOrtho {
    pub ortho_id: String,
    pub images: usize,
    pub mean_incidence_deg: f64,
    pub mean_phase_deg: f64,
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
                mean_phase_deg: images.iter().map(|i| i.phase_deg).sum::<f64>() / n,
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
    /// "learned" fed each crater's relief over diameter clamped into the run's training range
    /// (`--clamp-crater-relief`).
    pub learned_crater_relief_clamped: bool,
    /// The crops whose inputs lay outside the first run's training range (`input_range.json`); `None` when the
    /// run keeps none.
    pub inputs_outside_training_range: Option<crate::data::RangeReport>,
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
    /// [`crate::feature_matching`]); the paper's Table 1 used a learned matcher.
    pub feature_matching: BTreeMap<String, MatchSummary>,
    /// How the run's crater level was applied to "learned", when the run keeps one.
    pub crater_level: Option<CraterLevelUse>,
    pub per_ortho: Vec<PerOrtho>,
    /// The same images grouped by terrain class, unit, incidence, slope and lit fraction.
    pub breakdowns: Vec<Breakdown>,
    pub per_image: Vec<PerImage>,
}

/// Which crops the run's crater level set the level of ([`crate::crater_level`]).
#[derive(Debug, Clone, serde::Serialize)]
pub struct CraterLevelUse {
    /// Each band of crater radii and the weight that moved its crops' level (0: left as the network's).
    pub bands: Vec<crate::crater_level::BandWeight>,
    /// Crops that carry a crater frame (the dataset was published with a crater catalogue).
    pub crops_with_frame: usize,
    /// Of them, those in the level's band of ρ: their "learned" has the level applied.
    pub crops_in_band: usize,
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
    if report.learned_crater_relief_clamped {
        text.push_str(
            "learned: each crater's relief over diameter clamped into the run's training range (--clamp-crater-relief).\n\n",
        );
    }
    if let Some(range) = &report.inputs_outside_training_range {
        text.push_str(&format!("Inputs: {}.\n\n", range.summary()));
    }
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
    if let Some(level) = &report.crater_level {
        text.push_str(&format!(
            "learned: the network with the run's crater level (weights by zone of ρ: {}) on {} of {} crops ({} with \
             a crater frame); learned_network is the network alone.\n\n",
            level
                .bands
                .iter()
                .map(|b| format!("{:.3}–{:.3}: {}", b.rho_min, b.rho_max, b.weight))
                .collect::<Vec<_>>()
                .join(", "),
            level.crops_in_band,
            report.images,
            level.crops_with_frame
        ));
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
    text.push_str(&breakdowns_markdown(report));
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
         pooled figures above).\n\n| ortho | images | mean incidence ° | mean phase ° | {} |\n|---|---|---|---|{}\n",
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
            "| {} | {} | {:.1} | {:.1} | {} |\n",
            o.ortho_id,
            o.images,
            o.mean_incidence_deg,
            o.mean_phase_deg,
            cells.join(" | ")
        ));
    }
    text
}

/// One table per breakdown: images, learned / paper-Hapke SSE within the group, each group's share of learned's
/// summed SSE, and the mean per-image pixel MSE of every method.
fn breakdowns_markdown(report: &EvalReport) -> String {
    let names: Vec<&str> = report.methods.iter().map(|m| m.name.as_str()).collect();
    let mut text = String::from(
        "\n## Where the error sits\n\nThe images grouped by the ground under the crop's centre (the world's \
         `truth/terrain_class.tif`), by incidence, by the delivered DEM's mean slope and by the lit fraction. \
         *learned / paper* is the ratio of summed per-image SSE within the group (the headline's ratio, restricted \
         to it); *share* is the group's part of learned's summed SSE; *learned level* the mean \
         per-image ratio of learned's mean brightness to the ground truth's (1: right on average); then the mean \
         per-image pixel MSE.\n",
    );
    let total_learned: f64 = report
        .per_image
        .iter()
        .filter_map(|i| i.metrics.get("learned").map(|m| m.sse))
        .sum();
    for b in &report.breakdowns {
        text.push_str(&format!(
            "\n### By {}\n\n| {} | images | learned / paper | share | learned level | {} |\n|---|---|---|---|---|{}\n",
            b.by,
            b.by,
            names.join(" | "),
            "---|".repeat(names.len())
        ));
        for g in &b.groups {
            let ratio = match (g.sse.get("learned"), g.sse.get("hapke_paper")) {
                (Some(l), Some(p)) if *p > 0.0 => format!("{:.3}", l / p),
                _ => "—".into(),
            };
            let share = g
                .sse
                .get("learned")
                .filter(|_| total_learned > 0.0)
                .map_or("—".into(), |l| {
                    format!("{:.1} %", 100.0 * l / total_learned)
                });
            let cells: Vec<String> = names
                .iter()
                .map(|n| {
                    g.mean_pixel_mse
                        .get(*n)
                        .map_or("—".into(), |v| format!("{v:.3e}"))
                })
                .collect();
            let level = g
                .mean_level
                .get("learned")
                .map_or("—".into(), |l| format!("{l:.3}"));
            text.push_str(&format!(
                "| {} | {} | {} | {} | {} | {} |\n",
                g.group,
                g.images,
                ratio,
                share,
                level,
                cells.join(" | ")
            ));
        }
    }
    text
}

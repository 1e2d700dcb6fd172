//! `g2r-train model-choice`: which BRDF model each kind of ground needs ("model only what a scene needs").
//!
//! For every crop of a split and every candidate model, two renderings bracket what the model can do, with no
//! network in the way:
//! - `form_<m>`: the model-form oracle ([`ModelFormTable`]): at each pixel the best geometry-blind coefficients for
//!   the true material there, fitted over flat-surface orbital geometries. What the model's form attains whatever
//!   a network puts in its maps: a model whose form error is far above another's is not worth training in its
//!   place. Not a strict lower bound: a steep wall's local geometries leave the fit's range;
//! - `uniform_<m>`: one coefficient set for the whole Moon (least squares on train crops): the model with no spatial
//!   variation at all.
//!
//! `oracle` (the true Hapke maps) and `hapke_paper` (the paper's baseline) are rendered beside them as yardsticks.
//! Per ground (terrain class and unit), the choice is the cheapest candidate whose form error is within a tolerance
//! of the best candidate's: fewest parameter maps (what the network must predict), and at equal count the one
//! without Hapke's H-functions (about 20× the render cost of a cosine polynomial).

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{bail, Context, Result};
use dataset::contract::schema::{Sample, Split};
use dataset::science::brdf::BrdfModel;
use dataset::science::hapke::HapkeParams;
use rayon::prelude::*;

use crate::baseline::{hapke_render, normalise_like_paper, truth_and_valid};
use crate::data::{for_each_sample_group, SampleSource};
use crate::uniform_fit::{calibrate, model_uniform_render};

use super::model_form::ModelFormTable;
use super::tables::{breakdowns, group_images, PerImage};
use super::truth::{TrueAlbedo, TruthMaps};

/// A candidate's cost, in the order the choice compares it: parameter maps, then whether it evaluates Hapke.
pub fn model_cost(model: BrdfModel) -> (usize, bool) {
    (
        model.param_count(),
        matches!(model, BrdfModel::H1 | BrdfModel::H3),
    )
}

/// The cheapest model whose SSE is at most `(1 + tolerance)` × the smallest ([`model_cost`], then SSE); `None`
/// when no SSE is finite.
pub fn cheapest_within(form_sse: &[(BrdfModel, f64)], tolerance: f64) -> Option<BrdfModel> {
    let best = form_sse
        .iter()
        .map(|&(_, sse)| sse)
        .filter(|sse| sse.is_finite())
        .min_by(f64::total_cmp)?;
    form_sse
        .iter()
        .filter(|&&(_, sse)| sse <= best * (1.0 + tolerance))
        .min_by(|a, b| {
            model_cost(a.0)
                .cmp(&model_cost(b.0))
                .then(a.1.total_cmp(&b.1))
        })
        .map(|&(m, _)| m)
}

fn form_method(model: BrdfModel) -> String {
    format!("form_{}", model.name())
}

fn uniform_method(model: BrdfModel) -> String {
    format!("uniform_{}", model.name())
}

#[derive(Debug, Clone)]
pub struct ModelChoiceOptions {
    pub split: Split,
    pub max_samples: Option<usize>,
    /// Train crops for each candidate's uniform fit.
    pub calibration_samples: usize,
    pub candidates: Vec<BrdfModel>,
    /// How far above the best form error a cheaper model may be and still be chosen (0.05 = 5 %).
    pub tolerance: f64,
}

/// One candidate: its cost and its Moon-wide coefficients.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Candidate {
    pub model: String,
    pub parameter_maps: usize,
    pub evaluates_hapke: bool,
    /// The uniform fit's coefficients (no activation), least squares on train crops.
    pub uniform_coefficients: Vec<f64>,
}

/// One ground's errors and choice.
#[derive(Debug, Clone, serde::Serialize)]
pub struct GroundChoice {
    /// "all", or terrain class and unit ("terraced wall, mare").
    pub ground: String,
    pub images: usize,
    /// Every method's summed per-image SSE over the group.
    pub sse: BTreeMap<String, f64>,
    /// Each candidate's form-oracle SSE over `hapke_paper`'s.
    pub form_over_paper_hapke: BTreeMap<String, f64>,
    /// Each candidate's uniform SSE over `hapke_paper`'s.
    pub uniform_over_paper_hapke: BTreeMap<String, f64>,
    /// The candidate with the smallest form error.
    pub best: String,
    /// The cheapest candidate within the tolerance of `best`.
    pub chosen: String,
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct ModelChoiceReport {
    pub split: Split,
    pub images: usize,
    pub tolerance: f64,
    pub candidates: Vec<Candidate>,
    pub grounds: Vec<GroundChoice>,
}

/// Render every crop of the split with each candidate's form oracle and uniform fit (and the yardsticks), group by
/// ground, and choose per ground.
pub fn model_choice(
    source: &dyn SampleSource,
    truth: &TruthMaps,
    options: &ModelChoiceOptions,
) -> Result<ModelChoiceReport> {
    if options.candidates.is_empty() {
        bail!("model-choice needs at least one candidate model (--models m1,m2,l3,h1)");
    }
    if !options.tolerance.is_finite() || options.tolerance < 0.0 {
        bail!(
            "--tolerance {}: must be a finite fraction ≥ 0 (0.05 = 5 %)",
            options.tolerance
        );
    }
    let fixed = truth.fixed_material().context(
        "the world's c, B_S0, h_S and θ̄ vary across its maps, so no model-form oracle can be tabulated \
         (model-choice needs a world written by `g2r-pipeline synth`)",
    )?;
    let mut tables = Vec::new();
    let mut candidates = Vec::new();
    for &model in &options.candidates {
        let table = ModelFormTable::new(model, fixed).with_context(|| {
            format!(
                "model {}: its half-angle terms have no model-form oracle; leave it out of --models",
                model.name()
            )
        })?;
        let calibration = calibrate(source, options.calibration_samples, model)?;
        candidates.push(Candidate {
            model: model.name().to_string(),
            parameter_maps: model.param_count(),
            evaluates_hapke: model_cost(model).1,
            uniform_coefficients: calibration.model_uniform,
        });
        tables.push(table);
    }
    let mut per_image: Vec<PerImage> = Vec::new();
    for_each_sample_group(
        source,
        options.split,
        options.max_samples,
        "model-choice",
        |samples| {
            let scored: Vec<PerImage> = samples
                .par_iter()
                .map(|sample| {
                    let renderings = renderings(sample, truth, &tables, &candidates);
                    super::image_scores(sample, &renderings, Some(truth)).0
                })
                .collect();
            per_image.extend(scored);
        },
    )?;
    if per_image.is_empty() {
        bail!(
            "{}: split '{}' has no samples to compare models on",
            source.describe(),
            options.split
        );
    }
    let mut groups: Vec<(String, usize, BTreeMap<String, f64>)> =
        group_images(&per_image, |_| Some("all"))
            .into_iter()
            .map(|g| (g.group, g.images, g.sse))
            .collect();
    for breakdown in breakdowns(&per_image) {
        if breakdown.by == "terrain_class_and_unit" {
            groups.extend(
                breakdown
                    .groups
                    .into_iter()
                    .map(|g| (g.group, g.images, g.sse)),
            );
        }
    }
    let grounds = groups
        .into_iter()
        .map(|(ground, images, sse)| choose(ground, images, sse, options))
        .collect::<Result<_>>()?;
    Ok(ModelChoiceReport {
        split: options.split,
        images: per_image.len(),
        tolerance: options.tolerance,
        candidates,
        grounds,
    })
}

/// The yardsticks, then each candidate's form oracle and uniform fit.
fn renderings(
    sample: &Sample,
    truth: &TruthMaps,
    tables: &[ModelFormTable],
    candidates: &[Candidate],
) -> Vec<(String, Vec<f64>)> {
    let (ground_truth, valid) = truth_and_valid(sample);
    let hapke = hapke_render(sample, &HapkeParams::lunar_typical());
    let mut out = vec![
        (
            "hapke_paper".to_string(),
            normalise_like_paper(&hapke, &ground_truth, &valid),
        ),
        ("oracle".to_string(), truth.render(sample, TrueAlbedo::Full)),
    ];
    for (table, candidate) in tables.iter().zip(candidates) {
        out.push((
            form_method(table.model),
            truth.render_model_form(sample, table),
        ));
        out.push((
            uniform_method(table.model),
            model_uniform_render(sample, table.model, &candidate.uniform_coefficients),
        ));
    }
    out
}

fn choose(
    ground: String,
    images: usize,
    sse: BTreeMap<String, f64>,
    options: &ModelChoiceOptions,
) -> Result<GroundChoice> {
    let paper = *sse.get("hapke_paper").context("no hapke_paper error")?;
    let of = |method: String| sse.get(&method).copied().unwrap_or(f64::NAN);
    let form: Vec<(BrdfModel, f64)> = options
        .candidates
        .iter()
        .map(|&m| (m, of(form_method(m))))
        .collect();
    let best = form
        .iter()
        .filter(|(_, e)| e.is_finite())
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(m, _)| *m)
        .with_context(|| format!("{ground}: no candidate has a form error"))?;
    let chosen = cheapest_within(&form, options.tolerance).unwrap_or(best);
    let ratios = |method: fn(BrdfModel) -> String| {
        options
            .candidates
            .iter()
            .map(|&m| (m.name().to_string(), of(method(m)) / paper))
            .collect()
    };
    Ok(GroundChoice {
        form_over_paper_hapke: ratios(form_method),
        uniform_over_paper_hapke: ratios(uniform_method),
        best: best.name().to_string(),
        chosen: chosen.name().to_string(),
        ground,
        images,
        sse,
    })
}

/// The report as Markdown: per ground, each candidate's form and uniform error over paper-Hapke, and the choice.
pub fn model_choice_markdown(report: &ModelChoiceReport) -> String {
    let names: Vec<&str> = report.candidates.iter().map(|c| c.model.as_str()).collect();
    let mut md = format!(
        "# Model choice ({} split, {} crops)\n\nPer ground: each candidate's **form** error (the model with the best \
         coefficients for the true material at every pixel: what its form attains, whatever a network learns) and **uniform** \
         error (one coefficient set for the whole Moon), as SSE over paper-Hapke's; `oracle` is the true Hapke \
         maps. Chosen: the cheapest candidate (fewest parameter maps, then no Hapke) whose form error is within \
         {:.0} % of the best.\n\n",
        report.split,
        report.images,
        100.0 * report.tolerance
    );
    md.push_str("| ground | crops | oracle |");
    for n in &names {
        md.push_str(&format!(" form {n} |"));
    }
    for n in &names {
        md.push_str(&format!(" uniform {n} |"));
    }
    md.push_str(" best | chosen |\n|---|---|---|");
    md.push_str(&"---|".repeat(2 * names.len() + 2));
    md.push('\n');
    for g in &report.grounds {
        let oracle = g.sse.get("oracle").copied().unwrap_or(f64::NAN)
            / g.sse.get("hapke_paper").copied().unwrap_or(f64::NAN);
        md.push_str(&format!("| {} | {} | {oracle:.3} |", g.ground, g.images));
        for n in &names {
            md.push_str(&format!(" {:.3} |", g.form_over_paper_hapke[*n]));
        }
        for n in &names {
            md.push_str(&format!(" {:.3} |", g.uniform_over_paper_hapke[*n]));
        }
        md.push_str(&format!(" {} | **{}** |\n", g.best, g.chosen));
    }
    md.push_str("\n| model | parameter maps | evaluates Hapke | uniform coefficients |\n|---|---|---|---|\n");
    for c in &report.candidates {
        md.push_str(&format!(
            "| {} | {} | {} | {:?} |\n",
            c.model, c.parameter_maps, c.evaluates_hapke, c.uniform_coefficients
        ));
    }
    md
}

/// Write `model-choice.json` and `model-choice.md` into `out` (atomically), and the `provenance.json` of this run
/// beside them.
pub fn write_model_choice(report: &ModelChoiceReport, out: &Path) -> Result<()> {
    std::fs::create_dir_all(out)?;
    dataset::files::write_json_atomic(&out.join("model-choice.json"), report)?;
    dataset::files::write_text_atomic(
        &out.join("model-choice.md"),
        &model_choice_markdown(report),
    )?;
    dataset::provenance::Provenance::capture().write(&out.join("provenance.json"))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_cheapest_model_within_the_tolerance_wins_and_hapke_breaks_ties_last() {
        use BrdfModel::*;
        // M2 best; L3 (same 3 maps) 4 % worse; M1 (2 maps) 30 % worse; H1 (1 map) 10 × worse.
        let sse = [(M1, 1.3), (M2, 1.0), (L3, 1.04), (H1, 10.0)];
        assert_eq!(
            cheapest_within(&sse, 0.05),
            Some(M2),
            "at equal cost the smaller error"
        );
        assert_eq!(
            cheapest_within(&sse, 0.5),
            Some(M1),
            "fewer maps within 50 %"
        );
        assert_eq!(cheapest_within(&sse, 10.0), Some(H1), "one map within 10 ×");
        // H3 and M2 both have three maps: the cosine polynomial wins a tie within the tolerance.
        assert_eq!(cheapest_within(&[(H3, 1.0), (M2, 1.01)], 0.05), Some(M2));
        assert_eq!(cheapest_within(&[(H3, 1.0), (M2, 1.2)], 0.05), Some(H3));
        assert_eq!(cheapest_within(&[(M1, f64::NAN)], 0.05), None);
    }

    /// A world of one material, the Moon-wide Hapke, whose images are that Hapke rendered on the crops: H1's best
    /// coefficient is 1 at every pixel, so its form oracle renders the images as exactly as the true-map oracle
    /// does; a cosine polynomial cannot, so H1 is chosen.
    #[test]
    fn on_a_moon_wide_hapke_world_h1_matches_the_oracle_and_is_chosen() {
        use dataset::science::crs::LunarCrs;
        use dataset::science::raster::{
            write_geotiff, BandOut, BandValues, GeoTransform, RasterLayout,
        };
        let tmp = tempfile::tempdir().unwrap();
        let p = HapkeParams::lunar_typical();
        let mut samples = crate::testing::synthetic_samples(6, 11);
        for s in &mut samples {
            s.image = hapke_render(s, &p).iter().map(|&x| x as f32).collect();
        }
        let world = tmp.path().join("world");
        std::fs::create_dir_all(world.join("truth")).unwrap();
        // Every synthetic crop is centred on the origin (128 px of 5 m): a 1 km map holds them.
        assert!(samples
            .iter()
            .all(|s| s.center_x_m == 0.0 && s.center_y_m == 0.0));
        let crs = LunarCrs::equirectangular(0.0, 0.0);
        let layout = RasterLayout {
            width: 200,
            height: 200,
            transform: GeoTransform::north_up(-500.0, 500.0, 5.0),
            crs: &crs,
            nodata: -1.0,
        };
        let values = [p.w, p.b, p.c, p.b_s0, p.h_s, p.theta_bar_rad.to_degrees()];
        let bands: Vec<BandOut> = values
            .iter()
            .map(|&v| BandOut {
                values: BandValues::Constant(v as f32),
                description: "band",
            })
            .collect();
        write_geotiff(&world.join("truth/hapke_params.tif"), &layout, &bands, &[]).unwrap();
        let truth = TruthMaps::open(&world).unwrap();
        let data = tmp.path().join("data");
        crate::testing::write_synthetic_dataset(&data, samples.clone(), samples);
        let source = crate::data::LocalSource::open(&data).unwrap();
        let options = ModelChoiceOptions {
            split: Split::Val,
            max_samples: None,
            calibration_samples: 6,
            candidates: vec![BrdfModel::M1, BrdfModel::M2, BrdfModel::H1],
            tolerance: 0.05,
        };
        let report = model_choice(&source, &truth, &options).unwrap();
        assert_eq!(report.images, 6);
        let all = &report.grounds[0];
        assert_eq!(all.ground, "all");
        let sse = |method: &str| all.sse[method];
        // The images hold f32 I/F: the exact renderings miss them by rounding only.
        let rounding = 1e-12 * 6.0 * 128.0 * 128.0;
        assert!(
            sse("oracle") < rounding && sse("form_h1") < rounding,
            "{:?}",
            all.sse
        );
        assert!(
            sse("form_m1") > 1e3 * rounding && sse("form_m2") > 1e3 * rounding,
            "{:?}",
            all.sse
        );
        assert_eq!((all.best.as_str(), all.chosen.as_str()), ("h1", "h1"));
        // M6's half-angle terms have no form oracle: refused, naming the model and the flag.
        let m6 = ModelChoiceOptions {
            candidates: vec![BrdfModel::M6],
            ..options
        };
        let err = format!("{:#}", model_choice(&source, &truth, &m6).unwrap_err());
        assert!(err.contains("m6") && err.contains("--models"), "{err}");
        let negative = ModelChoiceOptions {
            candidates: vec![BrdfModel::H1],
            tolerance: -0.05,
            ..m6
        };
        let err = format!(
            "{:#}",
            model_choice(&source, &truth, &negative).unwrap_err()
        );
        assert!(err.contains("--tolerance"), "{err}");
        let md = model_choice_markdown(&report);
        assert!(md.contains("| all | 6 |") && md.contains("**h1**"), "{md}");
    }
}

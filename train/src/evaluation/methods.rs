//! The methods `eval` compares, and their renderings of one crop.

use dataset::contract::schema::Sample;
use dataset::science::hapke::HapkeParams;

use crate::baseline::{hapke_render, normalise_like_paper, truth_and_valid};
use crate::crater_level::CraterLevel;
use crate::uniform_fit::{lunar_lambert_render, model_uniform_render, Calibration};

use super::model_form::ModelFormTable;
use super::truth::{TrueAlbedo, TruthMaps};

/// The methods, in report order.
pub const METHODS: [(&str, &str); 11] = [
    (
        "learned",
        "U-Net → SVBRDF parameters → renderer layer (with the run's crater level, when it keeps one)",
    ),
    (
        "learned_network",
        "the network alone, without the run's crater level (only for runs that keep one: crater_level.json)",
    ),
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
    (
        "oracle_true_dem",
        "the oracle on the true DEM averaged to the same 5 m cells (needs --world): oracle − this is the error of the \
         delivered DEM's noise, smoothing and blunders, which no reflectance can fix",
    ),
    (
        "oracle_model_form",
        "the run's BRDF model with, at each pixel, the best geometry-blind coefficients for the true material \
         (least squares over orbital geometries), on the delivered DEM (needs --world): what the model's form \
         costs against `oracle`, whatever its maps hold",
    ),
];

/// Renderings of one sample by every method that runs (learned supplied by the caller, batched; with a crater
/// level, the network's own rendering is `learned_network` and `learned` has the level applied).
pub(super) fn method_renderings(
    sample: &Sample,
    learned: &[f64],
    crater_level: Option<&CraterLevel>,
    calibration: &Calibration,
    truth_maps: Option<&TruthMaps>,
    model_form: Option<&ModelFormTable>,
) -> Vec<(&'static str, Vec<f64>)> {
    let (truth, valid) = truth_and_valid(sample);
    let hapke = hapke_render(sample, &HapkeParams::lunar_typical());
    let mut with_level = learned.to_vec();
    if let Some(level) = crater_level {
        level.apply_to_rendering(sample, &mut with_level, &hapke);
    }
    let paper_norm = normalise_like_paper(&with_level, &truth, &valid);
    let mut out = vec![("learned", with_level)];
    if crater_level.is_some() {
        out.push(("learned_network", learned.to_vec()));
    }
    out.push(("learned_paper_norm", paper_norm));
    out.extend([
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
    ]);
    if let Some(maps) = truth_maps {
        out.push(("oracle", maps.render(sample, TrueAlbedo::Full)));
        if maps.has_morphology() {
            out.push((
                "oracle_morphology",
                maps.render(sample, TrueAlbedo::Morphology),
            ));
        }
        if let Some(on_true_dem) = maps.on_true_dem(sample) {
            out.push((
                "oracle_true_dem",
                maps.render(&on_true_dem, TrueAlbedo::Full),
            ));
        }
        if let Some(table) = model_form {
            out.push(("oracle_model_form", maps.render_model_form(sample, table)));
        }
    }
    out
}

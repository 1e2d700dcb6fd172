//! Uniform fits on train crops: one least-squares coefficient set for a BRDF model (what spatial variation
//! must beat, and the head's start in `fit`), honest scales for uniform Hapke and Lunar-Lambert.

use anyhow::{bail, Result};
use dataset::contract::schema::{Sample, Split};
use dataset::science::brdf::BrdfModel;
use dataset::science::geometry::PixelGeometry;
use dataset::science::hapke::{lunar_lambert_i_over_f, HapkeParams};
use dataset::science::least_squares::{nonnegative_least_squares, solve_small_system};

use crate::baseline::{hapke_render, lit_render, truth_and_valid};
use crate::data::{for_each_sample_group, SampleSource};

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
    lit_render(geometry, sun_lit, |c| {
        lunar_lambert_i_over_f(albedo, c.cos_i, c.cos_e, c.cos_g)
    })
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
    /// The same with every coefficient ≥ 0 ([`dataset::science::least_squares::nonnegative_least_squares`]): equal to `model_uniform` when that
    /// has no negative coefficient.
    pub model_uniform_nonnegative: Vec<f64>,
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

pub fn calibrate(
    source: &dyn SampleSource,
    samples: usize,
    model: BrdfModel,
) -> Result<Calibration> {
    let params = HapkeParams::lunar_typical();
    let (mut hapke, mut ll, mut seen) = (ScaleFit::default(), ScaleFit::default(), 0);
    let p = model.param_count();
    let (mut ata, mut atb) = (vec![vec![0.0; p]; p], vec![0.0; p]);
    for_each_sample_group(source, Split::Train, Some(samples), "calibrate", |group| {
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
        model_uniform_nonnegative: nonnegative_least_squares(&ata, &atb),
        model_uniform: solve_small_system(ata, atb),
    })
}

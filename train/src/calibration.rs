//! Uniform fits on train crops: one least-squares coefficient set for a BRDF model (what spatial variation
//! must beat, and the head's start in `fit`), honest scales for uniform Hapke and Lunar-Lambert.

use anyhow::{bail, Result};
use dataset::contract::schema::{Sample, Split};
use dataset::science::brdf::BrdfModel;
use dataset::science::geometry::PixelGeometry;
use dataset::science::hapke::{lunar_lambert_i_over_f, HapkeParams};

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
    /// The same with every coefficient ≥ 0 ([`nonnegative_least_squares`]): equal to `model_uniform` when that
    /// has no negative coefficient.
    pub model_uniform_nonnegative: Vec<f64>,
}

/// Minimise ‖A x − t‖² subject to x ≥ 0, given the normal equations (`ata` = AᵀA, `atb` = Aᵗt) of a few
/// unknowns. The optimum solves the unconstrained normal equations restricted to its non-zero coefficients, so
/// trying every support (2ⁿ of them; n ≤ 4 here) and keeping the best feasible solution is exact.
pub fn nonnegative_least_squares(ata: &[Vec<f64>], atb: &[f64]) -> Vec<f64> {
    let n = atb.len();
    assert!(n <= 8, "{n} unknowns: enumerating supports is for a few");
    // ‖A x − t‖² − ‖t‖² = xᵀ AᵀA x − 2 xᵀ Aᵀt.
    let objective = |x: &[f64]| {
        (0..n)
            .map(|i| x[i] * ((0..n).map(|j| ata[i][j] * x[j]).sum::<f64>() - 2.0 * atb[i]))
            .sum::<f64>()
    };
    let mut best = (vec![0.0; n], 0.0);
    for support in 1u32..1 << n {
        let idx: Vec<usize> = (0..n).filter(|&i| support & (1 << i) != 0).collect();
        let sub_a = idx
            .iter()
            .map(|&i| idx.iter().map(|&j| ata[i][j]).collect())
            .collect();
        let sub_b = idx.iter().map(|&i| atb[i]).collect();
        let sub_x = dataset::science::brdf::solve_small_system(sub_a, sub_b);
        // A singular support (collinear terms) solves to some finite x that need not be its optimum; it is still
        // scored by the true objective, and the optimum's own support (independent terms) is among those tried.
        if !sub_x.iter().all(|&v| v >= 0.0) {
            continue;
        }
        let mut x = vec![0.0; n];
        for (&i, v) in idx.iter().zip(sub_x) {
            x[i] = v;
        }
        let value = objective(&x);
        if value < best.1 {
            best = (x, value);
        }
    }
    best.0
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
    for_each_sample_group(source, Split::Train, Some(samples), |group| {
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
        model_uniform: dataset::science::brdf::solve_small_system(ata, atb),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Normal equations of a random tall system (rows × n), with the target drawn too.
    fn normal_equations(rows: &[(Vec<f64>, f64)]) -> (Vec<Vec<f64>>, Vec<f64>) {
        let n = rows[0].0.len();
        let (mut ata, mut atb) = (vec![vec![0.0; n]; n], vec![0.0; n]);
        for (a, t) in rows {
            for i in 0..n {
                atb[i] += a[i] * t;
                for j in 0..n {
                    ata[i][j] += a[i] * a[j];
                }
            }
        }
        (ata, atb)
    }

    proptest! {
        /// The Karush–Kuhn–Tucker conditions of the constrained optimum: x ≥ 0, the gradient AᵀA x − Aᵀt is ≥ 0
        /// everywhere and 0 where x > 0; and where the unconstrained solution is already ≥ 0 it is that solution.
        #[test]
        fn nonnegative_least_squares_meets_the_optimality_conditions(
            rows in prop::collection::vec((prop::collection::vec(0.0f64..1.0, 3), -1.0f64..1.0), 8..40)
        ) {
            let (ata, atb) = normal_equations(&rows);
            let x = nonnegative_least_squares(&ata, &atb);
            let scale = atb.iter().map(|v| v.abs()).fold(1e-12, f64::max)
                + ata.iter().flatten().map(|v| v.abs()).fold(0.0, f64::max);
            for i in 0..3 {
                let gradient: f64 = (0..3).map(|j| ata[i][j] * x[j]).sum::<f64>() - atb[i];
                prop_assert!(x[i] >= 0.0);
                prop_assert!(gradient >= -1e-9 * scale, "x {x:?}, gradient[{i}] {gradient}");
                if x[i] > 0.0 {
                    prop_assert!(gradient.abs() <= 1e-9 * scale, "x {x:?}, gradient[{i}] {gradient}");
                }
            }
            let free = dataset::science::brdf::solve_small_system(ata.clone(), atb.clone());
            if free.iter().all(|&v| v >= 0.0) {
                for (a, b) in x.iter().zip(&free) {
                    prop_assert!((a - b).abs() <= 1e-9 * (1.0 + b.abs()), "{x:?} vs {free:?}");
                }
            }
        }
    }

    /// Two identical terms (H3's are nearly so): the optimum is not unique, but what is returned meets the
    /// optimality conditions and fits the target as well as the one term alone.
    #[test]
    fn duplicated_terms_still_give_an_optimum() {
        let rows: Vec<(Vec<f64>, f64)> = (0..12)
            .map(|k| {
                let a = 0.5 + 0.1 * k as f64;
                (vec![a, a, 1.0], 3.0 * a - 0.2)
            })
            .collect();
        let (ata, atb) = normal_equations(&rows);
        let x = nonnegative_least_squares(&ata, &atb);
        assert!(x.iter().all(|&v| v >= 0.0), "{x:?}");
        for i in 0..3 {
            let gradient: f64 = (0..3).map(|j| ata[i][j] * x[j]).sum::<f64>() - atb[i];
            assert!(
                gradient >= -1e-9 && (x[i] == 0.0 || gradient.abs() <= 1e-9),
                "x {x:?}, gradient[{i}] {gradient}"
            );
        }
        // The constant would have to be negative (−0.2): it is dropped, and a + b is the slope-only fit.
        assert_eq!(x[2], 0.0);
        let (sa, st): (f64, f64) = rows
            .iter()
            .fold((0.0, 0.0), |(s, t), (r, y)| (s + r[0] * r[0], t + r[0] * y));
        assert!((x[0] + x[1] - st / sa).abs() < 1e-9, "{x:?}");
    }

    /// A target that one term explains with a negative coefficient: that term is dropped, the rest refitted.
    #[test]
    fn a_term_that_would_go_negative_is_dropped_and_the_rest_refitted() {
        // t = 2 a − b on rows where a and b vary independently: the unconstrained fit is (2, −1).
        let rows: Vec<(Vec<f64>, f64)> = (0..20)
            .map(|k| {
                let (a, b) = (1.0 + (k % 5) as f64, 1.0 + (k / 5) as f64);
                (vec![a, b], 2.0 * a - b)
            })
            .collect();
        let (ata, atb) = normal_equations(&rows);
        let free = dataset::science::brdf::solve_small_system(ata.clone(), atb.clone());
        assert!((free[0] - 2.0).abs() < 1e-9 && (free[1] + 1.0).abs() < 1e-9);
        let x = nonnegative_least_squares(&ata, &atb);
        assert_eq!(x[1], 0.0);
        // With b dropped, the best a alone: Σ a t / Σ a².
        assert!((x[0] - atb[0] / ata[0][0]).abs() < 1e-12, "{x:?}");
    }
}

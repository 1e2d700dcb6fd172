//! The model-form oracle: the run's BRDF model with, at every pixel, the best coefficients a map that cannot see
//! the geometry could hold for the world's true material there (least squares over the geometries of orbital
//! images, [`dataset::science::brdf::orbital_geometries`]). Against `oracle` (the true Hapke maps) it isolates what the
//! model's *form* costs, whatever a network puts in its maps: H1's single scale, for instance, cannot follow a
//! material whose phase function differs from the Moon-wide one.
//!
//! The true material varies only in w and b in the synthetic worlds (c, B_S0, h_S and θ̄ are constant bands), so
//! the fits are tabulated once over a (w, b) grid and interpolated bilinearly per pixel.

use dataset::science::brdf::{best_coefficients, orbital_geometries, BrdfModel};
use dataset::science::hapke::{hapke_i_over_f, HFunction, HapkeParams};
use rayon::prelude::*;

/// Albedo nodes: 0.02..=0.95 in steps of 0.01 (the generator's clamp range).
const W_NODES: (f64, f64, usize) = (0.02, 0.01, 94);
/// Asymmetry nodes: 0.05..=0.45 in steps of 0.01.
const B_NODES: (f64, f64, usize) = (0.05, 0.01, 41);

/// Best geometry-blind coefficients of one model on a (w, b) grid, for fixed c, B_S0, h_S and θ̄.
pub struct ModelFormTable {
    pub model: BrdfModel,
    /// The material's other parameters, shared by every pixel.
    pub fixed: HapkeParams,
    /// `coefficients[wi * B_NODES.2 + bi]`, one per term (activated values).
    coefficients: Vec<Vec<f64>>,
}

impl ModelFormTable {
    /// Fit `model` at every grid node (`None` for M6, whose half-angle terms the fit's cosines do not carry).
    pub fn new(model: BrdfModel, fixed: HapkeParams) -> Option<Self> {
        if model.uses_half_diff() {
            return None;
        }
        let geometries = orbital_geometries();
        let coefficients = (0..W_NODES.2 * B_NODES.2)
            .into_par_iter()
            .map(|k| {
                let w = W_NODES.0 + (k / B_NODES.2) as f64 * W_NODES.1;
                let b = B_NODES.0 + (k % B_NODES.2) as f64 * B_NODES.1;
                let material = HapkeParams { w, b, ..fixed };
                best_coefficients(model, &geometries, |c| {
                    hapke_i_over_f(&material, c.cos_i, c.cos_e, c.cos_g, HFunction::Hapke2002)
                })
                .0
            })
            .collect();
        Some(Self {
            model,
            fixed,
            coefficients,
        })
    }

    /// Coefficients for material (w, b), one per term of the model and 0 past them (the shape of
    /// [`BrdfModel::terms`]): bilinear between grid nodes, clamped to the grid. Per pixel, so no allocation.
    pub fn coefficients(&self, w: f64, b: f64) -> [f64; 4] {
        let node = |x: f64, (start, step, n): (f64, f64, usize)| {
            let t = ((x - start) / step).clamp(0.0, (n - 1) as f64);
            let i = (t.floor() as usize).min(n - 2);
            (i, t - i as f64)
        };
        let ((wi, wt), (bi, bt)) = (node(w, W_NODES), node(b, B_NODES));
        let at = |i: usize, j: usize| &self.coefficients[i * B_NODES.2 + j];
        let mut out = [0.0; 4];
        for (k, c) in out.iter_mut().enumerate().take(self.model.param_count()) {
            *c = (1.0 - wt) * ((1.0 - bt) * at(wi, bi)[k] + bt * at(wi, bi + 1)[k])
                + wt * ((1.0 - bt) * at(wi + 1, bi)[k] + bt * at(wi + 1, bi + 1)[k]);
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// At a grid node the table holds the direct fit; between nodes it stays within the fits' own spread.
    #[test]
    fn the_table_reproduces_direct_fits() {
        let fixed = HapkeParams::lunar_typical();
        let table = ModelFormTable::new(BrdfModel::H3, fixed).unwrap();
        let geometries = orbital_geometries();
        for (w, b) in [(0.32, 0.25), (0.58, 0.2), (0.123, 0.171)] {
            let material = HapkeParams { w, b, ..fixed };
            let (direct, _) = best_coefficients(BrdfModel::H3, &geometries, |c| {
                hapke_i_over_f(&material, c.cos_i, c.cos_e, c.cos_g, HFunction::Hapke2002)
            });
            let tabled = table.coefficients(w, b);
            for (d, t) in direct.iter().zip(&tabled) {
                // Nodes are 0.01 apart and the coefficients nearly linear in w and b: ≤ 1 % of the largest.
                let scale = direct.iter().fold(0.0f64, |m, x| m.max(x.abs()));
                assert!(
                    (d - t).abs() <= 0.01 * scale,
                    "w {w} b {b}: {direct:?} vs {tabled:?}"
                );
            }
        }
        // The Moon-wide material is H1's coefficient 1 exactly (a node of both axes).
        let h1 = ModelFormTable::new(BrdfModel::H1, fixed).unwrap();
        assert!((h1.coefficients(0.32, 0.25)[0] - 1.0).abs() < 1e-9);
        assert!(ModelFormTable::new(BrdfModel::M6, fixed).is_none());
    }
}

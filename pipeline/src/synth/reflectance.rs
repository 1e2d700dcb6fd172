//! True spatially varying Hapke parameters: correlated with morphology (fresh material, steep slopes, melt) but
//! not determined by it (an independent fBm component sets the floor no DEM-based model can beat).

use rayon::prelude::*;

use super::config::ReflectanceConfig;
use super::geologic_units::Units;
use super::noise::smoothstep;
use super::noise::Fbm;
use super::Grid;
use crate::rng::keyed_u64;

/// Single-scattering albedo w and HG asymmetry b per fine cell (c, B_S0, h_S, θ̄ are scene constants).
pub struct HapkeMaps {
    pub w: Vec<f32>,
    pub b: Vec<f32>,
    /// w without the independent component: units, freshness, slope and melt only. Evaluation's second oracle
    /// renders with it, to show how much of the error any terrain-reading model could remove at best.
    pub w_morphology: Vec<f32>,
}

pub fn hapke_maps(
    cfg: &ReflectanceConfig,
    grid: &Grid,
    units: &Units,
    heights: &[f32],
    freshness: &[f32],
    melt: &[f32],
    seed: u64,
) -> HapkeMaps {
    let independent = Fbm {
        key: keyed_u64(seed, "albedo-independent", 0),
        hurst: 0.6,
        amplitude: 1.0,
        largest_wavelength_m: cfg.independent_wavelength_m,
        smallest_wavelength_m: 2.0 * grid.gsd_m,
    };
    let (w, h) = (grid.width, grid.height);
    let steep_tan = cfg.steep_slope_deg.to_radians().tan();
    let mut w_map = vec![0f32; w * h];
    let mut b_map = vec![0f32; w * h];
    let mut morphology_map = vec![0f32; w * h];
    w_map
        .par_chunks_mut(w)
        .zip(b_map.par_chunks_mut(w))
        .zip(morphology_map.par_chunks_mut(w))
        .enumerate()
        .for_each(|(row, ((w_row, b_row), morphology_row))| {
            for col in 0..w {
                let (x, y) = grid.center(col, row);
                let i = row * w + col;
                // Mare/highland mixing with a soft boundary.
                let unit = units.highland(x, y);
                let base = cfg.w_mare + (cfg.w_highland - cfg.w_mare) * unit;
                // Slope from central differences on the true DEM (clamped at the raster edge).
                let at = |c: usize, r: usize| heights[r.min(h - 1) * w + c.min(w - 1)] as f64;
                let dzdx = (at(col + 1, row) - at(col.saturating_sub(1), row)) / (2.0 * grid.gsd_m);
                let dzdy = (at(col, row + 1) - at(col, row.saturating_sub(1))) / (2.0 * grid.gsd_m);
                let slope_tan = (dzdx * dzdx + dzdy * dzdy).sqrt();
                let steep = smoothstep(0.8 * steep_tan, 1.25 * steep_tan, slope_tan);
                let fresh = freshness[i] as f64;
                let noise = independent.at(x, y).clamp(-1.5, 1.5) / 1.5;
                let morphology = base
                    * (1.0 + cfg.fresh_brightening * fresh)
                    * (1.0 + cfg.steep_brightening * steep)
                    * (1.0 - cfg.melt_darkening * melt[i] as f64);
                let value = morphology * (1.0 + cfg.independent_variation * noise);
                w_row[col] = value.clamp(0.02, 0.95) as f32;
                morphology_row[col] = morphology.clamp(0.02, 0.95) as f32;
                // Fresh, blocky material back-scatters a little less sharply.
                b_row[col] = (cfg.b - 0.05 * fresh) as f32;
            }
        });
    HapkeMaps {
        w: w_map,
        b: b_map,
        w_morphology: morphology_map,
    }
}

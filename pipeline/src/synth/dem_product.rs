//! The DEM a user actually receives: the true DEM degraded like a stereo product — block-averaged to the
//! product grid, smoothed (stereo matching windows), with white and long-wavelength noise, a few matching blunders
//! and nodata holes. Real DEMs disagree with images; this is where our synthetic ones do.

use rand::Rng;
use rand_distr::{Distribution, Normal};
use rayon::prelude::*;

use super::config::DemProductConfig;
use super::noise::Fbm;
use super::Grid;
use crate::rng::{keyed_rng, keyed_u64};

pub fn degrade(
    cfg: &DemProductConfig,
    fine: &Grid,
    fine_heights: &[f32],
    dem: &Grid,
    seed: u64,
) -> Vec<f32> {
    let factor = (dem.gsd_m / fine.gsd_m).round() as usize;
    let (w, h) = (dem.width, dem.height);
    // 1. Area average of factor × factor fine cells (the grids share their top-left corner).
    let mut heights = vec![0f32; w * h];
    heights
        .par_chunks_mut(w)
        .enumerate()
        .for_each(|(row, out)| {
            for (col, v) in out.iter_mut().enumerate() {
                let mut sum = 0.0f64;
                for r in row * factor..(row + 1) * factor {
                    for c in col * factor..(col + 1) * factor {
                        sum += fine_heights[r * fine.width + c] as f64;
                    }
                }
                *v = (sum / (factor * factor) as f64) as f32;
            }
        });
    // 2. Separable Gaussian smoothing.
    let heights = dataset::science::raster::gaussian_blur(&heights, w, h, cfg.smoothing_sigma_px);
    // 3. Long-wavelength correlated error and white noise (per-row streams: deterministic under rayon).
    let correlated = Fbm {
        key: keyed_u64(seed, "dem-correlated-error", 0),
        hurst: 0.9,
        amplitude: cfg.correlated_error_m,
        largest_wavelength_m: cfg.correlated_error_wavelength_m,
        smallest_wavelength_m: 4.0 * dem.gsd_m,
    };
    let mut out = heights;
    out.par_chunks_mut(w)
        .enumerate()
        .for_each(|(row, out_row)| {
            let mut rng = keyed_rng(seed, "dem-white-noise", row as u64);
            let normal = Normal::new(0.0, cfg.noise_m.max(1e-12)).expect("valid sigma");
            for (col, v) in out_row.iter_mut().enumerate() {
                let (x, y) = dem.center(col, row);
                *v += (correlated.at(x, y) + normal.sample(&mut rng)) as f32;
            }
        });
    // 4. Blunders: Gaussian pits/spikes of a few metres, ~20 m across.
    let mut rng = keyed_rng(seed, "dem-blunders", 0);
    for _ in 0..cfg.blunders {
        let (cx, cy) = (rng.random_range(0..w) as f64, rng.random_range(0..h) as f64);
        let amp = rng.random_range(4.0..15.0) * if rng.random::<bool>() { 1.0 } else { -1.0 };
        let r_px = rng.random_range(2.0..5.0);
        let reach = (3.0 * r_px) as i64;
        for dr in -reach..=reach {
            for dc in -reach..=reach {
                let (c, r) = (cx as i64 + dc, cy as i64 + dr);
                if c >= 0 && r >= 0 && (c as usize) < w && (r as usize) < h {
                    let d2 = (dc * dc + dr * dr) as f64 / (r_px * r_px);
                    out[r as usize * w + c as usize] += (amp * (-d2).exp()) as f32;
                }
            }
        }
    }
    // 5. Nodata holes (failed matching, e.g. in shadows): small irregular NaN patches.
    let mut rng = keyed_rng(seed, "dem-holes", 0);
    for _ in 0..cfg.holes {
        let (cx, cy) = (rng.random_range(0..w) as i64, rng.random_range(0..h) as i64);
        let r_px = rng.random_range(2.0..6.0f64);
        let reach = r_px.ceil() as i64 + 1;
        for dr in -reach..=reach {
            for dc in -reach..=reach {
                let (c, r) = (cx + dc, cy + dr);
                let wobble = 1.0 + 0.3 * ((dc as f64 * 1.7).sin() * (dr as f64 * 1.3).cos());
                if c >= 0
                    && r >= 0
                    && (c as usize) < w
                    && (r as usize) < h
                    && ((dc * dc + dr * dr) as f64).sqrt() < r_px * wobble
                {
                    out[r as usize * w + c as usize] = f32::NAN;
                }
            }
        }
    }
    out
}

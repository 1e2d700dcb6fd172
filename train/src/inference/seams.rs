//! What is left of the crop seams: a rendering of the maps, and the seam score that compares differences across
//! crop edges with those elsewhere.

use dataset::contract::schema::CROP_PX;
use dataset::science::brdf::inverse_leaky_relu;
use dataset::science::raster::Raster;

use super::tiling::crop_starts;
use super::ParamMaps;

/// Render the maps over the DEM with one sun direction and a nadir camera (normals by central differences, cast
/// shadows ignored): enough to see seams, which live in the parameters, not in the geometry.
pub fn render_maps(maps: &ParamMaps, dem: &Raster, sun_dir_enu: [f64; 3]) -> Vec<f64> {
    use dataset::science::geometry::{plane_normal, Cosines, HalfDiffCosines};
    let (w, h) = (maps.width, maps.height);
    let gsd = dem.transform.gsd_m();
    let sun = glam::DVec3::from(sun_dir_enu).normalize();
    let view = glam::DVec3::Z;
    let z = |c: usize, r: usize| dem.data[r * w + c] as f64;
    (0..w * h)
        .map(|k| {
            let (c, r) = (k % w, k / w);
            let (cl, cr, ru, rd) = (
                c.saturating_sub(1),
                (c + 1).min(w - 1),
                r.saturating_sub(1),
                (r + 1).min(h - 1),
            );
            let dzdx = (z(cr, r) - z(cl, r)) / ((cr - cl).max(1) as f64 * gsd);
            let dzdy = (z(c, ru) - z(c, rd)) / ((rd - ru).max(1) as f64 * gsd);
            let n = plane_normal(dzdx, dzdy);
            let cosines = Cosines::new(n, sun, view);
            let half_diff = HalfDiffCosines::new(n, sun, view);
            let raw: Vec<f64> = maps
                .bands
                .iter()
                // The maps hold activated values; evaluate() expects raw ones.
                .map(|b| inverse_leaky_relu(b[k] as f64))
                .collect();
            if raw.iter().any(|v| !v.is_finite()) {
                return f64::NAN;
            }
            maps.model.evaluate(&raw, &cosines, &half_diff)
        })
        .collect()
}

/// Pixels this close to the image border are left out of [`seam_score`]: one-sided normals and reflected network
/// context make the outermost rows differ, which says nothing about seams.
pub const SEAM_BORDER_PX: usize = 4;

/// Seam score of a rendered image: the mean squared pixel-to-pixel difference across the lines where a crop of
/// the tiling (for this `overlap`) starts or ends, over the mean squared difference across all other lines, both
/// away from the image border. ≈ 1: seams invisible; hard-edged tiles score above 1.
pub fn seam_score(image: &[f64], width: usize, height: usize, overlap: usize) -> f64 {
    let edges = |len: usize| -> Vec<usize> {
        let mut e: Vec<usize> = crop_starts(len, overlap)
            .into_iter()
            .flat_map(|o| [o, o + CROP_PX as isize])
            .filter(|&x| x > 0 && x < len as isize)
            .map(|x| x as usize)
            .collect();
        e.sort_unstable();
        e.dedup();
        e
    };
    let (xs, ys) = (edges(width), edges(height));
    let m = SEAM_BORDER_PX;
    let inside = |c: usize, r: usize| c >= m && r >= m && c + m < width && r + m < height;
    let (mut seam, mut seam_n, mut rest, mut rest_n) = (0.0, 0usize, 0.0, 0usize);
    let mut add = |g: f64, on_seam: bool| {
        if !g.is_finite() {
            return;
        }
        if on_seam {
            seam += g * g;
            seam_n += 1;
        } else {
            rest += g * g;
            rest_n += 1;
        }
    };
    for r in 0..height {
        for c in 1..width {
            if inside(c, r) && inside(c - 1, r) {
                add(
                    image[r * width + c] - image[r * width + c - 1],
                    xs.binary_search(&c).is_ok(),
                );
            }
        }
    }
    for r in 1..height {
        for c in 0..width {
            if inside(c, r) && inside(c, r - 1) {
                add(
                    image[r * width + c] - image[(r - 1) * width + c],
                    ys.binary_search(&r).is_ok(),
                );
            }
        }
    }
    (seam / seam_n.max(1) as f64) / (rest / rest_n.max(1) as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::inference::tiling::crop_starts;

    #[test]
    fn seam_score_sees_a_step_on_a_crop_edge_and_not_a_smooth_ramp() {
        let (w, h) = (300, 300);
        let ramp: Vec<f64> = (0..w * h)
            .map(|k| (k % w) as f64 * 0.01 + (k / w) as f64 * 0.02)
            .collect();
        assert!((seam_score(&ramp, w, h, 0) - 1.0).abs() < 1e-9);
        let edge = crop_starts(w, 0)[1] as usize;
        let stepped: Vec<f64> = ramp
            .iter()
            .enumerate()
            .map(|(k, v)| v + if k % w >= edge { 0.5 } else { 0.0 })
            .collect();
        assert!(seam_score(&stepped, w, h, 0) > 10.0);
    }
}

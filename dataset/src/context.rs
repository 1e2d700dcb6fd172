//! The terrain context of a crop: a coarse, wide DEM window centred on the crop centre, stored with every sample
//! (`context_dem`) so a network can see what a 640 m crop cannot — whether it lies on a crater floor, a wall, an
//! ejecta blanket or a mare plain, kilometres across. One home for it: the project stage cuts it for the published
//! samples and `g2r-train infer` cuts it for crops of a new DEM, both through [`ContextSampler`].
//!
//! Cell `(i, j)` of the `CONTEXT_PX²` window (row-major, north row first) is the mean of the DEM pixels whose
//! centres fall in the square of side `gsd_m` centred at `centre + ((j − 15.5)·gsd, (15.5 − i)·gsd)` in map
//! metres: an area average, so a 512 m cell sees the same terrain whatever the DEM's own resolution.
//! A cell less than half covered by finite DEM pixels (outside the DEM, or a hole) is NaN.

use crate::raster::Raster;
use crate::schema::CONTEXT_PX;

/// Summed-area tables of a DEM's finite heights and of their count, for O(1) box means anywhere.
pub struct ContextSampler<'a> {
    dem: &'a Raster,
    /// `(width + 1) × (height + 1)`: sum of finite heights minus `offset_m` above and left of each corner.
    sums: Vec<f64>,
    counts: Vec<u32>,
    /// Subtracted before summing so sums stay small (heights are ~−1e3 m on the Moon's sphere).
    offset_m: f64,
}

impl<'a> ContextSampler<'a> {
    /// Build the tables (one pass over the DEM; 12 bytes per DEM pixel).
    pub fn new(dem: &'a Raster) -> Self {
        let (w, h) = (dem.width, dem.height);
        let finite = || dem.data.iter().filter(|z| z.is_finite());
        let n = finite().count().max(1);
        let offset_m = finite().map(|&z| z as f64).sum::<f64>() / n as f64;
        let stride = w + 1;
        let mut sums = vec![0f64; stride * (h + 1)];
        let mut counts = vec![0u32; stride * (h + 1)];
        for r in 0..h {
            let (mut row_sum, mut row_count) = (0f64, 0u32);
            for c in 0..w {
                let z = dem.data[r * w + c];
                if z.is_finite() {
                    row_sum += z as f64 - offset_m;
                    row_count += 1;
                }
                let k = (r + 1) * stride + c + 1;
                sums[k] = sums[k - stride] + row_sum;
                counts[k] = counts[k - stride] + row_count;
            }
        }
        Self {
            dem,
            sums,
            counts,
            offset_m,
        }
    }

    /// The `CONTEXT_PX²` window of `gsd_m` cells centred at map point (`center_x`, `center_y`).
    pub fn window(&self, center_x: f64, center_y: f64, gsd_m: f64) -> Vec<f32> {
        let half = CONTEXT_PX as f64 / 2.0;
        let mut out = Vec::with_capacity(CONTEXT_PX * CONTEXT_PX);
        for i in 0..CONTEXT_PX {
            for j in 0..CONTEXT_PX {
                let x0 = center_x + (j as f64 - half) * gsd_m;
                let y0 = center_y + (half - i as f64) * gsd_m;
                out.push(self.box_mean(x0, x0 + gsd_m, y0 - gsd_m, y0));
            }
        }
        out
    }

    /// Mean of the finite DEM pixels whose centres lie in map box [x0, x1) × (y0, y1]; NaN when they cover less
    /// than half of the pixels the box spans.
    fn box_mean(&self, x0: f64, x1: f64, y0: f64, y1: f64) -> f32 {
        let t = &self.dem.transform;
        // In centre coordinates pixel k sits at k: the pixels centred in [c0, c1) are ceil(c0) … ceil(c1) − 1.
        let (c0, r0) = t.map_to_pixel(x0, y1);
        let (c1, r1) = t.map_to_pixel(x1, y0);
        let first = |e: f64| e.ceil();
        let (ca, cb) = (first(c0.min(c1)), first(c0.max(c1)));
        let (ra, rb) = (first(r0.min(r1)), first(r0.max(r1)));
        let spanned = (cb - ca) * (rb - ra);
        if spanned <= 0.0 {
            return f32::NAN;
        }
        let clamp_c = |v: f64| v.clamp(0.0, self.dem.width as f64) as usize;
        let clamp_r = |v: f64| v.clamp(0.0, self.dem.height as f64) as usize;
        let (ca, cb, ra, rb) = (clamp_c(ca), clamp_c(cb), clamp_r(ra), clamp_r(rb));
        let stride = self.dem.width + 1;
        let corner_sum = |r: usize, c: usize| self.sums[r * stride + c];
        let corner_count = |r: usize, c: usize| self.counts[r * stride + c] as i64;
        let count = corner_count(rb, cb) - corner_count(ra, cb) - corner_count(rb, ca)
            + corner_count(ra, ca);
        if (count as f64) < 0.5 * spanned {
            return f32::NAN;
        }
        let sum = corner_sum(rb, cb) - corner_sum(ra, cb) - corner_sum(rb, ca) + corner_sum(ra, ca);
        (self.offset_m + sum / count as f64) as f32
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::crs::LunarCrs;
    use crate::raster::GeoTransform;

    fn dem(width: usize, height: usize, z: impl Fn(usize, usize) -> f32) -> Raster {
        let crs = LunarCrs::equirectangular(0.0, 0.0);
        let mut dem = Raster::new(
            width,
            height,
            GeoTransform::north_up(1000.0, 5000.0, 5.0),
            crs,
            0.0,
        );
        for r in 0..height {
            for c in 0..width {
                dem.data[r * width + c] = z(c, r);
            }
        }
        dem
    }

    /// The independent expectation: visit every DEM pixel, keep those whose centre lies in the cell.
    fn brute_force(dem: &Raster, cx: f64, cy: f64, gsd: f64) -> Vec<f32> {
        let half = CONTEXT_PX as f64 / 2.0;
        let mut out = Vec::new();
        for i in 0..CONTEXT_PX {
            for j in 0..CONTEXT_PX {
                let x0 = cx + (j as f64 - half) * gsd;
                let y1 = cy + (half - i as f64) * gsd;
                let (mut sum, mut n, mut spanned) = (0f64, 0usize, 0usize);
                // Pixels beyond the raster count as spanned-but-missing; scan every index near the cell.
                let t = &dem.transform;
                let c_lo = ((x0 - t.origin_x) / t.pixel_width).floor() as i64 - 2;
                let c_hi = ((x0 + gsd - t.origin_x) / t.pixel_width).ceil() as i64 + 2;
                let r_lo = ((y1 - t.origin_y) / t.pixel_height).floor() as i64 - 2;
                let r_hi = ((y1 - gsd - t.origin_y) / t.pixel_height).ceil() as i64 + 2;
                for r in r_lo..r_hi {
                    for c in c_lo..c_hi {
                        let (x, y) = dem.transform.pixel_center(c as f64, r as f64);
                        if x >= x0 && x < x0 + gsd && y <= y1 && y > y1 - gsd {
                            spanned += 1;
                            let inside = r >= 0
                                && c >= 0
                                && (r as usize) < dem.height
                                && (c as usize) < dem.width;
                            if inside {
                                let z = dem.get(c as usize, r as usize);
                                if z.is_finite() {
                                    sum += z as f64;
                                    n += 1;
                                }
                            }
                        }
                    }
                }
                out.push(if spanned == 0 || (n as f64) < 0.5 * spanned as f64 {
                    f32::NAN
                } else {
                    (sum / n as f64) as f32
                });
            }
        }
        out
    }

    #[test]
    fn windows_are_area_means_with_holes_and_the_outside_as_nan() {
        // Lunar-scale heights with a hole block; the centre is off the pixel grid so cells cut pixels unevenly.
        let dem = dem(120, 90, |c, r| {
            if (40..55).contains(&c) && (20..60).contains(&r) {
                f32::NAN
            } else {
                -1400.0 + ((c * 7 + r * 13) % 31) as f32 * 3.5
            }
        });
        for &(cx, cy, gsd) in &[
            (1000.0 + 300.0, 5000.0 - 225.0, 17.0),
            (1000.0 + 12.3, 5000.0 - 401.7, 9.5),
            (1000.0 + 600.0, 5000.0 - 450.0, 40.0),
        ] {
            let got = ContextSampler::new(&dem).window(cx, cy, gsd);
            let want = brute_force(&dem, cx, cy, gsd);
            assert_eq!(got.len(), CONTEXT_PX * CONTEXT_PX);
            let mut nans = 0;
            for (k, (g, w)) in got.iter().zip(&want).enumerate() {
                assert_eq!(g.is_nan(), w.is_nan(), "cell {k}: {g} vs {w}");
                if w.is_nan() {
                    nans += 1;
                } else {
                    assert!((g - w).abs() <= 1e-3, "cell {k}: {g} vs {w}");
                }
            }
            assert!(
                nans > 0 && nans < got.len(),
                "the cases reach outside: {nans}"
            );
        }
    }

    #[test]
    fn a_plane_averages_to_its_value_at_pixel_aligned_cell_centres() {
        let (a, b) = (0.25f64, -0.5f64);
        let dem = dem(400, 400, |c, r| {
            (-1200.0 + a * c as f64 + b * r as f64) as f32
        });
        // 4-pixel cells centred on a pixel corner: each cell holds exactly 4 × 4 pixels.
        let (cx, cy) = dem.transform.pixel_edge(200.0, 200.0);
        let got = ContextSampler::new(&dem).window(cx, cy, 20.0);
        for i in 0..CONTEXT_PX {
            for j in 0..CONTEXT_PX {
                let (c, r) = (
                    200.0 - 64.0 + 4.0 * j as f64 + 1.5,
                    200.0 - 64.0 + 4.0 * i as f64 + 1.5,
                );
                let want = -1200.0 + a * c + b * r;
                let g = got[i * CONTEXT_PX + j] as f64;
                assert!((g - want).abs() < 1e-3, "({i}, {j}): {g} vs {want}");
            }
        }
    }
}

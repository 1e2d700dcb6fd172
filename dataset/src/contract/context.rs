//! The terrain context of a crop: a coarse, wide DEM window centred on the crop centre, stored with every sample
//! (`context_dem`) so a network can see what a 640 m crop cannot — whether it lies on a crater floor, a wall, an
//! ejecta blanket or a mare plain, kilometres across. One home for it: the project stage cuts it for the published
//! samples and `g2r-train infer` cuts it for crops of a new DEM, both through [`ContextSampler`].
//!
//! Cell `(i, j)` of the `CONTEXT_PX²` window (row-major, north row first) is an area mean of the DEM over the
//! square of side `gsd_m` centred at `centre + ((j − 15.5)·gsd, (15.5 − i)·gsd)` in map metres, so a 512 m cell
//! sees the same terrain whatever the DEM's own resolution. The mean is taken at a resolution of blocks: the DEM
//! is cut into `k × k`-pixel blocks from its top-left corner, `k = max(1, ⌊gsd_m / (16 · pixel size)⌋)`, and a cell
//! averages the finite pixels of the blocks whose centres fall in it. Cell edges are thus placed to within half a
//! block (≤ 1/32 of a cell); with `k = 1` the blocks are the pixels. A cell whose blocks span pixels less than half
//! of which are finite DEM (outside the DEM, or a hole) is NaN.
//!
//! Why blocks: O(1) box means need summed-area tables, 12 bytes per table entry. Over every pixel of the
//! 8000 × 8000 tycho-full DEM that was 0.72 GiB, which took the dataset build's peak RSS from 1.8 to 2.5 GiB
//! (docs/design.md, Performance targets asks ≤ 2 GiB regardless of size); over 6 × 6-pixel blocks (512 m cells on a 5 m DEM) it is 21 MB.

use std::path::{Path, PathBuf};

use crate::contract::schema::CONTEXT_PX;
use crate::science::crs::CrsError;
use crate::science::raster::{read_raster, Raster, RasterError};

/// Blocks per cell edge (at least): sets the block size from the cell size and the DEM's pixel size.
pub const BLOCKS_PER_CELL: f64 = 16.0;

/// Summed-area tables of a DEM's finite heights and of their count, over `block_px²`-pixel blocks, for O(1) box
/// means anywhere.
pub struct ContextSampler<'a> {
    dem: &'a Raster,
    gsd_m: f64,
    block_px: usize,
    /// Block columns (the last one may be cut short by the DEM's edge).
    blocks_wide: usize,
    /// `(blocks_wide + 1) × (blocks_high + 1)`: sum of finite heights minus `offset_m` above and left of each block
    /// corner.
    sums: Vec<f64>,
    counts: Vec<u32>,
    /// Subtracted before summing so sums stay small (heights are ~−1e3 m on the Moon's sphere).
    offset_m: f64,
}

impl<'a> ContextSampler<'a> {
    /// Tables for windows of `gsd_m` cells, blocks sized as the module says (one pass over the DEM).
    pub fn new(dem: &'a Raster, gsd_m: f64) -> Self {
        let pixel_m = dem
            .transform
            .pixel_width
            .abs()
            .min(dem.transform.pixel_height.abs());
        let block_px = ((gsd_m / (BLOCKS_PER_CELL * pixel_m)).floor() as usize).max(1);
        Self::with_block_px(dem, gsd_m, block_px)
    }

    /// Tables over `block_px²`-pixel blocks (tests pick the block size directly).
    pub fn with_block_px(dem: &'a Raster, gsd_m: f64, block_px: usize) -> Self {
        assert!(block_px >= 1 && gsd_m > 0.0);
        let (w, h) = (dem.width, dem.height);
        let finite = || dem.data.iter().filter(|z| z.is_finite());
        let n = finite().count().max(1);
        let offset_m = finite().map(|&z| z as f64).sum::<f64>() / n as f64;
        let (blocks_wide, blocks_high) = (w.div_ceil(block_px), h.div_ceil(block_px));
        // Block sums first (one pass over the DEM), then the tables over blocks.
        let mut block_sums = vec![0f64; blocks_wide * blocks_high];
        let mut block_counts = vec![0u32; blocks_wide * blocks_high];
        for r in 0..h {
            let block_row = (r / block_px) * blocks_wide;
            for c in 0..w {
                let z = dem.data[r * w + c];
                if z.is_finite() {
                    block_sums[block_row + c / block_px] += z as f64 - offset_m;
                    block_counts[block_row + c / block_px] += 1;
                }
            }
        }
        let stride = blocks_wide + 1;
        let mut sums = vec![0f64; stride * (blocks_high + 1)];
        let mut counts = vec![0u32; stride * (blocks_high + 1)];
        for br in 0..blocks_high {
            let (mut row_sum, mut row_count) = (0f64, 0u32);
            for bc in 0..blocks_wide {
                row_sum += block_sums[br * blocks_wide + bc];
                row_count += block_counts[br * blocks_wide + bc];
                let k = (br + 1) * stride + bc + 1;
                sums[k] = sums[k - stride] + row_sum;
                counts[k] = counts[k - stride] + row_count;
            }
        }
        Self {
            dem,
            gsd_m,
            block_px,
            blocks_wide,
            sums,
            counts,
            offset_m,
        }
    }

    /// Pixels per block edge.
    pub fn block_px(&self) -> usize {
        self.block_px
    }

    /// The `CONTEXT_PX²` window centred at map point (`center_x`, `center_y`).
    pub fn window(&self, center_x: f64, center_y: f64) -> Vec<f32> {
        let (half, gsd_m) = (CONTEXT_PX as f64 / 2.0, self.gsd_m);
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

    /// Mean of the finite pixels of the blocks whose centres lie in map box [x0, x1) × (y0, y1]; NaN when they are
    /// less than half of the pixels those blocks span.
    fn box_mean(&self, x0: f64, x1: f64, y0: f64, y1: f64) -> f32 {
        let t = &self.dem.transform;
        let k = self.block_px as f64;
        // In pixel-centre coordinates pixel p sits at p and block b's centre at b·k + (k − 1)/2: the blocks centred
        // in [e0, e1) are ceil(f(e0)) … ceil(f(e1)) − 1 with f(e) = (e − (k − 1)/2) / k.
        let (c0, r0) = t.map_to_pixel(x0, y1);
        let (c1, r1) = t.map_to_pixel(x1, y0);
        let first = |e: f64| ((e - (k - 1.0) / 2.0) / k).ceil();
        let (ca, cb) = (first(c0.min(c1)), first(c0.max(c1)));
        let (ra, rb) = (first(r0.min(r1)), first(r0.max(r1)));
        let spanned = (cb - ca) * (rb - ra) * k * k;
        if spanned <= 0.0 {
            return f32::NAN;
        }
        let blocks_high = self.sums.len() / (self.blocks_wide + 1) - 1;
        let clamp_c = |v: f64| v.clamp(0.0, self.blocks_wide as f64) as usize;
        let clamp_r = |v: f64| v.clamp(0.0, blocks_high as f64) as usize;
        let (ca, cb, ra, rb) = (clamp_c(ca), clamp_c(cb), clamp_r(ra), clamp_r(rb));
        let stride = self.blocks_wide + 1;
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

/// Why a unit map cannot frame a DEM's samples: one line each, naming the file and the fix.
#[derive(Debug, thiserror::Error)]
pub enum UnitMapError {
    #[error(transparent)]
    Raster(#[from] RasterError),
    #[error("{path}: CRS differs from the DEM's; reproject the unit map with gdalwarp -t_srs to the DEM's CRS")]
    Crs { path: PathBuf },
    #[error("{path}: its CRS cannot be compared with the DEM's ({source}); give it the DEM's CRS with gdalwarp -t_srs")]
    CrsConversion { path: PathBuf, source: CrsError },
    #[error("{path}: value {value} at pixel ({col}, {row}) is not a highland fraction in [0, 1]; code mare 0 and highland 1 (gdal_calc.py), other ground as nodata")]
    Value {
        path: PathBuf,
        value: f32,
        col: usize,
        row: usize,
    },
    #[error(
        "{path}: covers none of the DEM; map the DEM's area, or build without inputs.unit_map"
    )]
    NoOverlap { path: PathBuf },
}

/// A site's mare/highland unit map for the context windows' `highland` plane: band 1 of a GDAL raster in the DEM's
/// CRS, 0 mare and 1 highland (fractions between are kept), nodata where unmapped. A geologic map's polygons
/// become one with `gdal_rasterize`; a global FeO map, thresholded, with `gdal_calc.py`. Any cell size: the
/// windows average it as they average the DEM.
pub fn read_unit_map(path: &Path, dem: &Raster) -> Result<Raster, UnitMapError> {
    let map = read_raster(path)?;
    let probes = dem.transform.corners(dem.width, dem.height);
    let same =
        dem.crs
            .same_map(&map.crs, &probes)
            .map_err(|source| UnitMapError::CrsConversion {
                path: path.to_path_buf(),
                source,
            })?;
    if !same {
        return Err(UnitMapError::Crs {
            path: path.to_path_buf(),
        });
    }
    if let Some(k) = map
        .data
        .iter()
        .position(|v| v.is_finite() && !(0.0..=1.0).contains(v))
    {
        return Err(UnitMapError::Value {
            path: path.to_path_buf(),
            value: map.data[k],
            col: k % map.width,
            row: k / map.width,
        });
    }
    let (x0, y0, x1, y1) = map.transform.bounds(map.width, map.height);
    let (dx0, dy0, dx1, dy1) = dem.transform.bounds(dem.width, dem.height);
    if x1 <= dx0 || dx1 <= x0 || y1 <= dy0 || dy1 <= y0 || !map.data.iter().any(|v| v.is_finite()) {
        return Err(UnitMapError::NoOverlap {
            path: path.to_path_buf(),
        });
    }
    Ok(map)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::science::crs::LunarCrs;
    use crate::science::raster::GeoTransform;

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

    /// The independent expectation: visit every `k × k` block near each cell (the DEM's block grid extended past
    /// its edges), keep those whose centre lies in the cell, and average their finite pixels.
    fn brute_force(dem: &Raster, cx: f64, cy: f64, gsd: f64, k: usize) -> Vec<f32> {
        let half = CONTEXT_PX as f64 / 2.0;
        let t = &dem.transform;
        let ki = k as i64;
        let mut out = Vec::new();
        for i in 0..CONTEXT_PX {
            for j in 0..CONTEXT_PX {
                let x0 = cx + (j as f64 - half) * gsd;
                let y1 = cy + (half - i as f64) * gsd;
                let (mut sum, mut n, mut spanned) = (0f64, 0usize, 0usize);
                let c_lo = ((x0 - t.origin_x) / t.pixel_width).floor() as i64 / ki - 2;
                let c_hi = ((x0 + gsd - t.origin_x) / t.pixel_width).ceil() as i64 / ki + 2;
                let r_lo = ((y1 - t.origin_y) / t.pixel_height).floor() as i64 / ki - 2;
                let r_hi = ((y1 - gsd - t.origin_y) / t.pixel_height).ceil() as i64 / ki + 2;
                for br in r_lo..r_hi {
                    for bc in c_lo..c_hi {
                        let centre = |b: i64| (b * ki) as f64 + (k as f64 - 1.0) / 2.0;
                        let (x, y) = t.pixel_center(centre(bc), centre(br));
                        if !(x >= x0 && x < x0 + gsd && y <= y1 && y > y1 - gsd) {
                            continue;
                        }
                        spanned += k * k;
                        for r in br * ki..(br + 1) * ki {
                            for c in bc * ki..(bc + 1) * ki {
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
        // Pixels as blocks, then 2- and 3-pixel blocks (a DEM edge cuts the last ones short: 120 = 40 × 3, 90 = 45 × 2).
        for &(cx, cy, gsd, k) in &[
            (1000.0 + 300.0, 5000.0 - 225.0, 17.0, 1),
            (1000.0 + 12.3, 5000.0 - 401.7, 9.5, 1),
            (1000.0 + 600.0, 5000.0 - 450.0, 40.0, 1),
            (1000.0 + 300.0, 5000.0 - 225.0, 17.0, 2),
            (1000.0 + 12.3, 5000.0 - 401.7, 31.0, 3),
            (1000.0 + 597.5, 5000.0 - 447.5, 40.0, 3),
            (1000.0 + 421.0, 5000.0 - 91.0, 23.0, 7),
        ] {
            let got = ContextSampler::with_block_px(&dem, gsd, k).window(cx, cy);
            let want = brute_force(&dem, cx, cy, gsd, k);
            assert_eq!(got.len(), CONTEXT_PX * CONTEXT_PX);
            let (mut nans, mut cells) = (0, 0);
            for (k, (g, w)) in got.iter().zip(&want).enumerate() {
                assert_eq!(g.is_nan(), w.is_nan(), "cell {k}: {g} vs {w}");
                if w.is_nan() {
                    nans += 1;
                } else {
                    assert!((g - w).abs() <= 1e-3, "cell {k}: {g} vs {w}");
                    cells += 1;
                }
            }
            assert!(
                nans > 0 && cells > 8,
                "the cases reach outside and inside: {nans} NaN, {cells} valued"
            );
        }
    }

    #[test]
    fn blocks_are_a_sixteenth_of_a_cell_or_single_pixels() {
        let dem = dem(64, 64, |_, _| -1400.0);
        // 5 m pixels: 512 m cells → ⌊512 / 80⌋ = 6-pixel blocks; 160 m → 2; below 160 m, pixels.
        for (gsd, k) in [(512.0, 6), (1024.0, 12), (160.0, 2), (159.0, 1), (20.0, 1)] {
            assert_eq!(
                ContextSampler::new(&dem, gsd).block_px(),
                k,
                "{gsd} m cells"
            );
        }
    }

    #[test]
    fn a_plane_averages_to_its_value_at_pixel_aligned_cell_centres() {
        let (a, b) = (0.25f64, -0.5f64);
        let dem = dem(400, 400, |c, r| {
            (-1200.0 + a * c as f64 + b * r as f64) as f32
        });
        // 4-pixel cells centred on a pixel corner: each cell holds exactly 4 × 4 pixels, as single pixels or as
        // 2 × 2 aligned blocks.
        let (cx, cy) = dem.transform.pixel_edge(200.0, 200.0);
        for k in [1, 2] {
            let got = ContextSampler::with_block_px(&dem, 20.0, k).window(cx, cy);
            plane_cells_match(&got, a, b);
        }
    }

    fn plane_cells_match(got: &[f32], a: f64, b: f64) {
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

//! Cast shadows and camera visibility on a full DEM.
//!
//! Two implementations of one quantity, the visible fraction of a source (the sun's 0.53° disk, or a point camera):
//! - [`HorizonGrid::march_visible_fraction`]: the reference — marches the horizon from one cell toward the source,
//!   with sphere curvature, and skips the march when the source is above the steepest slope on the DEM (exact:
//!   terrain that never rises faster than the ray cannot block it).
//! - [`HorizonGrid::sweep_visible_fraction`]: the raster version, O(cells × disk samples): propagates a
//!   "shadow surface" one pixel at a time away from the source. Tests hold it to the reference.
//!
//! The stages call neither directly: [`visibility_window`] cuts the part of a [`HeightField`] that can hold
//! blockers for one crop and sweeps only that (the projection stage and the synthetic world's orthos use it).
//!
//! Directions are given on the grid: a horizontal unit step toward the source in (col, row) pixels (rows grow
//! southward) and the source elevation angle above the local horizontal.

/// Angular radius of the sun seen from the Moon (0.53° disk).
pub const SUN_ANGULAR_RADIUS_RAD: f64 = 0.2665 * std::f64::consts::PI / 180.0;

/// Heights on a square-pixel grid, with the steepest slope precomputed for the march-skipping test.
#[derive(Debug)]
pub struct HorizonGrid<'a> {
    pub heights: &'a [f32],
    pub width: usize,
    pub height: usize,
    pub gsd_m: f64,
    max_height_m: f64,
    /// tan of the steepest slope between 8-neighbours anywhere on the grid.
    max_slope_tan: f64,
}

/// Where the source is, seen from the terrain.
#[derive(Debug, Clone, Copy)]
pub struct SourceDirection {
    /// Horizontal direction toward the source in pixel units (col, row); normalised internally.
    pub toward_col: f64,
    pub toward_row: f64,
    /// Elevation of the source's centre above the horizontal, radians.
    pub elevation_rad: f64,
    /// Angular radius of the source (0 for a point, e.g. a camera).
    pub angular_radius_rad: f64,
}

impl SourceDirection {
    /// From a unit vector toward the source in `frame`'s ENU axes, for a north-up raster in that frame's map CRS
    /// (columns = +x, rows = −y). The horizontal direction goes through the map Jacobian, so grid north may differ
    /// from true north (polar stereographic) without skewing shadows.
    pub fn from_enu(
        dir_enu: glam::DVec3,
        frame: &crate::science::crs::LocalFrame,
        angular_radius_rad: f64,
    ) -> Self {
        let horizontal = (dir_enu.x * dir_enu.x + dir_enu.y * dir_enu.y).sqrt();
        let on_map = frame.en_to_map(dir_enu.x, dir_enu.y);
        Self {
            toward_col: on_map.x,
            toward_row: -on_map.y,
            elevation_rad: dir_enu.z.atan2(horizontal),
            angular_radius_rad,
        }
    }
}

/// Turn heights above the sphere into the *up* coordinate of the ENU frame at (origin_col, origin_row): each cell
/// drops by r²/2R with r its distance from the origin. Sweeping these with the source direction of that one frame
/// is exact to second order across the grid (the tilt of far cells' local verticals is what the drop encodes);
/// without it a 20 km shadow search would be off by 115 m of height, more than the sun's disk near the terminator.
pub fn drop_for_curvature(
    heights: &mut [f32],
    width: usize,
    gsd_m: f64,
    origin_col: f64,
    origin_row: f64,
) {
    let two_r = 2.0 * crate::science::crs::MOON_RADIUS_M;
    for (i, h) in heights.iter_mut().enumerate() {
        let (dc, dr) = (
            (i % width) as f64 - origin_col,
            (i / width) as f64 - origin_row,
        );
        *h -= ((dc * dc + dr * dr) * gsd_m * gsd_m / two_r) as f32;
    }
}

/// Fraction of a disk of angular radius `radius` whose centre is `above` radians above a straight horizon.
pub fn disk_fraction_above(above: f64, radius: f64) -> f64 {
    if radius <= 0.0 {
        return if above > 0.0 { 1.0 } else { 0.0 };
    }
    let u = (above / radius).clamp(-1.0, 1.0);
    // Area of the unit disk below the horizon line (a circular segment at signed distance u), over π.
    1.0 - (u.acos() - u * (1.0 - u * u).sqrt()) / std::f64::consts::PI
}

impl<'a> HorizonGrid<'a> {
    pub fn new(heights: &'a [f32], width: usize, height: usize, gsd_m: f64) -> Self {
        assert_eq!(heights.len(), width * height);
        // Max height and steepest 8-neighbour rise, per row in parallel (max is order-independent: same result).
        use rayon::prelude::*;
        let (max_height_m, max_rise) = (0..height)
            .into_par_iter()
            .map(|row| {
                let (mut top, mut rise) = (f64::NEG_INFINITY, 0.0f64);
                for col in 0..width {
                    let h = heights[row * width + col];
                    if !h.is_finite() {
                        continue;
                    }
                    top = top.max(h as f64);
                    // Right, down, and both diagonals cover every 8-neighbour pair once.
                    for (dc, dr, dist) in [
                        (1, 0, 1.0),
                        (0, 1, 1.0),
                        (1, 1, std::f64::consts::SQRT_2),
                        (-1, 1, std::f64::consts::SQRT_2),
                    ] {
                        let (c2, r2) = (col as i64 + dc, row as i64 + dr);
                        if c2 < 0 || r2 < 0 || c2 >= width as i64 || r2 >= height as i64 {
                            continue;
                        }
                        let h2 = heights[r2 as usize * width + c2 as usize];
                        if h2.is_finite() {
                            rise = rise.max((h2 - h).abs() as f64 / (dist * gsd_m));
                        }
                    }
                }
                (top, rise)
            })
            .reduce(
                || (f64::NEG_INFINITY, 0.0),
                |a, b| (a.0.max(b.0), a.1.max(b.1)),
            );
        // Bilinear interpolation between cells can't be steeper than the steepest 8-neighbour pair by more than √2.
        Self {
            heights,
            width,
            height,
            gsd_m,
            max_height_m,
            max_slope_tan: max_rise * std::f64::consts::SQRT_2,
        }
    }

    /// True when the source's lowest point is above the steepest slope: nothing can cast a shadow (exact skip).
    pub fn source_clears_all_slopes(&self, dir: &SourceDirection) -> bool {
        (dir.elevation_rad - dir.angular_radius_rad).tan() > self.max_slope_tan
            && dir.elevation_rad - dir.angular_radius_rad > 0.0
    }

    /// Visible fraction of the source from cell (col, row), by marching the horizon toward it (the reference).
    /// Heights are above the sphere and `dir` is in the cell's own local frame; the march lowers each sample by
    /// d²/2R (sphere curvature seen from the cell).
    pub fn march_visible_fraction(&self, col: usize, row: usize, dir: &SourceDirection) -> f64 {
        if self.source_clears_all_slopes(dir) {
            return 1.0;
        }
        let h0 = self.heights[row * self.width + col] as f64;
        let horizontal = (dir.toward_col * dir.toward_col + dir.toward_row * dir.toward_row).sqrt();
        if horizontal < 1e-12 {
            return 1.0; // source at zenith
        }
        let (step_c, step_r) = (
            dir.toward_col / horizontal * 0.5,
            dir.toward_row / horizontal * 0.5,
        );
        let step_m = 0.5 * self.gsd_m;
        let darkest = dir.elevation_rad + dir.angular_radius_rad;
        let mut horizon_tan = f64::NEG_INFINITY;
        let radius = crate::science::crs::MOON_RADIUS_M;
        let (mut c, mut r) = (col as f64, row as f64);
        let mut dist = 0.0;
        loop {
            c += step_c;
            r += step_r;
            dist += step_m;
            if c < 0.0 || r < 0.0 || c > (self.width - 1) as f64 || r > (self.height - 1) as f64 {
                break;
            }
            let h = crate::science::raster::bilinear(self.heights, self.width, self.height, c, r)
                as f64;
            let tan_here = (h - dist * dist / (2.0 * radius) - h0) / dist;
            horizon_tan = horizon_tan.max(tan_here);
            if horizon_tan.atan() >= darkest {
                return 0.0; // the whole disk is already hidden
            }
            // Beyond here the ray at the current horizon is above every height on the grid.
            if h0 + dist * horizon_tan.max((dir.elevation_rad - dir.angular_radius_rad).tan())
                > self.max_height_m
            {
                break;
            }
        }
        if horizon_tan == f64::NEG_INFINITY {
            return 1.0;
        }
        disk_fraction_above(
            dir.elevation_rad - horizon_tan.atan(),
            dir.angular_radius_rad,
        )
    }

    /// Visible fraction of the source for every cell: a line sweep per disk sample, weighted by chord length.
    ///
    /// `disk_samples` elevation samples across the disk (1 = hard shadow at the centre). Returns row-major f32.
    pub fn sweep_visible_fraction(&self, dir: &SourceDirection, disk_samples: usize) -> Vec<f32> {
        self.sweep_visible_fraction_in(dir, disk_samples, 0..self.width, 0..self.height)
    }

    /// [`Self::sweep_visible_fraction`] kept only for the cells `cols × rows` (row-major over that rectangle):
    /// the sweeps still cross the whole grid, so blockers anywhere upstream count, but only the area of interest
    /// is stored (a window extended toward a low sun can be 4× the area it serves).
    pub fn sweep_visible_fraction_in(
        &self,
        dir: &SourceDirection,
        disk_samples: usize,
        cols: std::ops::Range<usize>,
        rows: std::ops::Range<usize>,
    ) -> Vec<f32> {
        let n = cols.len() * rows.len();
        if self.source_clears_all_slopes(dir) {
            return vec![1.0; n];
        }
        let samples = if dir.angular_radius_rad > 0.0 {
            disk_samples.max(1)
        } else {
            1
        };
        // Midpoint rule over the disk's vertical extent; weight = chord length at that height. The sweeps are
        // independent, so they run in parallel; their sum is taken in sample order (same bytes on any thread count).
        let disk: Vec<(f64, f64)> = (0..samples)
            .map(|k| {
                let y = if samples == 1 {
                    0.0
                } else {
                    -1.0 + (2.0 * k as f64 + 1.0) / samples as f64
                };
                let weight = if samples == 1 {
                    1.0
                } else {
                    (1.0 - y * y).sqrt()
                };
                // A disk straddling the zenith: its samples beyond 90° are the same as at 90° (source overhead).
                let elevation = (dir.elevation_rad + y * dir.angular_radius_rad)
                    .min(std::f64::consts::FRAC_PI_2 - 1e-9);
                (weight, elevation)
            })
            .collect();
        let lit: Vec<Vec<bool>> = {
            use rayon::prelude::*;
            disk.par_iter()
                .map(|&(_, elevation)| {
                    self.sweep_hard(
                        (dir.toward_col, dir.toward_row),
                        elevation,
                        (cols.clone(), rows.clone()),
                    )
                })
                .collect()
        };
        let mut total = vec![0.0f32; n];
        let mut weight_sum = 0.0;
        for ((weight, _), lit) in disk.iter().zip(lit) {
            for (t, l) in total.iter_mut().zip(lit) {
                *t += *weight as f32 * l as u8 as f32;
            }
            weight_sum += weight;
        }
        total.iter_mut().for_each(|t| *t /= weight_sum as f32);
        total
    }

    /// Hard-edged visibility of a point source at `elevation` (radians): the shadow-surface recurrence
    /// S(p) = max(h(p), S(p + step) − |step|·tan(elevation)), processed from the source side over the whole grid;
    /// returned for the cells `cols × rows` only (row-major over that rectangle).
    fn sweep_hard(
        &self,
        (toward_col, toward_row): (f64, f64),
        elevation: f64,
        (cols, rows): (std::ops::Range<usize>, std::ops::Range<usize>),
    ) -> Vec<bool> {
        let (w, h) = (self.width, self.height);
        let (aoi_w, aoi_n) = (cols.len(), cols.len() * rows.len());
        if elevation <= 0.0 {
            return vec![false; aoi_n];
        }
        if elevation.tan() > self.max_slope_tan {
            return vec![true; aoi_n];
        }
        let tan_e = elevation.tan();
        // Work on a view where the dominant axis of the direction is "columns" and the source lies at lower index.
        let col_major = toward_col.abs() >= toward_row.abs();
        let (major, minor) = if col_major {
            (toward_col, toward_row)
        } else {
            (toward_row, toward_col)
        };
        if major.abs() < 1e-15 {
            return vec![true; aoi_n];
        }
        let slope = minor / major.abs(); // minor-axis offset per major step toward the source
        let step_m = self.gsd_m * (1.0 + slope * slope).sqrt();
        let (n_major, n_minor) = if col_major { (w, h) } else { (h, w) };
        let (aoi_major, aoi_minor) = if col_major {
            (cols.clone(), rows.clone())
        } else {
            (rows.clone(), cols.clone())
        };
        let index = |maj: usize, min: usize| {
            if col_major {
                min * w + maj
            } else {
                maj * w + min
            }
        };
        let aoi_index = |maj: usize, min: usize| {
            let (c, r) = if col_major { (maj, min) } else { (min, maj) };
            (r - rows.start) * aoi_w + (c - cols.start)
        };
        let toward_low = major < 0.0; // source toward decreasing major index
        let mut lit = vec![true; aoi_n];
        let mut prev = vec![f64::NEG_INFINITY; n_minor];
        let mut cur = vec![0.0f64; n_minor];
        for step in 0..n_major {
            let maj = if toward_low { step } else { n_major - 1 - step };
            let keep = aoi_major.contains(&maj);
            for (min, cur_s) in cur.iter_mut().enumerate() {
                let hh = self.heights[index(maj, min)] as f64;
                let hh = if hh.is_finite() {
                    hh
                } else {
                    f64::NEG_INFINITY
                };
                // Upstream neighbour: one major step toward the source, minor offset by `slope`.
                let upstream = if step == 0 {
                    f64::NEG_INFINITY
                } else {
                    let pos = min as f64 + slope;
                    if pos < 0.0 || pos > (n_minor - 1) as f64 {
                        f64::NEG_INFINITY
                    } else {
                        let lo = pos.floor() as usize;
                        let hi = (lo + 1).min(n_minor - 1);
                        let f = pos - lo as f64;
                        let (a, b) = (prev[lo], prev[hi]);
                        if a == f64::NEG_INFINITY || b == f64::NEG_INFINITY {
                            a.max(b)
                        } else {
                            a * (1.0 - f) + b * f
                        }
                    }
                };
                let shadow_top = upstream - step_m * tan_e;
                if keep && aoi_minor.contains(&min) {
                    lit[aoi_index(maj, min)] = hh >= shadow_top;
                }
                *cur_s = hh.max(shadow_top);
            }
            std::mem::swap(&mut prev, &mut cur);
        }
        lit
    }
}

/// A north-up height raster (heights above the sphere, NaN = nodata) with its georeferencing and total relief.
#[derive(Debug, Clone, Copy)]
pub struct HeightField<'a> {
    pub heights: &'a [f32],
    pub width: usize,
    pub height: usize,
    pub transform: crate::science::raster::GeoTransform,
    /// Highest minus lowest finite height: bounds the longest shadow anything on this raster can receive.
    pub relief_m: f64,
}

impl<'a> HeightField<'a> {
    pub fn new(
        heights: &'a [f32],
        width: usize,
        height: usize,
        transform: crate::science::raster::GeoTransform,
    ) -> Self {
        let (lo, hi) = heights
            .iter()
            .filter(|h| h.is_finite())
            .fold((f32::MAX, f32::MIN), |(a, b), &h| (a.min(h), b.max(h)));
        let relief_m = if hi >= lo { (hi - lo) as f64 } else { 0.0 };
        Self {
            heights,
            width,
            height,
            transform,
            relief_m,
        }
    }
}

/// Visible fraction of one source over a window of a [`HeightField`] (window pixel (0, 0) = field pixel
/// (col0, row0)).
#[derive(Debug, Clone)]
pub struct VisibilityWindow {
    pub col0: usize,
    pub row0: usize,
    pub width: usize,
    pub height: usize,
    pub fraction: Vec<f32>,
    /// Cells the sweep crossed: the area of interest extended toward the source (only the former is stored).
    pub swept_cells: usize,
}

impl VisibilityWindow {
    /// Visible fraction of field cell (col, row) (its centre), or 0 outside the window.
    pub fn cell(&self, col: usize, row: usize) -> f32 {
        match (col.checked_sub(self.col0), row.checked_sub(self.row0)) {
            (Some(c), Some(r)) if c < self.width && r < self.height => {
                self.fraction[r * self.width + c]
            }
            _ => 0.0,
        }
    }

    /// Bilinear visible fraction at continuous *field* pixel coordinates (pixel-centre convention).
    pub fn at(&self, col: f64, row: f64) -> f32 {
        crate::science::raster::bilinear(
            &self.fraction,
            self.width,
            self.height,
            col - self.col0 as f64,
            row - self.row0 as f64,
        )
    }
}

/// Sweep a source's visibility over the field pixels `cols × rows` (half-open ranges), extended toward the source by
/// the longest shadow the field's relief can cast at the source's elevation (capped at 20 km), so blockers outside
/// the area of interest are seen. Heights are first dropped into `frame`'s up coordinate ([`drop_for_curvature`]) so the one
/// direction `toward_source_enu` (in `frame`) holds across the window.
pub fn visibility_window(
    field: &HeightField<'_>,
    cols: std::ops::Range<usize>,
    rows: std::ops::Range<usize>,
    frame: &crate::science::crs::LocalFrame,
    toward_source_enu: glam::DVec3,
    angular_radius_rad: f64,
    disk_samples: usize,
) -> VisibilityWindow {
    let (cols, rows) = (
        cols.start.min(field.width)..cols.end.min(field.width),
        rows.start.min(field.height)..rows.end.min(field.height),
    );
    let gsd = field.transform.gsd_m();
    let elevation = toward_source_enu.z.clamp(-1.0, 1.0).asin().max(1e-3);
    let dir = SourceDirection::from_enu(toward_source_enu, frame, angular_radius_rad);
    // Blockers lie at most `reach_px` away *toward the source*, and the sweep runs from the source side, so cells on
    // the far side never affect the area of interest: extend toward the source only, per axis by the ray's share
    // (+10 % for the grid's small rotation against the frame, +4 px for interpolation). Extending all four sides by
    // the full reach swept ~2-4× the cells for the same values.
    let reach_px = (field.relief_m / elevation.tan()).min(20_000.0) / gsd;
    let norm = dir.toward_col.hypot(dir.toward_row).max(1e-12);
    let extent = |component: f64, toward: bool| {
        if toward {
            (1.1 * reach_px * component.abs() / norm).ceil() as usize + 4
        } else {
            4
        }
    };
    let col0 = cols
        .start
        .saturating_sub(extent(dir.toward_col, dir.toward_col < 0.0));
    let row0 = rows
        .start
        .saturating_sub(extent(dir.toward_row, dir.toward_row < 0.0));
    let col1 = (cols.end + extent(dir.toward_col, dir.toward_col > 0.0)).min(field.width);
    let row1 = (rows.end + extent(dir.toward_row, dir.toward_row > 0.0)).min(field.height);
    let (width, height) = (col1 - col0, row1 - row0);
    let mut window: Vec<f32> = (row0..row1)
        .flat_map(|r| {
            field.heights[r * field.width + col0..r * field.width + col1]
                .iter()
                .copied()
        })
        .collect();
    let (oc, or) = field
        .transform
        .map_to_pixel(frame.origin_map.x, frame.origin_map.y);
    drop_for_curvature(&mut window, width, gsd, oc - col0 as f64, or - row0 as f64);
    let grid = HorizonGrid::new(&window, width, height, gsd);
    // Only the area of interest is kept: the extension exists to hold blockers, not answers.
    let fraction = grid.sweep_visible_fraction_in(
        &dir,
        disk_samples,
        cols.start - col0..cols.end - col0,
        rows.start - row0..rows.end - row0,
    );
    VisibilityWindow {
        col0: cols.start,
        row0: rows.start,
        width: cols.len(),
        height: rows.len(),
        fraction,
        swept_cells: width * height,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_window_extended_toward_the_source_matches_a_sweep_of_the_whole_field() {
        use crate::science::crs::{LocalFrame, LunarCrs};
        use crate::science::raster::GeoTransform;
        // 360 × 360 cells of 5 m: rolling terrain plus a 200 m ridge; area of interest in the middle.
        let (w, h, gsd) = (360usize, 360usize, 5.0);
        let heights: Vec<f32> = (0..w * h)
            .map(|i| {
                let (c, r) = ((i % w) as f64, (i / w) as f64);
                let ridge = if (c - 1.3 * r).abs() < 6.0 {
                    200.0
                } else {
                    0.0
                };
                (30.0 * (c / 17.0).sin() * (r / 23.0).cos()
                    + 12.0 * (c / 5.0 + r / 7.0).sin()
                    + ridge) as f32
            })
            .collect();
        let crs = LunarCrs::equirectangular(-43.3, -11.4);
        let (x0, y0) = crs.from_lonlat_deg(-11.4, -43.3).unwrap();
        let transform = GeoTransform::north_up(x0 - 900.0, y0 + 900.0, gsd);
        let field = HeightField::new(&heights, w, h, transform);
        let frame = LocalFrame::new(&crs, x0, y0, 0.0).unwrap();
        let (cols, rows) = (150..210, 160..200);
        for (azimuth_deg, elevation_deg) in [
            (30.0, 12.0),
            (135.0, 20.0),
            (250.0, 8.0),
            (330.0, 15.0),
            (90.0, 10.0),
        ] {
            let (az, el) = (f64::to_radians(azimuth_deg), f64::to_radians(elevation_deg));
            let toward = glam::DVec3::new(az.sin() * el.cos(), az.cos() * el.cos(), el.sin());
            let window = visibility_window(
                &field,
                cols.clone(),
                rows.clone(),
                &frame,
                toward,
                SUN_ANGULAR_RADIUS_RAD,
                4,
            );
            // The sweep reaches beyond the area of interest toward the source, but not over the whole field.
            assert!(
                window.swept_cells > cols.len() * rows.len() && window.swept_cells < w * h,
                "swept {} cells (area of interest {}, field {})",
                window.swept_cells,
                cols.len() * rows.len(),
                w * h
            );
            assert_eq!((window.width, window.height), (cols.len(), rows.len()));
            // Reference: the same sweep over the whole field.
            let mut all = heights.clone();
            let (oc, or) = transform.map_to_pixel(frame.origin_map.x, frame.origin_map.y);
            drop_for_curvature(&mut all, w, gsd, oc, or);
            let grid = HorizonGrid::new(&all, w, h, gsd);
            let dir = SourceDirection::from_enu(toward, &frame, SUN_ANGULAR_RADIUS_RAD);
            let reference = grid.sweep_visible_fraction(&dir, 4);
            let mut shadowed = 0;
            for r in rows.clone() {
                for c in cols.clone() {
                    let expected = reference[r * w + c];
                    shadowed += (expected < 1.0) as usize;
                    assert_eq!(
                        window.cell(c, r),
                        expected,
                        "azimuth {azimuth_deg}° at ({c}, {r})"
                    );
                }
            }
            assert!(
                shadowed > 0,
                "azimuth {azimuth_deg}°: the ridge must shadow part of the area"
            );
        }
    }

    #[test]
    fn disk_fraction_limits() {
        let r = SUN_ANGULAR_RADIUS_RAD;
        assert_eq!(disk_fraction_above(2.0 * r, r), 1.0);
        assert_eq!(disk_fraction_above(-2.0 * r, r), 0.0);
        assert!((disk_fraction_above(0.0, r) - 0.5).abs() < 1e-15);
        // Symmetry: f(u) + f(-u) = 1.
        assert!(
            (disk_fraction_above(0.3 * r, r) + disk_fraction_above(-0.3 * r, r) - 1.0).abs()
                < 1e-14
        );
    }

    /// A vertical step (wall) of height H at column c_wall, flat elsewhere: shadow length = H / tan(elevation).
    fn step_terrain(w: usize, h: usize, c_wall: usize, wall_m: f32) -> Vec<f32> {
        (0..w * h)
            .map(|i| if i % w < c_wall { wall_m } else { 0.0 })
            .collect()
    }

    #[test]
    fn march_matches_analytic_step_shadow() {
        let (w, h, gsd) = (200, 5, 1.0);
        let heights = step_terrain(w, h, 50, 10.0);
        let grid = HorizonGrid::new(&heights, w, h, gsd);
        let elev = 20f64.to_radians();
        let dir = SourceDirection {
            toward_col: -1.0,
            toward_row: 0.0,
            elevation_rad: elev,
            angular_radius_rad: 0.0,
        };
        // Wall top edge is between col 49 (10 m) and col 50 (0 m): bilinear puts the edge at col 49.
        let shadow_len_px = 10.0 / elev.tan() / gsd;
        for col in 50..w {
            let d = col as f64 - 49.0;
            let expected = if d < shadow_len_px { 0.0 } else { 1.0 };
            // Within one pixel of the analytic edge the discretisation decides; elsewhere it must agree.
            if (d - shadow_len_px).abs() > 1.0 {
                assert_eq!(
                    grid.march_visible_fraction(col, 2, &dir),
                    expected,
                    "col {col}"
                );
            }
        }
    }

    #[test]
    fn soft_shadow_is_half_lit_at_the_analytic_edge_of_a_ramp() {
        // A long ramp rising toward the sun exactly at the sun's elevation: the horizon sits at the sun centre.
        let (w, h, gsd) = (400, 3, 1.0);
        let elev = 15f64.to_radians();
        let heights: Vec<f32> = (0..w * h)
            .map(|i| ((w - i % w) as f64 * gsd * elev.tan()) as f32)
            .collect();
        let grid = HorizonGrid::new(&heights, w, h, gsd);
        let dir = SourceDirection {
            toward_col: -1.0,
            toward_row: 0.0,
            elevation_rad: elev,
            angular_radius_rad: SUN_ANGULAR_RADIUS_RAD,
        };
        let f = grid.march_visible_fraction(300, 1, &dir);
        // Curvature lowers the far horizon a hair, so slightly more than half the disk shows.
        assert!((f - 0.5).abs() < 0.05, "{f}");
        let lifted = SourceDirection {
            elevation_rad: elev + 2.0 * SUN_ANGULAR_RADIUS_RAD,
            ..dir
        };
        assert_eq!(grid.march_visible_fraction(300, 1, &lifted), 1.0);
    }

    #[test]
    fn steep_sun_skips_the_march_exactly() {
        let (w, h) = (64, 64);
        let heights: Vec<f32> = (0..w * h)
            .map(|i| ((i % w) as f32 * 0.3).sin() * 2.0)
            .collect();
        let grid = HorizonGrid::new(&heights, w, h, 1.0);
        let high = SourceDirection {
            toward_col: 1.0,
            toward_row: 0.3,
            elevation_rad: 80f64.to_radians(),
            angular_radius_rad: SUN_ANGULAR_RADIUS_RAD,
        };
        assert!(grid.source_clears_all_slopes(&high));
        assert!(grid
            .sweep_visible_fraction(&high, 5)
            .iter()
            .all(|&v| v == 1.0));
    }

    #[test]
    fn curvature_drop_puts_the_terminator_where_the_sphere_does() {
        // Perfectly smooth sphere (all heights 0), sun 0.1° above the horizon at the origin, toward −col. A point d
        // metres away from the sun sees it at 0.1° − d/R: the sphere itself hides it beyond d = R·tan(0.1°) ≈ 3032 m.
        let (w, h, gsd) = (4000, 3, 2.0);
        let mut heights = vec![0f32; w * h];
        drop_for_curvature(&mut heights, w, gsd, 0.0, 1.0);
        let grid = HorizonGrid::new(&heights, w, h, gsd);
        let dir = SourceDirection {
            toward_col: -1.0,
            toward_row: 0.0,
            elevation_rad: 0.1f64.to_radians(),
            angular_radius_rad: 0.0,
        };
        let lit = grid.sweep_visible_fraction(&dir, 1);
        let terminator_m = crate::science::crs::MOON_RADIUS_M * 0.1f64.to_radians().tan();
        for col in (0..w).step_by(7) {
            let d = col as f64 * gsd;
            if (d - terminator_m).abs() > 40.0 {
                assert_eq!(
                    lit[w + col],
                    (d < terminator_m) as u8 as f32,
                    "col {col} at {d} m"
                );
            }
        }
        // Without the drop, a flat grid is lit everywhere: curvature is what darkens it.
        let flat = vec![0f32; w * h];
        assert!(HorizonGrid::new(&flat, w, h, gsd)
            .sweep_visible_fraction(&dir, 1)
            .iter()
            .all(|&v| v == 1.0));
    }

    #[test]
    fn sweep_agrees_with_march_on_rough_terrain() {
        let (w, h) = (96, 80);
        let heights: Vec<f32> = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f32, (i / w) as f32);
                6.0 * (x * 0.21).sin() * (y * 0.17).cos() + 3.0 * (x * 0.05 + y * 0.11).sin()
            })
            .collect();
        let grid = HorizonGrid::new(&heights, w, h, 2.0);
        for (tc, tr, elev_deg) in [
            (1.0, 0.0, 12.0),
            (-0.6, 0.8, 20.0),
            (0.3, -0.95, 8.0),
            (-1.0, -1.0, 15.0),
        ] {
            let dir = SourceDirection {
                toward_col: tc,
                toward_row: tr,
                elevation_rad: f64::to_radians(elev_deg),
                angular_radius_rad: 0.0,
            };
            let sweep = grid.sweep_visible_fraction(&dir, 1);
            let (mut disagree, mut total) = (0, 0);
            for row in 0..h {
                for col in 0..w {
                    let m = grid.march_visible_fraction(col, row, &dir);
                    total += 1;
                    if (m - sweep[row * w + col] as f64).abs() > 0.5 {
                        disagree += 1;
                    }
                }
            }
            // Both discretise the shadow edge; they may differ only in edge cells.
            let share = disagree as f64 / total as f64;
            assert!(
                share < 0.03,
                "direction ({tc},{tr}) at {elev_deg}°: {share:.3} of cells disagree"
            );
        }
    }
}

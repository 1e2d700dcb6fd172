//! `g2r-train render`: novel views of a DEM by ray marching a pinhole camera's rays over the heightfield.
//!
//! - Geometry: one local ENU frame at the DEM centre (f64). A ray point's height above the sphere is exact
//!   (|body-fixed| − R); its map position comes from the frame's quadratic lon/lat model inverted by two Newton
//!   steps (the first-order Jacobian alone drifts ~20 m at 6 km from the centre at Tycho's latitude).
//! - Empty-space skipping with a max-mipmap: level 0 holds the max of each bilinear cell's four corners, level L
//!   the max of 2×2 cells of level L−1; the ray advances to the exit of the coarsest cell whose max lies below it
//!   (or to the depth of that max), and steps at most ¼ pixel once no cell is clear; hits are refined by bisection.
//! - Shading: N jittered rays per pixel (keyed ChaCha), a shadow ray toward a sun direction jittered over the solar
//!   disk, uniform Hapke or a parameter GeoTIFF from `infer`, and an optional Gaussian PSF.

use crate::contract::rng::keyed_rng;
use crate::science::brdf::{inverse_leaky_relu, BrdfModel};
use crate::science::crs::{LocalFrame, MOON_RADIUS_M};
use crate::science::geometry::{plane_normal, Cosines, HalfDiffCosines};
use crate::science::hapke::{hapke_i_over_f, HFunction, HapkeParams};
use crate::science::raster::Raster;
use anyhow::{bail, Result};
use glam::{DVec2, DVec3};
use rand::Rng;

use crate::science::horizon::SUN_ANGULAR_RADIUS_RAD;
use crate::views::trajectory::Pose;

const MAX_STEPS: usize = 200_000;

/// Fill nodata (NaN) pixels from their valid neighbours, ring by ring inward (each pass sets a hole pixel to the
/// mean of its valid 8-neighbours). Returns how many pixels were filled; a DEM with no valid pixel is left as is.
pub fn fill_holes(dem: &mut Raster) -> usize {
    let (w, h) = (dem.width, dem.height);
    let mut filled = 0;
    if !dem.data.iter().any(|v| v.is_finite()) {
        return 0;
    }
    loop {
        let holes: Vec<usize> = (0..w * h).filter(|&k| !dem.data[k].is_finite()).collect();
        if holes.is_empty() {
            return filled;
        }
        let updates: Vec<(usize, f32)> = holes
            .iter()
            .filter_map(|&k| {
                let (c, r) = ((k % w) as isize, (k / w) as isize);
                let (mut sum, mut n) = (0.0f64, 0usize);
                for (dc, dr) in [
                    (-1, -1),
                    (0, -1),
                    (1, -1),
                    (-1, 0),
                    (1, 0),
                    (-1, 1),
                    (0, 1),
                    (1, 1),
                ] {
                    let (cc, rr) = (c + dc, r + dr);
                    if cc >= 0 && rr >= 0 && (cc as usize) < w && (rr as usize) < h {
                        let v = dem.data[rr as usize * w + cc as usize];
                        if v.is_finite() {
                            sum += v as f64;
                            n += 1;
                        }
                    }
                }
                (n > 0).then(|| (k, (sum / n as f64) as f32))
            })
            .collect();
        for (k, v) in updates {
            dem.data[k] = v;
            filled += 1;
        }
    }
}

/// The DEM as a surface that rays from anywhere can be intersected with (a camera's, or a shadow ray toward the
/// sun): a max-mipmap over the bilinear surface. The stages' shadows march a cell's horizon instead
/// ([`crate::science::horizon`]); a test holds the two to each other.
pub struct RayCaster<'a> {
    dem: &'a Raster,
    pub frame: LocalFrame,
    /// levels[L] is (width, height, max heights).
    levels: Vec<(usize, usize, Vec<f32>)>,
    max_height: f64,
    min_height: f64,
}

impl<'a> RayCaster<'a> {
    pub fn new(dem: &'a Raster) -> Result<Self> {
        let (w, h) = (dem.width, dem.height);
        if w < 2 || h < 2 {
            bail!("the DEM must be at least 2 × 2 pixels");
        }
        let finite: Vec<f64> = dem
            .data
            .iter()
            .filter(|v| v.is_finite())
            .map(|&v| v as f64)
            .collect();
        if finite.len() != dem.data.len() {
            bail!("the DEM has nodata holes: fill them first (raycast::fill_holes; the marcher needs a closed surface)");
        }
        let mean = finite.iter().sum::<f64>() / finite.len() as f64;
        let (cx, cy) = dem
            .transform
            .pixel_center((w - 1) as f64 / 2.0, (h - 1) as f64 / 2.0);
        let frame = LocalFrame::new(&dem.crs, cx, cy, mean)?;
        let (mut cw, mut ch) = (w - 1, h - 1);
        let mut level0 = Vec::with_capacity(cw * ch);
        for r in 0..ch {
            for c in 0..cw {
                let v = [
                    dem.get(c, r),
                    dem.get(c + 1, r),
                    dem.get(c, r + 1),
                    dem.get(c + 1, r + 1),
                ];
                level0.push(v.into_iter().fold(f32::NEG_INFINITY, f32::max));
            }
        }
        let max_height = level0.iter().fold(f32::NEG_INFINITY, |a, &b| a.max(b)) as f64;
        let mut levels = vec![(cw, ch, level0)];
        while cw > 1 || ch > 1 {
            let (nw, nh) = (cw.div_ceil(2), ch.div_ceil(2));
            let prev = &levels.last().expect("level 0").2;
            let next: Vec<f32> = (0..nw * nh)
                .map(|k| {
                    let (c, r) = (k % nw * 2, k / nw * 2);
                    let mut m = f32::NEG_INFINITY;
                    for (dc, dr) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                        if c + dc < cw && r + dr < ch {
                            m = m.max(prev[(r + dr) * cw + c + dc]);
                        }
                    }
                    m
                })
                .collect();
            levels.push((nw, nh, next));
            (cw, ch) = (nw, nh);
        }
        let min_height = finite.iter().copied().fold(f64::INFINITY, f64::min);
        Ok(Self {
            dem,
            frame,
            levels,
            max_height,
            min_height,
        })
    }

    /// Height above the sphere of an ENU point (exact).
    fn height_of(&self, p: DVec3) -> f64 {
        self.frame.enu_to_body_point(p).length() - MOON_RADIUS_M
    }

    /// Continuous pixel coordinates of an ENU point's ground position.
    fn pixel_of(&self, p: DVec3) -> DVec2 {
        self.pixel_at_height(p, self.height_of(p))
    }

    /// [`Self::pixel_of`] for a point whose height above the sphere `h` is already known (the marcher needs both).
    fn pixel_at_height(&self, p: DVec3, h: f64) -> DVec2 {
        let f = &self.frame;
        // Invert at the point's own height: horizontal ENU offsets grow with (R + h) / (R + h0).
        let mut map = f.origin_map + f.en_to_map(p.x, p.y);
        for _ in 0..2 {
            let at = f.map_to_enu(map.x, map.y, h);
            map += f.en_to_map(p.x - at.x, p.y - at.y);
        }
        let (c, r) = self.dem.transform.map_to_pixel(map.x, map.y);
        DVec2::new(c, r)
    }

    fn inside(&self, px: DVec2) -> bool {
        px.x >= 0.0
            && px.y >= 0.0
            && px.x <= (self.dem.width - 1) as f64
            && px.y <= (self.dem.height - 1) as f64
    }

    fn surface(&self, px: DVec2) -> f64 {
        self.dem.bilinear(px.x, px.y) as f64
    }

    /// How far the ray may advance from `s` (at pixel `px`, height `h`) without crossing the surface, using the
    /// coarsest clear max-mipmap cell; `None` when no cell is clear (the ray is within a cell's height range).
    fn safe_step(&self, px: DVec2, h: f64, px_per_s: DVec2, up_per_s: f64) -> Option<f64> {
        for (level, (w, hh, maxes)) in self.levels.iter().enumerate().rev() {
            let size = (1usize << level) as f64;
            let (ci, ri) = ((px.x / size).floor(), (px.y / size).floor());
            if ci < 0.0 || ri < 0.0 || ci as usize >= *w || ri as usize >= *hh {
                continue;
            }
            let top = maxes[ri as usize * w + ci as usize] as f64;
            if top >= h {
                continue;
            }
            let exit = |pos: f64, lo: f64, v: f64| {
                if v > 1e-15 {
                    (lo + size - pos) / v
                } else if v < -1e-15 {
                    (lo - pos) / v
                } else {
                    f64::INFINITY
                }
            };
            let leave = exit(px.x, ci * size, px_per_s.x).min(exit(px.y, ri * size, px_per_s.y));
            let sink = if up_per_s < 0.0 {
                (h - top) / -up_per_s
            } else {
                f64::INFINITY
            };
            return Some(leave.min(sink).max(1e-3));
        }
        None
    }

    /// First surface point along `origin + s·dir` (ENU, |dir| = 1), or `None` if the ray leaves the DEM.
    pub fn intersect(&self, origin: DVec3, dir: DVec3) -> Option<(DVec3, DVec2)> {
        let gsd = self.dem.transform.gsd_m();
        // Skip straight to the slab below the highest terrain (h(s) ≥ h0 + s·dir.z: curvature only lifts it).
        let h0 = self.height_of(origin);
        let mut s = if h0 > self.max_height + 1.0 {
            if dir.z >= 0.0 {
                return None;
            }
            (h0 - self.max_height - 1.0) / -dir.z
        } else {
            0.0
        };
        // Map velocity of the ray (pixels per metre along it) from a finite difference: linear enough per ray.
        let px_per_s = self.pixel_of(origin + (s + 1.0) * dir) - self.pixel_of(origin + s * dir);
        let fine = 0.25 * gsd / dir.x.hypot(dir.y).max(dir.z.abs());
        let mut prev = s;
        let mut entered = false;
        for _ in 0..MAX_STEPS {
            let p = origin + s * dir;
            let h = self.height_of(p);
            let px = self.pixel_at_height(p, h);
            if !self.inside(px) {
                // Outside the DEM: a ray that has been over it and left, or that climbs away, misses.
                if entered || (dir.z >= 0.0 && h > self.max_height) || h < self.min_height - 1.0 {
                    return None;
                }
                s += gsd;
                continue;
            }
            entered = true;
            if h <= self.surface(px) {
                // Bisection between the last point above and this one.
                let (mut lo, mut hi) = (prev, s);
                for _ in 0..30 {
                    let mid = 0.5 * (lo + hi);
                    let q = origin + mid * dir;
                    let qh = self.height_of(q);
                    let qpx = self.pixel_at_height(q, qh);
                    if self.inside(qpx) && qh <= self.surface(qpx) {
                        hi = mid;
                    } else {
                        lo = mid;
                    }
                }
                let hit = origin + hi * dir;
                return Some((hit, self.pixel_of(hit)));
            }
            if dir.z >= 0.0 && h > self.max_height {
                return None;
            }
            prev = s;
            s += self.safe_step(px, h, px_per_s, dir.z).unwrap_or(fine);
        }
        None
    }

    /// Surface normal (ENU) at pixel coordinates, from central differences of the bilinear surface.
    pub fn normal(&self, px: DVec2) -> DVec3 {
        let t = &self.dem.transform;
        let d = 0.5;
        let dz_dc = (self.surface(px + DVec2::new(d, 0.0)) - self.surface(px - DVec2::new(d, 0.0)))
            / (2.0 * d);
        let dz_dr = (self.surface(px + DVec2::new(0.0, d)) - self.surface(px - DVec2::new(0.0, d)))
            / (2.0 * d);
        let (dz_dx, dz_dy) = (dz_dc / t.pixel_width, dz_dr / t.pixel_height);
        // Gradient in (east, north): J⁻ᵀ ∇_xy z, with J = map_to_en.
        let m = &self.frame.map_to_en;
        let det = m[0][0] * m[1][1] - m[0][1] * m[1][0];
        let dz_de = (m[1][1] * dz_dx - m[1][0] * dz_dy) / det;
        let dz_dn = (-m[0][1] * dz_dx + m[0][0] * dz_dy) / det;
        plane_normal(dz_de, dz_dn)
    }
}

/// What reflects the light.
pub enum Reflectance {
    Hapke(HapkeParams),
    /// Parameter maps from `infer` (activated values; same grid as the DEM).
    Params {
        model: BrdfModel,
        bands: Vec<Raster>,
    },
}

impl Reflectance {
    /// Parameter maps of `model` (one band per parameter, in the model's term order).
    pub fn from_param_bands(model: BrdfModel, bands: Vec<Raster>) -> Result<Self> {
        anyhow::ensure!(
            bands.len() == model.param_count(),
            "{} bands, but {} has {} parameters: pass a GeoTIFF written by `g2r-train infer`",
            bands.len(),
            model.name(),
            model.param_count()
        );
        Ok(Self::Params { model, bands })
    }

    fn value(&self, px: DVec2, c: &Cosines, hd: &HalfDiffCosines) -> f64 {
        match self {
            Self::Hapke(p) => hapke_i_over_f(p, c.cos_i, c.cos_e, c.cos_g, HFunction::Hapke2002),
            Self::Params { model, bands } => {
                let raw: Vec<f64> = bands
                    .iter()
                    .map(|b| inverse_leaky_relu(b.bilinear(px.x, px.y) as f64))
                    .collect();
                model.evaluate(&raw, c, hd)
            }
        }
    }
}

#[derive(Debug, Clone, Copy)]
pub struct ViewOptions {
    pub width: usize,
    pub height: usize,
    /// Horizontal field of view.
    pub fov_deg: f64,
    pub rays_per_pixel: usize,
    pub shadows: bool,
    /// Gaussian PSF sigma in pixels (0 = none).
    pub psf_sigma_px: f64,
    pub seed: u64,
}

/// Statistics of one rendered view.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct ViewStats {
    pub hit_fraction: f64,
    pub shadowed_fraction: f64,
    pub mean_i_over_f: f64,
}

/// Render one view: I/F per pixel (row-major, top row first); rays that miss the DEM give 0.
pub fn render_view(
    field: &RayCaster,
    reflectance: &Reflectance,
    pose: &Pose,
    sun_body: DVec3,
    options: &ViewOptions,
    view_index: u64,
) -> (Vec<f64>, ViewStats) {
    let frame = &field.frame;
    let camera = frame.body_point_to_enu(pose.position_body_m);
    let sun = frame.sun_dir_enu(sun_body);
    // Two unit vectors across the sun's disk, for soft-shadow jitter.
    let across = sun.any_orthonormal_pair();
    let focal = (options.width as f64 / 2.0) / (options.fov_deg.to_radians() / 2.0).tan();
    let mut rng = keyed_rng(options.seed, "render-rays", view_index);
    let (mut hits, mut shadowed, mut samples) = (0usize, 0usize, 0usize);
    let mut image = vec![0.0; options.width * options.height];
    for j in 0..options.height {
        for i in 0..options.width {
            let mut sum = 0.0;
            for _ in 0..options.rays_per_pixel.max(1) {
                let (u, v): (f64, f64) = if options.rays_per_pixel > 1 {
                    (rng.random(), rng.random())
                } else {
                    (0.5, 0.5)
                };
                let cam = DVec3::new(
                    (i as f64 + u - options.width as f64 / 2.0) / focal,
                    (j as f64 + v - options.height as f64 / 2.0) / focal,
                    1.0,
                )
                .normalize();
                let dir = frame.body_dir_to_enu(pose.camera_to_body * cam).normalize();
                samples += 1;
                let Some((hit, px)) = field.intersect(camera, dir) else {
                    continue;
                };
                hits += 1;
                let normal = field.normal(px);
                let view = -dir;
                let c = Cosines::new(normal, sun, view);
                if c.cos_i <= 0.0 || c.cos_e <= 0.0 {
                    continue;
                }
                if options.shadows {
                    let (a, b): (f64, f64) = (
                        rng.random::<f64>() * std::f64::consts::TAU,
                        rng.random::<f64>().sqrt(),
                    );
                    let jitter = SUN_ANGULAR_RADIUS_RAD * b;
                    let towards =
                        (sun + jitter * (a.cos() * across.0 + a.sin() * across.1)).normalize();
                    if field.intersect(hit + 0.05 * normal, towards).is_some() {
                        shadowed += 1;
                        continue;
                    }
                }
                sum += reflectance.value(px, &c, &HalfDiffCosines::new(normal, sun, view));
            }
            image[j * options.width + i] = sum / options.rays_per_pixel.max(1) as f64;
        }
    }
    if options.psf_sigma_px > 0.0 {
        // The PNGs are 16-bit: f32 precision is ample for the blur.
        let values: Vec<f32> = image.iter().map(|&v| v as f32).collect();
        image = crate::science::raster::gaussian_blur(
            &values,
            options.width,
            options.height,
            options.psf_sigma_px,
        )
        .into_iter()
        .map(f64::from)
        .collect();
    }
    let stats = ViewStats {
        hit_fraction: hits as f64 / samples.max(1) as f64,
        shadowed_fraction: shadowed as f64 / hits.max(1) as f64,
        mean_i_over_f: image.iter().sum::<f64>() / image.len().max(1) as f64,
    };
    (image, stats)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::science::crs::LunarCrs;
    use crate::science::raster::GeoTransform;

    /// A DEM of `n × n` 5 m pixels centred on map (0, −1 309 000) with heights from `f(col, row)`.
    fn dem(n: usize, f: impl Fn(usize, usize) -> f32) -> Raster {
        let half = n as f64 * 2.5;
        let mut r = Raster::new(
            n,
            n,
            GeoTransform::north_up(-half, -1_309_000.0 + half, 5.0),
            LunarCrs::equirectangular(-43.31, -11.36),
            0.0,
        );
        for row in 0..n {
            for col in 0..n {
                r.data[row * n + col] = f(col, row);
            }
        }
        r
    }

    fn nadir_pose(field: &RayCaster, altitude: f64, pitch_deg: f64) -> Pose {
        let f = &field.frame;
        crate::views::trajectory::pose_from_lonlat(
            f.origin_lon_deg,
            f.origin_lat_deg,
            altitude,
            0.0,
            pitch_deg,
            0.0,
        )
    }

    fn options(size: usize) -> ViewOptions {
        ViewOptions {
            width: size,
            height: size,
            fov_deg: 45.0,
            rays_per_pixel: 1,
            shadows: true,
            psf_sigma_px: 0.0,
            seed: 1,
        }
    }

    #[test]
    fn nadir_view_of_a_flat_dem_equals_hapke_at_the_known_geometry() {
        let raster = dem(64, |_, _| -1200.0);
        let field = RayCaster::new(&raster).unwrap();
        let pose = nadir_pose(&field, 2_000.0, 0.0);
        // Sun 40° from zenith toward the east, far away.
        let f = &field.frame;
        let sun_enu = DVec3::new(40f64.to_radians().sin(), 0.0, 40f64.to_radians().cos());
        let sun_body = f.enu_to_body_point(sun_enu * 1.5e11);
        let params = HapkeParams::lunar_typical();
        let mut opts = options(3);
        opts.fov_deg = 1.0;
        let (image, stats) = render_view(
            &field,
            &Reflectance::Hapke(params),
            &pose,
            sun_body,
            &opts,
            0,
        );
        assert_eq!(stats.hit_fraction, 1.0);
        let (ci, ce) = (40f64.to_radians().cos(), 1.0);
        let expected = hapke_i_over_f(&params, ci, ce, ci, HFunction::Hapke2002);
        assert!(
            (image[4] - expected).abs() < 2e-5 * expected,
            "{} vs {expected}",
            image[4]
        );
    }

    #[test]
    fn an_oblique_boresight_hits_where_the_sphere_geometry_says() {
        // Flat DEM at h = −1200 m: the surface is the sphere of radius R − 1200.
        let raster = dem(800, |_, _| -1200.0);
        let field = RayCaster::new(&raster).unwrap();
        let pose = nadir_pose(&field, 3_000.0, 20.0);
        let f = &field.frame;
        let origin = f.body_point_to_enu(pose.position_body_m);
        let dir = f
            .body_dir_to_enu(pose.camera_to_body * DVec3::Z)
            .normalize();
        let (hit, _) = field.intersect(origin, dir).expect("hits");
        // Exact ray-sphere intersection in body-fixed coordinates.
        let (o, d) = (pose.position_body_m, pose.camera_to_body * DVec3::Z);
        let radius = MOON_RADIUS_M - 1200.0;
        let b = o.dot(d);
        let t = -b - (b * b - (o.length_squared() - radius * radius)).sqrt();
        let expected = f.body_point_to_enu(o + t * d);
        assert!((hit - expected).length() < 0.05, "{hit} vs {expected}");
        // 20° off nadir from 4.2 km above the surface: ~1.5 km north of the nadir point.
        assert!(
            (hit.y - 4_200.0 * 20f64.to_radians().tan()).abs() < 30.0,
            "{hit}"
        );
    }

    #[test]
    fn ground_position_of_a_high_point_far_from_the_centre_is_exact() {
        // 4 km × 4 km; a point 1.9 km east and north of the centre, 2 km above the frame origin.
        let raster = dem(800, |_, _| -1200.0);
        let field = RayCaster::new(&raster).unwrap();
        let f = &field.frame;
        let (x, y) = (f.origin_map.x + 1_900.0, f.origin_map.y + 1_900.0);
        for h in [-1200.0, 800.0, 3000.0] {
            let p = f.map_to_enu(x, y, h);
            let px = field.pixel_of(p);
            let (c, r) = raster.transform.map_to_pixel(x, y);
            assert!(
                (px.x - c).abs() < 1e-3 && (px.y - r).abs() < 1e-3,
                "h {h}: {px} vs ({c}, {r})"
            );
        }
    }

    #[test]
    fn mipmap_marching_finds_the_same_surface_as_fine_brute_force_stepping() {
        let raster = dem(96, |c, r| {
            -1200.0
                + 30.0 * ((c as f32 / 7.0).sin() * (r as f32 / 5.0).cos())
                + if (40..44).contains(&c) { 80.0 } else { 0.0 }
        });
        let field = RayCaster::new(&raster).unwrap();
        let mut rng = keyed_rng(3, "raycast-test", 0);
        let mut compared = 0;
        for _ in 0..200 {
            let origin = DVec3::new(
                rng.random_range(-150.0..150.0),
                rng.random_range(-150.0..150.0),
                400.0,
            );
            let dir = DVec3::new(
                rng.random_range(-0.8..0.8),
                rng.random_range(-0.8..0.8),
                -1.0,
            )
            .normalize();
            let fast = field.intersect(origin, dir);
            // Brute force: 2 cm steps from the top of the terrain.
            let mut brute = None;
            let mut s = 0.0;
            while s < 3_000.0 {
                let p = origin + s * dir;
                let px = field.pixel_of(p);
                if !field.inside(px) {
                    if s > 0.0 && brute.is_none() && field.height_of(p) < field.max_height {
                        break;
                    }
                } else if field.height_of(p) <= field.surface(px) {
                    brute = Some(p);
                    break;
                }
                s += 0.02;
            }
            match (fast, brute) {
                (Some((a, _)), Some(b)) => {
                    assert!((a - b).length() < 0.05, "{a} vs {b}");
                    compared += 1;
                }
                (None, None) => {}
                (a, b) => panic!("disagree: mipmap {a:?}, brute {b:?}"),
            }
        }
        assert!(compared > 80, "{compared}");
    }

    /// The view renderer's shadow ray and the stages' horizon march ([`crate::science::horizon`]) are two
    /// marchers of one surface: 3D rays from any point through a max-mipmap, and a cell's horizon toward a distant
    /// source. On rolling terrain under a 12° sun from the north-east, every cell the march sees fully lit (or
    /// fully hidden) with a 0.3° margin on either side of the sun's centre (a disk of that radius wholly above, or
    /// wholly below, its horizon) is lit (shadowed) by the ray toward the sun's centre. Left out: cells within the
    /// margin of their horizon (the two samplings' to differ on), and cells whose own pixel rises toward the sun to
    /// within the margin of it (their own slope is their horizon).
    #[test]
    fn shadow_rays_agree_with_the_horizon_march_away_from_the_shadow_edge() {
        use crate::science::horizon::{HorizonGrid, SourceDirection};
        let n = 128;
        let raster = dem(n, |c, r| {
            let (x, y) = (c as f64 * 5.0, r as f64 * 5.0);
            (-1200.0
                + 40.0 * (x / 90.0).sin() * (y / 70.0).cos()
                + 12.0 * (x / 23.0 + y / 31.0).sin()) as f32
        });
        let field = RayCaster::new(&raster).unwrap();
        let frame = &field.frame;
        let (elevation, azimuth) = (12f64.to_radians(), 45f64.to_radians());
        let sun = DVec3::new(
            elevation.cos() * azimuth.sin(),
            elevation.cos() * azimuth.cos(),
            elevation.sin(),
        );
        let grid = HorizonGrid::new(&raster.data, n, n, 5.0);
        let margin = SourceDirection::from_enu(sun, frame, 0.3f64.to_radians());
        let toward = DVec2::new(margin.toward_col, margin.toward_row).normalize();
        let (mut lit, mut dark, mut disagree) = (0, 0, Vec::new());
        for row in 8..n - 8 {
            for col in 8..n - 8 {
                let seen = grid.march_visible_fraction(col, row, &margin);
                if seen != 0.0 && seen != 1.0 {
                    continue;
                }
                let (x, y) = raster.transform.pixel_center(col as f64, row as f64);
                let px = DVec2::new(col as f64, row as f64);
                // The steepest rise toward the sun within the cell's first pixel (on 0.01 px steps): where it comes
                // within the margin of the sun, the cell's own slope is its horizon, which a ray lifted off the
                // surface and a march sampled every half pixel each see their own way (the renderer darkens such
                // cells by their cosine). Blockers a pixel or more away are what the two must agree on.
                let h0 = raster.get(col, row) as f64;
                let own_rise = (1..=100)
                    .map(|k| {
                        let d = k as f64 * 0.01;
                        let ahead =
                            raster.bilinear(col as f64 + d * toward.x, row as f64 + d * toward.y);
                        ((ahead as f64 - h0) / (5.0 * d)).atan()
                    })
                    .fold(f64::NEG_INFINITY, f64::max);
                if own_rise >= margin.elevation_rad - margin.angular_radius_rad {
                    continue;
                }
                let ground = frame.map_to_enu(x, y, h0);
                // Lifted 1 mm off the surface, not the renderer's 5 cm: a 5 cm lift is 0.5° at 6 m, more than the
                // margin, and near blockers are what the two must agree on.
                let shadowed = field
                    .intersect(ground + 1e-3 * field.normal(px), sun)
                    .is_some();
                if shadowed != (seen == 0.0) {
                    disagree.push((col, row, seen));
                }
                if shadowed {
                    dark += 1;
                } else {
                    lit += 1;
                }
            }
        }
        // Both kinds of cell are compared (the terrain casts shadows; most of it is lit).
        assert!(dark > 500 && lit > 5_000, "dark {dark}, lit {lit}");
        assert!(
            disagree.is_empty(),
            "{} cells disagree: {:?}",
            disagree.len(),
            &disagree[..disagree.len().min(10)]
        );
    }

    #[test]
    fn a_ridge_casts_a_shadow_toward_the_west_under_an_eastern_sun() {
        // A 200 m north–south ridge at columns 60..64 of a flat plain.
        let raster = dem(128, |c, _| {
            if (60..64).contains(&c) {
                -1000.0
            } else {
                -1200.0
            }
        });
        let field = RayCaster::new(&raster).unwrap();
        let f = &field.frame;
        let sun_enu = DVec3::new(80f64.to_radians().sin(), 0.0, 80f64.to_radians().cos()); // 10° elevation, east
        let sun_body = f.enu_to_body_point(sun_enu * 1.5e11);
        let pose = nadir_pose(&field, 3_000.0, 0.0);
        let mut opts = options(64);
        opts.fov_deg = 12.0; // ~640 m across: the ridge and plains on both sides
        let reflect = Reflectance::Hapke(HapkeParams::lunar_typical());
        let (shadowed, stats) = render_view(&field, &reflect, &pose, sun_body, &opts, 0);
        opts.shadows = false;
        let (unshadowed, _) = render_view(&field, &reflect, &pose, sun_body, &opts, 0);
        assert!(stats.shadowed_fraction > 0.1, "{stats:?}");
        // The row through the centre: west of the ridge dark with shadows, lit without; east of it lit in both.
        let row = 32 * 64;
        let west: f64 = (row + 2..row + 20).map(|k| shadowed[k]).sum();
        let west_lit: f64 = (row + 2..row + 20).map(|k| unshadowed[k]).sum();
        let east: f64 = (row + 44..row + 62).map(|k| shadowed[k]).sum();
        assert!(west < 0.05 * west_lit, "west {west} vs {west_lit}");
        assert!(east > 0.5 * west_lit, "east {east}");
    }
}

#[cfg(test)]
mod fill_tests {
    use super::*;
    use crate::science::crs::LunarCrs;
    use crate::science::raster::GeoTransform;

    #[test]
    fn holes_fill_from_valid_neighbours_and_are_counted() {
        let mut r = Raster::new(
            5,
            5,
            GeoTransform::north_up(0.0, 0.0, 5.0),
            LunarCrs::equirectangular(0.0, 0.0),
            10.0,
        );
        r.data[12] = f32::NAN; // centre: all 8 neighbours are 10
        r.data[0] = f32::NAN;
        r.data[1] = f32::NAN; // corner pair: filled from their valid neighbours
        r.data[6] = 40.0;
        assert_eq!(fill_holes(&mut r), 3);
        assert!(r.data.iter().all(|v| v.is_finite()));
        assert_eq!(r.data[12], (7.0 * 10.0 + 40.0) / 8.0);
        let mut empty = Raster::new(
            2,
            2,
            GeoTransform::north_up(0.0, 0.0, 5.0),
            LunarCrs::equirectangular(0.0, 0.0),
            f32::NAN,
        );
        assert_eq!(fill_holes(&mut empty), 0);
    }
}

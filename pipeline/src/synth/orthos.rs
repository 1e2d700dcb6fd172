//! Render one orthoimage from the *true* fine DEM and true Hapke maps: per-pixel geometry in a local ENU frame per
//! tile, soft cast shadows and camera occlusion swept on the fine DEM, pushbroom camera position per ground point,
//! sensor noise. The ortho grid is the map grid, so rendering here is also orthorectification.

use dataset::science::crs::{LocalFrame, LunarCrs, MOON_RADIUS_M};
use dataset::science::geometry::{plane_normal, Cosines};
use dataset::science::hapke::{hapke_i_over_f, HFunction, HapkeParams};
use dataset::science::horizon::{visibility_window, HeightField, SUN_ANGULAR_RADIUS_RAD};
use dataset::science::raster::bilinear;
use rand_distr::{Distribution, Normal};
use rayon::prelude::*;

use super::acquisition::Strip;
use super::config::{AcquisitionConfig, ReflectanceConfig};
use super::reflectance::HapkeMaps;
use super::Grid;
use crate::rng::keyed_rng;

const TILE: usize = 64;

/// Counts reported with each rendered ortho.
#[derive(Debug, Clone, Copy, Default, serde::Serialize)]
pub struct RenderStats {
    pub pixels: usize,
    pub valid: usize,
    pub occluded: usize,
    /// Pixels with less than half the sun disk visible.
    pub shadowed: usize,
}

/// The true world an ortho is rendered from.
pub struct TruthScene<'a> {
    pub crs: &'a LunarCrs,
    pub fine: &'a Grid,
    pub field: HeightField<'a>,
    pub maps: &'a HapkeMaps,
}

impl<'a> TruthScene<'a> {
    pub fn new(crs: &'a LunarCrs, fine: &'a Grid, heights: &'a [f32], maps: &'a HapkeMaps) -> Self {
        let field = HeightField::new(heights, fine.width, fine.height, fine.transform());
        Self {
            crs,
            fine,
            field,
            maps,
        }
    }
}

/// Render the strip's ortho (NaN outside the strip or where the camera can't see the ground).
pub fn render_ortho(
    scene: &TruthScene,
    refl: &ReflectanceConfig,
    acq: &AcquisitionConfig,
    strip: &Strip,
    ortho_index: usize,
    seed: u64,
    progress: &indicatif::ProgressBar,
) -> (Vec<f32>, RenderStats) {
    let (crs, fine, heights, maps) = (scene.crs, scene.fine, scene.field.heights, scene.maps);
    let g = &strip.grid;
    let center = g.center(g.width / 2, g.height / 2);
    let strip_frame = LocalFrame::new(crs, center.0, center.1, 0.0).expect("valid CRS");
    // Sun (soft disk) and camera (point, ~50 km away: one direction per strip, mid-strip) visibility on the truth.
    let (fc0, fr0) = fine.to_pixel(g.min_x, g.max_y);
    let cols = (fc0.floor().max(0.0) as usize)
        ..((fc0 + (g.width as f64 * g.gsd_m / fine.gsd_m)).ceil() as usize + 1).min(fine.width);
    let rows = (fr0.floor().max(0.0) as usize)
        ..((fr0 + (g.height as f64 * g.gsd_m / fine.gsd_m)).ceil() as usize + 1).min(fine.height);
    let sun_enu = strip_frame.sun_dir_enu(strip.meta.sun_body());
    let sun_vis = visibility_window(
        &scene.field,
        cols.clone(),
        rows.clone(),
        &strip_frame,
        sun_enu,
        SUN_ANGULAR_RADIUS_RAD,
        acq.sun_disk_samples,
    );
    let mid = dataset::science::geometry::spacecraft_position_at(
        strip.meta.spacecraft_start_body_m.into(),
        strip.meta.spacecraft_stop_body_m.into(),
        0.5,
    );
    let camera_vis = visibility_window(
        &scene.field,
        cols,
        rows,
        &strip_frame,
        strip_frame.body_point_to_enu(mid).normalize(),
        0.0,
        1,
    );
    let constants = HapkeParams {
        w: 0.0,
        b: refl.b,
        c: refl.c,
        b_s0: refl.b_s0,
        h_s: refl.h_s,
        theta_bar_rad: refl.theta_bar_deg.to_radians(),
        porosity_k: 1.0,
    };
    let tiles_x = g.width.div_ceil(TILE);
    let tiles_y = g.height.div_ceil(TILE);
    progress.set_length((tiles_x * tiles_y) as u64);
    let tiles: Vec<(Vec<f32>, RenderStats)> = (0..tiles_x * tiles_y)
        .into_par_iter()
        .map(|t| {
            let (tx, ty) = (t % tiles_x, t / tiles_x);
            let (c0, r0) = (tx * TILE, ty * TILE);
            let (c1, r1) = ((c0 + TILE).min(g.width), (r0 + TILE).min(g.height));
            let mut out = vec![f32::NAN; (c1 - c0) * (r1 - r0)];
            let mut stats = RenderStats::default();
            let (tcx, tcy) = g.center((c0 + c1) / 2, (r0 + r1) / 2);
            let (fc, fr) = fine.to_pixel(tcx, tcy);
            let h_center = bilinear(heights, fine.width, fine.height, fc, fr) as f64;
            let frame = LocalFrame::new(crs, tcx, tcy, h_center).expect("valid CRS");
            let sun_dir = frame.sun_dir_enu(strip.meta.sun_body());
            // Map gradient → ENU gradient: ∇_EN z = (J⁻¹)ᵀ ∇_xy z.
            let (inv_e, inv_n) = (frame.en_to_map(1.0, 0.0), frame.en_to_map(0.0, 1.0));
            let mut rng = keyed_rng(seed, &format!("sensor-noise-{ortho_index}"), t as u64);
            let noise = Normal::new(0.0, 1.0).expect("unit normal");
            let step = fine.gsd_m;
            for row in r0..r1 {
                for col in c0..c1 {
                    let (x, y) = g.center(col, row);
                    stats.pixels += 1;
                    if !strip.contains(x, y) {
                        continue;
                    }
                    let (fc, fr) = fine.to_pixel(x, y);
                    let hgt = |dc: f64, dr: f64| {
                        bilinear(heights, fine.width, fine.height, fc + dc, fr + dr) as f64
                    };
                    let h = hgt(0.0, 0.0);
                    let dzdx = (hgt(1.0, 0.0) - hgt(-1.0, 0.0)) / (2.0 * step);
                    let dzdy = -(hgt(0.0, 1.0) - hgt(0.0, -1.0)) / (2.0 * step);
                    let grad_e = inv_e.x * dzdx + inv_e.y * dzdy;
                    let grad_n = inv_n.x * dzdx + inv_n.y * dzdy;
                    let p = frame.map_to_enu(x, y, h);
                    // The local vertical at p is tilted from the tile's by (E, N)/R: a slope of its own.
                    let normal =
                        plane_normal(grad_e + p.x / MOON_RADIUS_M, grad_n + p.y / MOON_RADIUS_M);
                    let camera_visible = camera_vis.at(fc, fr);
                    if camera_visible < 0.5 {
                        stats.occluded += 1;
                        continue;
                    }
                    let spacecraft = strip.meta.spacecraft_for_ground(frame.enu_to_body_point(p));
                    let view_dir = (frame.body_point_to_enu(spacecraft) - p).normalize();
                    let cos = Cosines::new(normal, sun_dir, view_dir);
                    let params = HapkeParams {
                        w: bilinear(&maps.w, fine.width, fine.height, fc, fr) as f64,
                        b: bilinear(&maps.b, fine.width, fine.height, fc, fr) as f64,
                        ..constants
                    };
                    let lit = sun_vis.at(fc, fr) as f64;
                    if lit < 0.5 {
                        stats.shadowed += 1;
                    }
                    let signal = lit
                        * hapke_i_over_f(
                            &params,
                            cos.cos_i,
                            cos.cos_e,
                            cos.cos_g,
                            HFunction::Hapke2002,
                        );
                    let value = signal * (1.0 + acq.noise_relative * noise.sample(&mut rng))
                        + acq.noise_absolute * noise.sample(&mut rng);
                    out[(row - r0) * (c1 - c0) + (col - c0)] = value.max(0.0) as f32;
                    stats.valid += 1;
                }
            }
            progress.inc(1);
            (out, stats)
        })
        .collect();
    let mut image = vec![f32::NAN; g.width * g.height];
    let mut total = RenderStats::default();
    for (t, (tile, stats)) in tiles.into_iter().enumerate() {
        let (tx, ty) = (t % tiles_x, t / tiles_x);
        let (c0, r0) = (tx * TILE, ty * TILE);
        let tw = (c0 + TILE).min(g.width) - c0;
        for (k, line) in tile.chunks(tw).enumerate() {
            image[(r0 + k) * g.width + c0..(r0 + k) * g.width + c0 + tw].copy_from_slice(line);
        }
        total.pixels += stats.pixels;
        total.valid += stats.valid;
        total.occluded += stats.occluded;
        total.shadowed += stats.shadowed;
    }
    (image, total)
}

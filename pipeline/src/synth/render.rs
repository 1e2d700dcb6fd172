//! Render one orthoimage from the *true* fine DEM and true Hapke maps: per-pixel geometry in a local ENU frame per
//! tile, soft cast shadows and camera occlusion swept on the fine DEM, pushbroom camera position per ground point,
//! sensor noise. The ortho grid is the map grid, so rendering here is also orthorectification.

use dataset::crs::{LocalFrame, LunarCrs, MOON_RADIUS_M};
use dataset::geometry::Cosines;
use dataset::hapke::{hapke_i_over_f, HFunction, HapkeParams};
use dataset::horizon::{drop_for_curvature, HorizonGrid, SourceDirection, SUN_ANGULAR_RADIUS_RAD};
use dataset::raster::bilinear;
use glam::DVec3;
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

/// A window of the fine grid with the sun / camera visibility rasters swept over it.
struct Visibility {
    c0: usize,
    r0: usize,
    width: usize,
    height: usize,
    sun: Vec<f32>,
    camera: Vec<f32>,
}

impl Visibility {
    fn sample(field: &[f32], v: &Visibility, fc: f64, fr: f64) -> f32 {
        bilinear(field, v.width, v.height, fc - v.c0 as f64, fr - v.r0 as f64)
    }
}

/// The true world an ortho is rendered from.
pub struct TruthScene<'a> {
    pub crs: &'a LunarCrs,
    pub fine: &'a Grid,
    pub heights: &'a [f32],
    pub maps: &'a HapkeMaps,
    /// Highest minus lowest true height: bounds the longest shadow any ortho can receive.
    pub relief_m: f64,
}

impl<'a> TruthScene<'a> {
    pub fn new(crs: &'a LunarCrs, fine: &'a Grid, heights: &'a [f32], maps: &'a HapkeMaps) -> Self {
        let (lo, hi) = heights
            .iter()
            .filter(|h| h.is_finite())
            .fold((f32::MAX, f32::MIN), |(a, b), &h| (a.min(h), b.max(h)));
        Self {
            crs,
            fine,
            heights,
            maps,
            relief_m: (hi - lo) as f64,
        }
    }
}

fn sweep_window(
    scene: &TruthScene,
    strip: &Strip,
    frame: &LocalFrame,
    acq: &AcquisitionConfig,
) -> Visibility {
    let (fine, heights) = (scene.fine, scene.heights);
    // Shadows can be cast from beyond the strip: extend the window by the longest possible shadow.
    let sun_enu = frame.sun_dir_enu(strip.meta.sun_body());
    let elevation = sun_enu.z.asin().max(1e-3);
    let margin_m = (scene.relief_m / elevation.tan()).min(20_000.0) + 4.0 * fine.gsd_m;
    let g = &strip.grid;
    let to_col = |x: f64| ((x - fine.min_x) / fine.gsd_m).floor();
    let to_row = |y: f64| ((fine.max_y - y) / fine.gsd_m).floor();
    let c0 = to_col(g.min_x - margin_m).max(0.0) as usize;
    let c1 = (to_col(g.max_x() + margin_m) as usize + 1).min(fine.width);
    let r0 = to_row(g.max_y + margin_m).max(0.0) as usize;
    let r1 = (to_row(g.min_y() - margin_m) as usize + 1).min(fine.height);
    let (width, height) = (c1 - c0, r1 - r0);
    let mut window: Vec<f32> = (r0..r1)
        .flat_map(|r| {
            heights[r * fine.width + c0..r * fine.width + c1]
                .iter()
                .copied()
        })
        .collect();
    // Heights in the strip frame's up coordinate, so its single sun/camera direction holds across the window.
    let (oc, or) = fine.to_pixel(frame.origin_map.x, frame.origin_map.y);
    drop_for_curvature(
        &mut window,
        width,
        fine.gsd_m,
        oc - c0 as f64,
        or - r0 as f64,
    );
    let horizon = HorizonGrid::new(&window, width, height, fine.gsd_m);
    let sun_dir = SourceDirection::from_enu(sun_enu, frame, SUN_ANGULAR_RADIUS_RAD);
    let sun = horizon.sweep_visible_fraction(&sun_dir, acq.sun_disk_samples);
    // Camera ~50 km away: one direction per strip (mid-strip) is accurate to the strip's angular width.
    let mid = dataset::geometry::spacecraft_position_at(
        strip.meta.spacecraft_start_body_m.into(),
        strip.meta.spacecraft_stop_body_m.into(),
        0.5,
    );
    let cam_dir = (frame.body_point_to_enu(mid)).normalize();
    let camera = horizon.sweep_visible_fraction(&SourceDirection::from_enu(cam_dir, frame, 0.0), 1);
    Visibility {
        c0,
        r0,
        width,
        height,
        sun,
        camera,
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
    let (crs, fine, heights, maps) = (scene.crs, scene.fine, scene.heights, scene.maps);
    let g = &strip.grid;
    let center = g.center(g.width / 2, g.height / 2);
    let strip_frame = LocalFrame::new(crs, center.0, center.1, 0.0).expect("valid CRS");
    let vis = sweep_window(scene, strip, &strip_frame, acq);
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
                    // The local vertical at p is tilted from the tile's by (E, N)/R.
                    let normal = DVec3::new(
                        -grad_e - p.x / MOON_RADIUS_M,
                        -grad_n - p.y / MOON_RADIUS_M,
                        1.0,
                    )
                    .normalize();
                    let camera_visible = Visibility::sample(&vis.camera, &vis, fc, fr);
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
                    let lit = Visibility::sample(&vis.sun, &vis, fc, fr) as f64;
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

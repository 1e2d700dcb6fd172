//! NAC-like acquisitions: long, narrow pushbroom strips with irregular nodata borders, varied sun, 70 % nadir /
//! 30 % slewed, from a ~50 km circular orbit. Produces the metadata a real user would have, plus the strip
//! outline (which only the renderer uses; the pipeline finds valid pixels from nodata, as with real data).

use dataset::contract::acquisition::{iso_utc_from_j2000_seconds, AcquisitionMetadata};
use dataset::science::crs::{LocalFrame, LunarCrs};
use glam::{DMat3, DQuat, DVec2, DVec3};
use rand::Rng;

use super::config::AcquisitionConfig;
use super::noise::gradient_noise;
use super::Grid;
use crate::rng::{keyed_rng, keyed_u64};

/// Mean Earth–Moon–Sun distance: the sun's body-fixed position is placed this far along its direction.
const SUN_DISTANCE_M: f64 = 1.496e11;
/// Typical lunar orbital ground speed at 50 km altitude.
const GROUND_SPEED_M_S: f64 = 1_600.0;

/// A planned acquisition: metadata plus the strip geometry in map coordinates.
#[derive(Debug, Clone)]
pub struct Strip {
    pub meta: AcquisitionMetadata,
    pub start_map: DVec2,
    /// Unit along-track axis (map).
    pub axis: DVec2,
    pub length_m: f64,
    pub width_m: f64,
    border_key: u64,
    border_roughness_m: f64,
    /// Ortho raster grid (snapped to the ortho gsd, clipped to the scene).
    pub grid: Grid,
    pub incidence_deg: f64,
}

impl Strip {
    /// Inside the irregular strip outline (map coordinates)?
    pub fn contains(&self, x: f64, y: f64) -> bool {
        let rel = DVec2::new(x, y) - self.start_map;
        let u = rel.dot(self.axis);
        let v = rel.perp_dot(self.axis); // cross-track, positive to the left of the axis
        let half = self.width_m / 2.0;
        // Gradient noise stays within ±1.5 (tested), so pixels this far from every border are inside outright.
        let sure = 1.5 * self.border_roughness_m;
        if u > sure && u < self.length_m - sure && v.abs() < half - sure {
            return true;
        }
        if u < -sure || u > self.length_m + sure || v.abs() > half + sure {
            return false;
        }
        let wobble = |t: f64, lane: u64| {
            self.border_roughness_m
                * gradient_noise(
                    t / 400.0,
                    lane as f64 * 7.3,
                    self.border_key.wrapping_add(lane),
                )
        };
        u > wobble(v, 1)
            && u < self.length_m + wobble(v, 2)
            && v > -half + wobble(u, 3)
            && v < half + wobble(u, 4)
    }
}

/// Plan `cfg.count` strips over the scene `scene` (map grid of the world).
pub fn plan(
    cfg: &AcquisitionConfig,
    scene: &Grid,
    crs: &LunarCrs,
    base_height_m: f64,
    seed: u64,
) -> Vec<Strip> {
    use rand::seq::SliceRandom;
    let mut incidence_bins: Vec<usize> = (0..cfg.count).collect();
    incidence_bins.shuffle(&mut keyed_rng(seed, "incidence-bins", 0));
    (0..cfg.count)
        .map(|k| plan_one(cfg, scene, crs, base_height_m, seed, k, incidence_bins[k]))
        .collect()
}

fn plan_one(
    cfg: &AcquisitionConfig,
    scene: &Grid,
    crs: &LunarCrs,
    base_height_m: f64,
    seed: u64,
    k: usize,
    bin: usize,
) -> Strip {
    let mut rng = keyed_rng(seed, "acquisition", k as u64);
    let scene_w = scene.max_x() - scene.min_x;
    let scene_h = scene.max_y - scene.min_y();
    // Stratified cross-track placement so strips cover the scene, jittered; slight heading off north.
    let cx = scene.min_x
        + cfg.strip_width_m / 2.0
        + (scene_w - cfg.strip_width_m)
            * ((k as f64 + rng.random_range(0.2..0.8)) / cfg.count as f64);
    let cy = scene.min_y() + scene_h / 2.0 + rng.random_range(-0.04..0.04) * scene_h;
    let heading = rng
        .random_range(-cfg.max_heading_deg..=cfg.max_heading_deg)
        .to_radians();
    let ascending = rng.random::<bool>();
    let axis = DVec2::new(heading.sin(), heading.cos()) * if ascending { 1.0 } else { -1.0 };
    let length_m = cfg.strip_length_fraction * scene_h;
    let center = DVec2::new(cx, cy);
    let start_map = center - axis * (length_m / 2.0);
    let stop_map = center + axis * (length_m / 2.0);

    // Sun: incidence stratified over the range (a keyed shuffle of equal bins, jittered within the bin) so every
    // world has both low-sun and high-sun images; azimuth from the east or west (morning/evening) ± 40°.
    let bin_width = (cfg.incidence_max_deg - cfg.incidence_min_deg) / cfg.count as f64;
    let incidence_deg =
        cfg.incidence_min_deg + bin_width * (bin as f64 + rng.random_range(0.0..1.0));
    let from_east = rng.random::<bool>();
    let azimuth_deg: f64 = if from_east { 90.0 } else { 270.0 } + rng.random_range(-40.0..40.0); // clockwise from north
    let frame = LocalFrame::new(crs, cx, cy, base_height_m).expect("scene CRS is valid");
    let (inc, az) = (incidence_deg.to_radians(), azimuth_deg.to_radians());
    let sun_enu = DVec3::new(inc.sin() * az.sin(), inc.sin() * az.cos(), inc.cos());
    let sun_body = frame.origin_body + frame.body_to_enu.transpose() * sun_enu * SUN_DISTANCE_M;

    // Spacecraft: ground track along the strip, shifted cross-track for slewed looks.
    let slewed = rng.random::<f64>() < cfg.slewed_fraction;
    let roll_deg = if slewed {
        rng.random_range(cfg.slew_min_deg..=cfg.slew_max_deg)
            * if rng.random::<bool>() { 1.0 } else { -1.0 }
    } else {
        0.0
    };
    let cross = DVec2::new(-axis.y, axis.x); // left of the axis
    let track_offset = cross * (cfg.altitude_m * roll_deg.to_radians().tan());
    let spacecraft = |p: DVec2| {
        let q = p + track_offset;
        crs.body_fixed(q.x, q.y, base_height_m + cfg.altitude_m)
            .expect("scene CRS is valid")
    };
    let (sc_start, sc_stop) = (spacecraft(start_map), spacecraft(stop_map));

    // Attitude at mid-strip: camera z = boresight toward the strip centre, x = along-track, y completes.
    let sc_mid = dataset::science::geometry::spacecraft_position_at(sc_start, sc_stop, 0.5);
    let target = crs
        .body_fixed(cx, cy, base_height_m)
        .expect("scene CRS is valid");
    let boresight = (target - sc_mid).normalize();
    let along = (sc_stop - sc_start).normalize();
    let x_axis = (along - boresight * along.dot(boresight)).normalize();
    let y_axis = boresight.cross(x_axis);
    let attitude = DQuat::from_mat3(&DMat3::from_cols(x_axis, y_axis, boresight)).normalize();
    let slant = cfg.altitude_m / roll_deg.to_radians().cos();
    let fov_deg = 2.0
        * (cfg.strip_width_m * roll_deg.to_radians().cos() / (2.0 * slant))
            .atan()
            .to_degrees();

    // Times: acquisitions spread over ~3 years from 2010, each strip lasting length / ground speed.
    let start_s = 315_000_000.0 + k as f64 * 86_400.0 * 37.0 + rng.random_range(0.0..86_400.0);
    let stop_s = start_s + length_m / GROUND_SPEED_M_S;
    let ortho_id = format!("M{:07}", 1_000_000 + 1_000 * k + rng.random_range(0..1000));

    // Ortho grid: bounding box of the outline (+ border wobble), snapped to the ortho gsd, clipped to the scene.
    let half = cfg.strip_width_m / 2.0 + cfg.border_roughness_m * 1.5;
    let corners = [
        start_map + cross * half,
        start_map - cross * half,
        stop_map + cross * half,
        stop_map - cross * half,
    ];
    let pad = axis * (cfg.border_roughness_m * 1.5);
    let xs = corners
        .iter()
        .flat_map(|c| [c.x - pad.x.abs(), c.x + pad.x.abs()]);
    let ys = corners
        .iter()
        .flat_map(|c| [c.y - pad.y.abs(), c.y + pad.y.abs()]);
    let (min_x, max_x) = xs.fold((f64::MAX, f64::MIN), |(a, b), v| (a.min(v), b.max(v)));
    let (min_y, max_y) = ys.fold((f64::MAX, f64::MIN), |(a, b), v| (a.min(v), b.max(v)));
    let gsd = cfg.ortho_gsd_m;
    let snap_down = |v: f64, origin: f64| origin + ((v - origin) / gsd).floor() * gsd;
    let snap_up = |v: f64, origin: f64| origin + ((v - origin) / gsd).ceil() * gsd;
    let gx0 = snap_down(min_x.max(scene.min_x), scene.min_x);
    let gx1 = snap_up(max_x.min(scene.max_x()), scene.min_x);
    let gy1 = snap_up(max_y.min(scene.max_y), scene.max_y);
    let gy0 = snap_down(min_y.max(scene.min_y()), scene.max_y);
    let grid = Grid {
        min_x: gx0,
        max_y: gy1,
        gsd_m: gsd,
        width: ((gx1 - gx0) / gsd).round() as usize,
        height: ((gy1 - gy0) / gsd).round() as usize,
    };

    let meta = AcquisitionMetadata {
        ortho_id: ortho_id.clone(),
        image_file: format!("{ortho_id}.tif"),
        camera_id: if k.is_multiple_of(2) {
            "NAC-L".into()
        } else {
            "NAC-R".into()
        },
        start_time_utc: iso_utc_from_j2000_seconds(start_s),
        stop_time_utc: iso_utc_from_j2000_seconds(stop_s),
        sun_position_body_m: sun_body.into(),
        spacecraft_start_body_m: sc_start.into(),
        spacecraft_stop_body_m: sc_stop.into(),
        camera_attitude_wxyz: [attitude.w, attitude.x, attitude.y, attitude.z],
        fov_deg,
        pixel_scale_m: gsd,
        roll_deg,
    };
    Strip {
        meta,
        start_map,
        axis,
        length_m,
        width_m: cfg.strip_width_m,
        border_key: keyed_u64(seed, "strip-border", k as u64),
        border_roughness_m: cfg.border_roughness_m,
        grid,
        incidence_deg,
    }
}

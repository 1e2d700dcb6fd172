//! Each ortho's acquisition geometry in the forms LROC users receive it: an ALE image support data file (ISD) and
//! a row of a cumulative index table with its PDS3 label. They are written from the metadata the world itself
//! wrote, so the importers (`crate::import`) can be checked against it.
//!
//! A real ISD carries SPICE's lunar orientation; the world has no ephemeris, so its ISDs use the IAU lunar
//! rotation model without periodic terms (J2000 → a principal-axis frame) and a fixed small rotation into the
//! body-fixed frame, standing in for SPICE's MOON_PA → MOON_ME offset. Any rotation that the importer undoes
//! exactly would do; a real one keeps the numbers realistic.

use dataset::contract::acquisition::{
    ephemeris_time_from_utc_seconds, j2000_seconds_from_iso_utc, AcquisitionMetadata,
};
use dataset::science::crs::{lonlat_from_body_fixed, LunarCrs, MOON_RADIUS_M};
use dataset::science::geometry::spacecraft_position_at;
use glam::{DMat3, DQuat, DVec2, DVec3};

use super::acquisition::Strip;
use crate::import::index;
use crate::import::isd::{
    mat_to_row_major, quat_to_wxyz, FocalLengthModel, Isd, Radii, Rotations, States, J2000,
    LINE_SCANNER_MODEL,
};

/// LROC NAC focal length, mm.
const NAC_FOCAL_LENGTH_MM: f64 = 699.62;
/// Seconds between ephemeris samples, and how far they reach beyond the strip (ALE pads its tables likewise).
const SAMPLE_STEP_S: f64 = 1.0;
const SAMPLE_PAD_S: f64 = 3.3;

fn arcsec(v: f64) -> f64 {
    (v / 3600.0).to_radians()
}

/// J2000 → the world's principal-axis frame at ephemeris time `et` (IAU 2009 lunar pole and prime meridian,
/// secular terms only).
fn principal_axes_from_j2000(et: f64) -> DMat3 {
    let days = et / 86_400.0;
    let (alpha0, delta0) = (269.9949_f64.to_radians(), 66.5392_f64.to_radians());
    let w = (38.3213 + 13.176_358_15 * days).to_radians();
    // Frame rotations R3(W) R1(90° − δ0) R3(90° + α0), as active rotations of vectors by the negated angles.
    DMat3::from_rotation_z(-w)
        * DMat3::from_rotation_x(-(std::f64::consts::FRAC_PI_2 - delta0))
        * DMat3::from_rotation_z(-(std::f64::consts::FRAC_PI_2 + alpha0))
}

/// Principal axes → body-fixed: a constant rotation of the size of the real MOON_PA → MOON_ME offset.
fn body_from_principal_axes() -> DMat3 {
    DMat3::from_rotation_z(arcsec(-0.30))
        * DMat3::from_rotation_y(arcsec(-78.56))
        * DMat3::from_rotation_x(arcsec(-67.92))
}

/// Spacecraft frame → camera frame: the camera's fixed mounting.
fn camera_from_spacecraft() -> DMat3 {
    DMat3::from_rotation_z(std::f64::consts::FRAC_PI_2) * DMat3::from_rotation_x(arcsec(40.0))
}

/// The ISD of one strip, sampled from its metadata: the world's spacecraft arc, sun and attitude.
pub fn isd(meta: &AcquisitionMetadata, image_lines: usize, image_samples: usize) -> Isd {
    let utc = |text: &str| j2000_seconds_from_iso_utc(text).expect("the world writes valid times");
    let (start, stop) = (
        ephemeris_time_from_utc_seconds(utc(&meta.start_time_utc)),
        ephemeris_time_from_utc_seconds(utc(&meta.stop_time_utc)),
    );
    let center = 0.5 * (start + stop);
    let times: Vec<f64> = (0..)
        .map(|k| start - SAMPLE_PAD_S + k as f64 * SAMPLE_STEP_S)
        .take_while(|&t| t <= stop + SAMPLE_PAD_S + SAMPLE_STEP_S)
        .collect();
    let body_from_j2000 = |t: f64| body_from_principal_axes() * principal_axes_from_j2000(t);
    let (sc_start, sc_stop) = (
        DVec3::from(meta.spacecraft_start_body_m),
        DVec3::from(meta.spacecraft_stop_body_m),
    );
    let spacecraft =
        |t: f64| spacecraft_position_at(sc_start, sc_stop, (t - start) / (stop - start));
    let km = |v: DVec3| (v / 1000.0).to_array();
    let states = |position: &dyn Fn(f64) -> DVec3| States {
        ephemeris_times: times.clone(),
        positions: times
            .iter()
            .map(|&t| km(body_from_j2000(t).transpose() * position(t)))
            .collect(),
        velocities: None,
        reference_frame: J2000,
    };
    let [w, x, y, z] = meta.camera_attitude_wxyz;
    let camera_to_body = DMat3::from_quat(DQuat::from_xyzw(x, y, z, w));
    let spacecraft_from_j2000 = |t: f64| {
        camera_from_spacecraft().transpose() * camera_to_body.transpose() * body_from_j2000(t)
    };
    let rotations = |rotation: &dyn Fn(f64) -> DMat3,
                     constant: DMat3,
                     frames: Vec<i64>,
                     constants: Vec<i64>| Rotations {
        time_dependent_frames: frames,
        ephemeris_times: times.clone(),
        quaternions: times
            .iter()
            .map(|&t| quat_to_wxyz(DQuat::from_mat3(&rotation(t)).normalize()))
            .collect(),
        constant_frames: Some(constants),
        constant_rotation: Some(mat_to_row_major(constant)),
        reference_frame: J2000,
    };
    let detector_mm = 2.0 * NAC_FOCAL_LENGTH_MM * (meta.fov_deg.to_radians() / 2.0).tan();
    let pixels_per_mm = image_samples as f64 / detector_mm;
    let line_duration = (stop - start) / image_lines as f64;
    let left = meta.camera_id.ends_with('L');
    Isd {
        name_model: LINE_SCANNER_MODEL.into(),
        name_platform: "LUNAR RECONNAISSANCE ORBITER".into(),
        name_sensor: meta.camera_id.clone(),
        image_lines: image_lines as f64,
        image_samples: image_samples as f64,
        starting_ephemeris_time: start,
        center_ephemeris_time: center,
        line_scan_rate: vec![[0.5, start - center, line_duration]],
        radii: Radii {
            semimajor: MOON_RADIUS_M / 1000.0,
            semiminor: MOON_RADIUS_M / 1000.0,
            unit: "km".into(),
        },
        // NAIF ids as SPICE names them: MOON_ME 31001, MOON_ME_DE421 31007, MOON_PA_DE421 31006; LRO -85000,
        // NAC-L -85600, NAC-R -85610.
        body_rotation: rotations(
            &principal_axes_from_j2000,
            body_from_principal_axes(),
            vec![31006, J2000],
            vec![31001, 31007, 31006],
        ),
        instrument_pointing: rotations(
            &spacecraft_from_j2000,
            camera_from_spacecraft(),
            vec![-85000, J2000],
            vec![if left { -85600 } else { -85610 }, -85000],
        ),
        instrument_position: states(&spacecraft),
        sun_position: states(&|_| DVec3::from(meta.sun_position_body_m)),
        focal_length_model: FocalLengthModel {
            focal_length: NAC_FOCAL_LENGTH_MM,
        },
        focal2pixel_samples: [0.0, 0.0, pixels_per_mm],
        focal2pixel_lines: [0.0, pixels_per_mm, 0.0],
        detector_sample_summing: 1.0,
        detector_line_summing: 1.0,
    }
}

/// Index columns as the world writes them: (name, width, text?).
fn index_columns() -> Vec<(&'static str, usize, bool)> {
    index::COLUMNS
        .iter()
        .map(|&name| match name {
            "PRODUCT_ID" => (name, 12, true),
            "FRAME_ID" => (name, 5, true),
            "START_TIME" | "STOP_TIME" => (name, 23, false),
            "SOLAR_DISTANCE" => (name, 16, false),
            _ => (name, 12, false),
        })
        .collect()
}

/// The index row of one strip: the centre (seen from mid-strip) and the corners of the strip outline (seen from
/// the first and last lines) where the lines of sight meet the reference sphere, the sub-solar and
/// sub-spacecraft points (mid-strip), longitudes in 0–360° east as LROC writes them.
pub fn index_row(strip: &Strip, crs: &LunarCrs, base_height_m: f64) -> Vec<String> {
    let meta = &strip.meta;
    let cross = DVec2::new(-strip.axis.y, strip.axis.x) * (strip.width_m / 2.0);
    let stop_map = strip.start_map + strip.axis * strip.length_m;
    let centre_map = strip.start_map + strip.axis * (strip.length_m / 2.0);
    let sc_start = DVec3::from(meta.spacecraft_start_body_m);
    let sc_stop = DVec3::from(meta.spacecraft_stop_body_m);
    // As in a real index, a point's coordinates are where the line of sight to it meets the reference sphere.
    let on_sphere = |spacecraft: DVec3, p: DVec2| {
        let target = crs
            .body_fixed(p.x, p.y, base_height_m)
            .expect("scene CRS is valid");
        sphere_intersection(spacecraft, (target - spacecraft).normalize())
    };
    let angle = |v: f64| format!("{v:.6}");
    let lat_lon = |p: DVec3| {
        let (lon, lat, _) = lonlat_from_body_fixed(p);
        [angle(lat), angle(lon.rem_euclid(360.0))]
    };
    let sc_mid = spacecraft_position_at(sc_start, sc_stop, 0.5);
    let sun = DVec3::from(meta.sun_position_body_m);
    let mut row = vec![
        meta.ortho_id.clone(),
        if meta.camera_id.ends_with('L') {
            "LEFT"
        } else {
            "RIGHT"
        }
        .to_string(),
        meta.start_time_utc.trim_end_matches('Z').to_string(),
        meta.stop_time_utc.trim_end_matches('Z').to_string(),
    ];
    // Upper = first line, left = left of the direction of flight.
    for (spacecraft, p) in [
        (sc_mid, centre_map),
        (sc_start, strip.start_map + cross),
        (sc_start, strip.start_map - cross),
        (sc_stop, stop_map + cross),
        (sc_stop, stop_map - cross),
    ] {
        row.extend(lat_lon(on_sphere(spacecraft, p)));
    }
    row.extend(lat_lon(sun));
    row.push(format!("{:.3}", sun.length() / 1000.0));
    row.extend(lat_lon(sc_mid));
    row.push(format!("{:.6}", (sc_mid.length() - MOON_RADIUS_M) / 1000.0));
    row
}

/// Where the ray from `origin` along unit `direction` first meets the reference sphere.
fn sphere_intersection(origin: DVec3, direction: DVec3) -> DVec3 {
    let b = origin.dot(direction);
    let c = origin.length_squared() - MOON_RADIUS_M * MOON_RADIUS_M;
    origin + direction * (-b - (b * b - c).max(0.0).sqrt())
}

/// `CUMINDEX.LBL` and `CUMINDEX.TAB` for these rows.
pub fn index_files(rows: &[Vec<String>]) -> (String, String) {
    index::write_table("CUMINDEX.TAB", &index_columns(), rows)
}

//! USGS ALE image support data (ISD, the JSON `isd_generate` writes from SPICE) for a line-scan camera such as
//! the LROC NAC.
//!
//! What the ISD says and how it is read (ALE's formatter; ISIS frame conventions):
//! - `instrument_position` / `sun_position`: km, J2000 (`reference_frame` 1), relative to the target's centre, at
//!   `ephemeris_times` (TDB s past J2000). Interpolated with Lagrange polynomials over the nearest 8 samples, as the
//!   CSM line-scan model does.
//! - `body_rotation`: quaternions (w, x, y, z) rotating J2000 vectors into the last time-dependent frame, then
//!   `constant_rotation` (3×3, row-major) into the body-fixed frame. `instrument_pointing`: likewise J2000 → the
//!   spacecraft frame, then `constant_rotation` into the sensor frame (+z the boresight). Quaternions are slerped
//!   between the two samples around each time.
//! - Times of image lines from `line_scan_rate` (`[line, seconds after center_ephemeris_time, seconds per line]`,
//!   lines counted from 0.5 at the top of the first line): the strip starts at line 0.5 and stops at
//!   `image_lines + 0.5`.
//! - Cross-track field of view from `focal_length_model.focal_length` (mm), the detector pitch
//!   (1 / |`focal2pixel_samples`| pixels per mm), `image_samples` and `detector_sample_summing`.

use std::path::Path;

use glam::{DMat3, DQuat, DVec3};

use super::{ImportError, ImportedGeometry};
use dataset::contract::acquisition::utc_seconds_from_ephemeris_time;
use dataset::science::crs::MOON_RADIUS_M;

/// The J2000 frame's NAIF id: every vector and rotation of a usable ISD is referred to it.
pub const J2000: i64 = 1;
/// The CSM model name ALE gives line-scan (pushbroom) cameras: the geometry this importer models.
pub const LINE_SCANNER_MODEL: &str = "USGS_ASTRO_LINE_SCANNER_SENSOR_MODEL";
/// Samples used by the position interpolation (the CSM line-scan model's Lagrange order).
const LAGRANGE_POINTS: usize = 8;

#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Isd {
    pub name_model: String,
    pub name_platform: String,
    pub name_sensor: String,
    pub image_lines: f64,
    pub image_samples: f64,
    pub starting_ephemeris_time: f64,
    pub center_ephemeris_time: f64,
    pub line_scan_rate: Vec<[f64; 3]>,
    pub radii: Radii,
    pub body_rotation: Rotations,
    pub instrument_pointing: Rotations,
    pub instrument_position: States,
    pub sun_position: States,
    pub focal_length_model: FocalLengthModel,
    pub focal2pixel_samples: [f64; 3],
    pub focal2pixel_lines: [f64; 3],
    pub detector_sample_summing: f64,
    pub detector_line_summing: f64,
}

#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Radii {
    pub semimajor: f64,
    pub semiminor: f64,
    pub unit: String,
}

#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Rotations {
    pub time_dependent_frames: Vec<i64>,
    pub ephemeris_times: Vec<f64>,
    /// (w, x, y, z), unit norm.
    pub quaternions: Vec<[f64; 4]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub constant_frames: Option<Vec<i64>>,
    /// Row-major 3×3; identity when absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub constant_rotation: Option<[f64; 9]>,
    pub reference_frame: i64,
}

#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct States {
    pub ephemeris_times: Vec<f64>,
    /// km.
    pub positions: Vec<[f64; 3]>,
    /// km/s.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub velocities: Option<Vec<[f64; 3]>>,
    pub reference_frame: i64,
}

#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct FocalLengthModel {
    /// mm.
    pub focal_length: f64,
}

/// Rotation of a (w, x, y, z) quaternion as glam's.
pub fn quat_from_wxyz([w, x, y, z]: [f64; 4]) -> DQuat {
    DQuat::from_xyzw(x, y, z, w)
}

pub fn quat_to_wxyz(q: DQuat) -> [f64; 4] {
    [q.w, q.x, q.y, q.z]
}

/// A row-major 3×3 as a matrix.
pub fn mat_from_row_major(m: &[f64; 9]) -> DMat3 {
    DMat3::from_cols_array(m).transpose()
}

pub fn mat_to_row_major(m: DMat3) -> [f64; 9] {
    m.transpose().to_cols_array()
}

impl Isd {
    pub fn load(path: &Path) -> Result<Self, ImportError> {
        let text = std::fs::read_to_string(path).map_err(|source| ImportError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let isd: Self = serde_json::from_str(&text).map_err(|source| ImportError::IsdSyntax {
            path: path.to_path_buf(),
            source,
        })?;
        isd.validate(path)?;
        Ok(isd)
    }

    /// Everything the geometry relies on, each failure naming its key.
    pub fn validate(&self, path: &Path) -> Result<(), ImportError> {
        let bad = |key: &str, problem: String| Err(ImportError::field(path, key, problem));
        if self.name_model != LINE_SCANNER_MODEL {
            return bad(
                "name_model",
                format!(
                    "'{}' is not a line-scan camera; this importer models pushbroom strips ({LINE_SCANNER_MODEL}, e.g. the LROC NAC)",
                    self.name_model
                ),
            );
        }
        if self.radii.unit != "km" {
            return bad(
                "radii.unit",
                format!("'{}': ALE ISDs give radii in km", self.radii.unit),
            );
        }
        if (self.radii.semimajor * 1000.0 - MOON_RADIUS_M).abs() > 1_000.0 {
            return bad(
                "radii.semimajor",
                format!(
                    "{} km is not the Moon ({} km): the ISD is for another target",
                    self.radii.semimajor,
                    MOON_RADIUS_M / 1000.0
                ),
            );
        }
        if !(self.image_lines >= 1.0 && self.image_samples >= 1.0) {
            return bad(
                "image_lines",
                "image_lines and image_samples must be positive".into(),
            );
        }
        if self.line_scan_rate.is_empty() {
            return bad(
                "line_scan_rate",
                "empty: the time of each image line is unknown".into(),
            );
        }
        if self.line_scan_rate.iter().any(|r| !is_positive(r[2])) {
            return bad("line_scan_rate", "seconds per line must be positive".into());
        }
        if self.line_scan_rate.windows(2).any(|w| w[1][0] <= w[0][0]) {
            return bad("line_scan_rate", "line numbers must increase".into());
        }
        let first_line = self.line_time(0.5);
        if (first_line - self.starting_ephemeris_time).abs() > 1e-3 {
            return bad(
                "starting_ephemeris_time",
                format!(
                    "{} s disagrees with line_scan_rate's time of line 0.5 ({first_line} s)",
                    self.starting_ephemeris_time
                ),
            );
        }
        for (key, rotations) in [
            ("body_rotation", &self.body_rotation),
            ("instrument_pointing", &self.instrument_pointing),
        ] {
            check_reference_frame(path, key, rotations.reference_frame)?;
            check_times(
                path,
                key,
                &rotations.ephemeris_times,
                rotations.quaternions.len(),
            )?;
            for (i, q) in rotations.quaternions.iter().enumerate() {
                let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
                if !is_within(norm - 1.0, 1e-6) {
                    return bad(
                        &format!("{key}.quaternions[{i}]"),
                        format!("norm {norm}, not a unit quaternion (w, x, y, z)"),
                    );
                }
            }
            if let Some(m) = &rotations.constant_rotation {
                let m = mat_from_row_major(m);
                let orthonormal = (m * m.transpose() - DMat3::IDENTITY)
                    .to_cols_array()
                    .iter()
                    .all(|v| v.abs() < 1e-6);
                if !orthonormal || (m.determinant() - 1.0).abs() > 1e-6 {
                    return bad(
                        &format!("{key}.constant_rotation"),
                        "not a rotation matrix (orthonormal, determinant 1, row-major)".into(),
                    );
                }
            }
        }
        for (key, states, range_km) in [
            (
                "instrument_position",
                &self.instrument_position,
                (MOON_RADIUS_M / 1000.0 + 1.0)..(MOON_RADIUS_M / 1000.0 + 1000.0),
            ),
            ("sun_position", &self.sun_position, 1.0e7..1.0e9),
        ] {
            check_reference_frame(path, key, states.reference_frame)?;
            check_times(path, key, &states.ephemeris_times, states.positions.len())?;
            if let Some(p) = states
                .positions
                .iter()
                .find(|p| !range_km.contains(&DVec3::from(**p).length()))
            {
                let r = DVec3::from(*p).length();
                return bad(
                    &format!("{key}.positions"),
                    format!("{r:.6e} from the Moon's centre, expected {:.0e}–{:.0e}: ALE ISDs give km (are these metres?)", range_km.start, range_km.end),
                );
            }
        }
        let (start, stop) = self.strip_times();
        for (key, times) in [
            (
                "body_rotation.ephemeris_times",
                &self.body_rotation.ephemeris_times,
            ),
            (
                "instrument_pointing.ephemeris_times",
                &self.instrument_pointing.ephemeris_times,
            ),
            (
                "instrument_position.ephemeris_times",
                &self.instrument_position.ephemeris_times,
            ),
            (
                "sun_position.ephemeris_times",
                &self.sun_position.ephemeris_times,
            ),
        ] {
            let (first, last) = (times[0], times[times.len() - 1]);
            // A single sample (a body or sun that barely moves) covers the strip as a constant.
            if times.len() > 1 && (start < first - 1e-6 || stop > last + 1e-6) {
                return bad(
                    key,
                    format!("covers {first}–{last} s but the strip spans {start}–{stop} s"),
                );
            }
        }
        if !is_positive(self.focal_length_model.focal_length) {
            return bad(
                "focal_length_model.focal_length",
                "must be positive (mm)".into(),
            );
        }
        if self.pixels_per_mm() <= 0.0 {
            return bad(
                "focal2pixel_samples",
                "no sample scale (pixels per mm)".into(),
            );
        }
        if self.detector_sample_summing.is_nan() || self.detector_sample_summing < 1.0 {
            return bad("detector_sample_summing", "must be ≥ 1".into());
        }
        Ok(())
    }

    /// Ephemeris time of fractional image line `line` (0.5 = top of the first line).
    pub fn line_time(&self, line: f64) -> f64 {
        let rate = self
            .line_scan_rate
            .iter()
            .rev()
            .find(|r| r[0] <= line)
            .unwrap_or(&self.line_scan_rate[0]);
        self.center_ephemeris_time + rate[1] + (line - rate[0]) * rate[2]
    }

    /// Ephemeris times of the first line's top and the last line's bottom.
    pub fn strip_times(&self) -> (f64, f64) {
        (self.line_time(0.5), self.line_time(self.image_lines + 0.5))
    }

    fn pixels_per_mm(&self) -> f64 {
        self.focal2pixel_samples[1].hypot(self.focal2pixel_samples[2])
    }

    /// J2000 → Moon body-fixed at ephemeris time `et`.
    pub fn body_from_j2000(&self, et: f64) -> DMat3 {
        rotation_at(&self.body_rotation, et)
    }

    /// The project's geometry: positions at the first and last line, the sun and the attitude at mid-strip.
    pub fn geometry(&self, product_id: &str) -> ImportedGeometry {
        let (start, stop) = self.strip_times();
        let mid = 0.5 * (start + stop);
        let body_position = |states: &States, et: f64| {
            self.body_from_j2000(et)
                * lagrange(&states.ephemeris_times, &states.positions, et)
                * 1000.0
        };
        let sensor_from_j2000 = rotation_at(&self.instrument_pointing, mid);
        let camera_to_body = self.body_from_j2000(mid) * sensor_from_j2000.transpose();
        let detector_mm = self.image_samples * self.detector_sample_summing / self.pixels_per_mm();
        ImportedGeometry {
            product_id: product_id.to_string(),
            camera_id: self.name_sensor.clone(),
            start_utc_s: utc_seconds_from_ephemeris_time(start),
            stop_utc_s: utc_seconds_from_ephemeris_time(stop),
            sun_body_m: body_position(&self.sun_position, mid),
            spacecraft_start_body_m: body_position(&self.instrument_position, start),
            spacecraft_stop_body_m: body_position(&self.instrument_position, stop),
            camera_to_body: DQuat::from_mat3(&camera_to_body).normalize(),
            fov_deg: 2.0
                * (detector_mm / (2.0 * self.focal_length_model.focal_length))
                    .atan()
                    .to_degrees(),
        }
    }
}

/// `x > 0`, false for NaN: every check here must fail on NaN.
fn is_positive(x: f64) -> bool {
    x > 0.0
}

/// `|x| ≤ tolerance`, false for NaN.
fn is_within(x: f64, tolerance: f64) -> bool {
    x.abs() <= tolerance
}

fn check_reference_frame(path: &Path, key: &str, frame: i64) -> Result<(), ImportError> {
    if frame != J2000 {
        return Err(ImportError::field(
            path,
            &format!("{key}.reference_frame"),
            format!("frame {frame}, expected J2000 ({J2000}): regenerate the ISD with ALE's default frames"),
        ));
    }
    Ok(())
}

fn check_times(path: &Path, key: &str, times: &[f64], values: usize) -> Result<(), ImportError> {
    let key = format!("{key}.ephemeris_times");
    if times.is_empty() {
        return Err(ImportError::field(path, &key, "empty"));
    }
    if times.len() != values {
        return Err(ImportError::field(
            path,
            &key,
            format!("{} times for {values} samples", times.len()),
        ));
    }
    if let Some(i) = times.windows(2).position(|w| !is_positive(w[1] - w[0])) {
        return Err(ImportError::field(
            path,
            &key,
            format!(
                "not strictly increasing ({} then {} at index {})",
                times[i],
                times[i + 1],
                i + 1
            ),
        ));
    }
    Ok(())
}

/// The rotation J2000 → final frame of `rotations` at `et`: slerp between the samples around `et` (constant
/// beyond a single sample), then the constant rotation.
fn rotation_at(rotations: &Rotations, et: f64) -> DMat3 {
    let times = &rotations.ephemeris_times;
    let q = if times.len() == 1 {
        quat_from_wxyz(rotations.quaternions[0])
    } else {
        let i = times
            .partition_point(|&t| t <= et)
            .clamp(1, times.len() - 1);
        let (q0, q1) = (
            quat_from_wxyz(rotations.quaternions[i - 1]),
            quat_from_wxyz(rotations.quaternions[i]),
        );
        // q and −q are the same rotation: take the short way.
        let q1 = if q0.dot(q1) < 0.0 { -q1 } else { q1 };
        q0.slerp(q1, (et - times[i - 1]) / (times[i] - times[i - 1]))
    };
    let constant = rotations
        .constant_rotation
        .as_ref()
        .map_or(DMat3::IDENTITY, mat_from_row_major);
    constant * DMat3::from_quat(q.normalize())
}

/// Lagrange interpolation of `values` at `t` over the (up to) [`LAGRANGE_POINTS`] samples nearest to it.
fn lagrange(times: &[f64], values: &[[f64; 3]], t: f64) -> DVec3 {
    let n = times.len().min(LAGRANGE_POINTS);
    let centre = times.partition_point(|&x| x <= t);
    let first = centre.saturating_sub(n / 2).min(times.len() - n);
    let window = first..first + n;
    window
        .clone()
        .map(|i| {
            let weight: f64 = window
                .clone()
                .filter(|&j| j != i)
                .map(|j| (t - times[j]) / (times[i] - times[j]))
                .product();
            DVec3::from(values[i]) * weight
        })
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lagrange_is_exact_on_cubics_and_at_nodes() {
        let times: Vec<f64> = (0..12).map(|i| 10.0 + 0.7 * i as f64).collect();
        let f = |t: f64| [t * t * t - 2.0 * t, 3.0 * t * t, 1.0];
        let values: Vec<[f64; 3]> = times.iter().map(|&t| f(t)).collect();
        for t in [10.0, 10.35, 13.1, 17.7, 17.0] {
            let got = lagrange(&times, &values, t);
            let want = DVec3::from(f(t));
            assert!(
                (got - want).length() < 1e-9 * want.length(),
                "{t}: {got} vs {want}"
            );
        }
    }

    #[test]
    fn slerp_follows_a_uniform_spin() {
        // A spin at 1 rad/s about z sampled every second: slerp is exact for a constant axis and rate.
        let times: Vec<f64> = (0..5).map(f64::from).collect();
        let spin = |t: f64| DQuat::from_rotation_z(t);
        let rotations = Rotations {
            time_dependent_frames: vec![31006, J2000],
            ephemeris_times: times.clone(),
            quaternions: times.iter().map(|&t| quat_to_wxyz(spin(t))).collect(),
            constant_frames: None,
            constant_rotation: Some(mat_to_row_major(DMat3::from_rotation_x(0.3))),
            reference_frame: J2000,
        };
        let t = 2.37;
        let want = DMat3::from_rotation_x(0.3) * DMat3::from_quat(spin(t));
        let got = rotation_at(&rotations, t);
        let err = (got - want)
            .to_cols_array()
            .iter()
            .map(|v| v.abs())
            .fold(0.0, f64::max);
        assert!(err < 1e-12, "{err}");
    }
}

//! Acquisition metadata: the per-orthoimage JSON a real user has next to each image (NAC-like pushbroom strips).
//!
//! Positions are in the Moon body-fixed frame (sphere R = 1737400 m, metres). Parsing errors name the missing or
//! malformed field (serde), and [`AcquisitionMetadata::validate`] catches physically impossible values.

use std::path::{Path, PathBuf};

use glam::{DQuat, DVec3};

use crate::crs::MOON_RADIUS_M;
use crate::geometry::{imaging_fraction, spacecraft_position_at};

#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AcquisitionMetadata {
    pub ortho_id: String,
    /// Orthoimage file name, relative to this JSON file.
    pub image_file: String,
    pub camera_id: String,
    /// ISO 8601 UTC.
    pub start_time_utc: String,
    pub stop_time_utc: String,
    /// Sun position, body-fixed metres.
    pub sun_position_body_m: [f64; 3],
    /// Spacecraft position at the first and last image line, body-fixed metres (circular-orbit arc between).
    pub spacecraft_start_body_m: [f64; 3],
    pub spacecraft_stop_body_m: [f64; 3],
    /// Camera attitude at mid-strip as a unit quaternion (w, x, y, z): camera frame → body-fixed.
    pub camera_attitude_wxyz: [f64; 4],
    /// Cross-track field of view, degrees.
    pub fov_deg: f64,
    /// Native ground sample distance of the orthoimage, metres.
    pub pixel_scale_m: f64,
    /// Off-nadir roll at acquisition (0 for nadir), degrees.
    pub roll_deg: f64,
}

#[derive(Debug, thiserror::Error)]
pub enum MetadataError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: invalid acquisition metadata ({source}); every field of dataset::acquisition::AcquisitionMetadata is required")]
    Parse {
        path: PathBuf,
        source: serde_json::Error,
    },
    #[error("{path}: {problem}")]
    Invalid { path: PathBuf, problem: String },
}

impl AcquisitionMetadata {
    pub fn load(path: &Path) -> Result<Self, MetadataError> {
        let text = std::fs::read_to_string(path).map_err(|source| MetadataError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let meta: Self = serde_json::from_str(&text).map_err(|source| MetadataError::Parse {
            path: path.to_path_buf(),
            source,
        })?;
        meta.validate().map_err(|problem| MetadataError::Invalid {
            path: path.to_path_buf(),
            problem,
        })?;
        Ok(meta)
    }

    pub fn validate(&self) -> Result<(), String> {
        let all = self
            .sun_position_body_m
            .iter()
            .chain(&self.spacecraft_start_body_m)
            .chain(&self.spacecraft_stop_body_m);
        if all.clone().any(|v| !v.is_finite()) {
            return Err("positions must be finite numbers (metres, body-fixed)".into());
        }
        for (name, p) in [
            ("spacecraft_start_body_m", self.spacecraft_start_body_m),
            ("spacecraft_stop_body_m", self.spacecraft_stop_body_m),
        ] {
            let alt = DVec3::from(p).length() - MOON_RADIUS_M;
            if !(1_000.0..1_000_000.0).contains(&alt) {
                return Err(format!("{name} is {alt:.0} m above the sphere; expected an orbit (1-1000 km): are the units metres?"));
            }
        }
        if DVec3::from(self.sun_position_body_m).length() < 1e10 {
            return Err("sun_position_body_m is closer than 1e10 m: give the Sun's body-fixed position in metres".into());
        }
        if !(self.fov_deg > 0.0 && self.fov_deg < 90.0 && self.pixel_scale_m > 0.0) {
            return Err("fov_deg must be in (0, 90) and pixel_scale_m > 0".into());
        }
        Ok(())
    }

    pub fn sun_body(&self) -> DVec3 {
        DVec3::from(self.sun_position_body_m)
    }

    /// Spacecraft position when the pushbroom imaged `ground_body` (see [`imaging_fraction`]).
    pub fn spacecraft_for_ground(&self, ground_body: DVec3) -> DVec3 {
        let (start, stop) = (
            DVec3::from(self.spacecraft_start_body_m),
            DVec3::from(self.spacecraft_stop_body_m),
        );
        spacecraft_position_at(start, stop, imaging_fraction(ground_body, start, stop))
    }

    pub fn camera_attitude(&self) -> DQuat {
        let [w, x, y, z] = self.camera_attitude_wxyz;
        DQuat::from_xyzw(x, y, z, w)
    }
}

/// ISO 8601 UTC timestamp for `seconds` after 2000-01-01T00:00:00Z (no wall clock involved).
pub fn iso_utc_from_j2000_seconds(seconds: f64) -> String {
    let whole = seconds.floor() as i64;
    let millis = ((seconds - whole as f64) * 1000.0).round() as i64;
    let (days, secs_of_day) = (whole.div_euclid(86_400), whole.rem_euclid(86_400));
    // Civil-from-days (H. Hinnant), days since 1970-01-01; J2000 is day 10957.
    let z = days + 10_957 + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + (month <= 2) as i64;
    format!(
        "{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}.{millis:03}Z",
        secs_of_day / 3600,
        secs_of_day % 3600 / 60,
        secs_of_day % 60
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn iso_dates_are_correct() {
        assert_eq!(iso_utc_from_j2000_seconds(0.0), "2000-01-01T00:00:00.000Z");
        assert_eq!(
            iso_utc_from_j2000_seconds(86_400.0 * 60.0 + 3661.5),
            "2000-03-01T01:01:01.500Z"
        );
        // 2011-05-01 is 4138 days after J2000.
        assert_eq!(
            iso_utc_from_j2000_seconds(4138.0 * 86_400.0),
            "2011-05-01T00:00:00.000Z"
        );
    }

    #[test]
    fn missing_field_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("m.json");
        std::fs::write(&path, r#"{"ortho_id": "a"}"#).unwrap();
        let err = AcquisitionMetadata::load(&path).unwrap_err().to_string();
        assert!(
            err.contains("m.json") && err.contains("missing field"),
            "{err}"
        );
    }
}

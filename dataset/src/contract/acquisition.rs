//! Acquisition metadata: the per-orthoimage JSON a real user has next to each image (NAC-like pushbroom strips).
//!
//! Positions are in the Moon body-fixed frame (sphere R = 1737400 m, metres). Parsing errors name the missing or
//! malformed field (serde), and [`AcquisitionMetadata::validate`] catches physically impossible values.

use std::path::{Path, PathBuf};

use glam::{DQuat, DVec3};
use hifitime::{Epoch, Unit};

use crate::science::crs::MOON_RADIUS_M;
use crate::science::geometry::{imaging_fraction, spacecraft_position_at};

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
    #[error("{path}: invalid acquisition metadata ({source}); every field of dataset::contract::acquisition::AcquisitionMetadata is required")]
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

    /// Signed off-nadir angle of the boresight (camera +z) at mid-strip, degrees, from the positions and attitude:
    /// positive when the camera looks to the right of the ground track (the spacecraft flies to the left of the
    /// strip it images). What `roll_deg` holds for imported metadata.
    pub fn off_nadir_roll_deg(&self) -> f64 {
        let (start, stop) = (
            DVec3::from(self.spacecraft_start_body_m),
            DVec3::from(self.spacecraft_stop_body_m),
        );
        let up = spacecraft_position_at(start, stop, 0.5).normalize();
        let left = up.cross((stop - start).normalize()).normalize();
        let boresight = self.camera_attitude() * DVec3::Z;
        (-boresight.dot(left))
            .atan2(-boresight.dot(up))
            .to_degrees()
    }
}

/// 2000-01-01T00:00:00Z, the origin of the UTC second counts below: seconds on the UTC scale, which skips leap
/// seconds (as the timestamps of PDS labels and LROC index tables do).
fn utc_origin() -> Epoch {
    Epoch::from_gregorian_utc_at_midnight(2000, 1, 1)
}

fn epoch_from_utc_seconds(seconds: f64) -> Epoch {
    Epoch::from_utc_duration(utc_origin().to_utc_duration() + seconds * Unit::Second)
}

fn utc_seconds_of(epoch: Epoch) -> f64 {
    (epoch.to_utc_duration() - utc_origin().to_utc_duration()).to_seconds()
}

/// ISO 8601 UTC timestamp, to the millisecond, for `seconds` after 2000-01-01T00:00:00Z (no wall clock involved).
pub fn iso_utc_from_j2000_seconds(seconds: f64) -> String {
    let (year, month, day, hour, minute, second, nanos) = epoch_from_utc_seconds(seconds)
        .round(Unit::Millisecond * 1)
        .to_gregorian_utc();
    format!(
        "{year:04}-{month:02}-{day:02}T{hour:02}:{minute:02}:{second:02}.{:03}Z",
        nanos / 1_000_000
    )
}

/// Seconds after 2000-01-01T00:00:00Z for an ISO 8601 UTC timestamp (`YYYY-MM-DDThh:mm:ss[.fff][Z]`, the form
/// PDS labels and LROC index tables use, optionally quoted); the inverse of [`iso_utc_from_j2000_seconds`].
/// `None` when malformed, or when it is a date without a time of day (an acquisition needs the instant).
pub fn j2000_seconds_from_iso_utc(text: &str) -> Option<f64> {
    let text = text.trim().trim_matches('"');
    if !text.contains('T') {
        return None;
    }
    Epoch::from_gregorian_str(text).ok().map(utc_seconds_of)
}

/// SPICE ephemeris time (TDB seconds past the J2000 epoch, as in ALE ISDs) of a UTC instant given as seconds after
/// 2000-01-01T00:00:00Z (the timestamps of [`iso_utc_from_j2000_seconds`]), through the IERS leap-second table
/// and SPICE's TDB model.
pub fn ephemeris_time_from_utc_seconds(utc_seconds: f64) -> f64 {
    epoch_from_utc_seconds(utc_seconds).to_et_seconds()
}

/// The inverse of [`ephemeris_time_from_utc_seconds`] (exact away from a leap second itself).
pub fn utc_seconds_from_ephemeris_time(et: f64) -> f64 {
    utc_seconds_of(Epoch::from_et_seconds(et))
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

    #[test]
    fn iso_parse_inverts_format() {
        for s in [
            0.0,
            3661.5,
            4138.0 * 86_400.0 + 12.345,
            -86_400.0 * 400.0,
            9.87e8,
        ] {
            let text = iso_utc_from_j2000_seconds(s);
            let back = j2000_seconds_from_iso_utc(&text).unwrap();
            assert!((back - s).abs() < 1e-3, "{text}: {back} vs {s}");
        }
        // PDS labels omit the Z and may carry more digits.
        assert_eq!(
            j2000_seconds_from_iso_utc("2000-01-02T00:00:01.25"),
            Some(86_401.25)
        );
        for bad in ["2011-13-01T00:00:00", "2011-05-01", "20110501T000000", ""] {
            assert_eq!(j2000_seconds_from_iso_utc(bad), None, "{bad}");
        }
    }

    #[test]
    fn ephemeris_time_matches_spice() {
        // The J2000 epoch is 12:00:00 TT = 11:58:55.816 UTC; TDB differs from TT by at most 1.7 ms.
        let epoch = j2000_seconds_from_iso_utc("2000-01-01T11:58:55.816").unwrap();
        let et = ephemeris_time_from_utc_seconds(epoch);
        assert!(et.abs() < 1.7e-3, "{et}");
        // SPICE str2et('2010-01-01T00:00:00') = 315,576,066.1839 (TDB, given to 0.1 ms).
        let utc_2010 = j2000_seconds_from_iso_utc("2010-01-01T00:00:00").unwrap();
        let et = ephemeris_time_from_utc_seconds(utc_2010);
        assert!((et - 315_576_066.183_9).abs() < 1e-4, "{et}");
        for utc in [utc_2010, 5.0e8, 6.0e8, 1.0e6] {
            let back = utc_seconds_from_ephemeris_time(ephemeris_time_from_utc_seconds(utc));
            assert!((back - utc).abs() < 1e-6, "{utc}: {back}");
        }
    }

    #[test]
    fn a_leap_second_lasts_one_utc_second_and_two_of_ephemeris_time() {
        // 2016-12-31T23:59:60 was inserted: one second of UTC count, two of elapsed time across it.
        let before = j2000_seconds_from_iso_utc("2016-12-31T23:59:59").unwrap();
        let after = j2000_seconds_from_iso_utc("2017-01-01T00:00:00").unwrap();
        assert_eq!(after - before, 1.0);
        let elapsed =
            ephemeris_time_from_utc_seconds(after) - ephemeris_time_from_utc_seconds(before);
        assert!((elapsed - 2.0).abs() < 1e-6, "{elapsed}");
        // A day without one: 86,400 s of both (TDB's rate differs from TT's by under 2e-8).
        let (a, b) = (before - 86_400.0 * 100.0, before - 86_400.0 * 99.0);
        let elapsed = ephemeris_time_from_utc_seconds(b) - ephemeris_time_from_utc_seconds(a);
        assert!((elapsed - 86_400.0).abs() < 2e-3, "{elapsed}");
    }
}

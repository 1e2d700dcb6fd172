//! Acquisition metadata: the per-orthoimage JSON a real user has next to each image (NAC-like pushbroom strips).
//!
//! Positions are in the Moon body-fixed frame (sphere R = 1737400 m, metres). Parsing errors name the missing or
//! malformed field (serde), and [`AcquisitionMetadata::validate`] catches physically impossible values.

use std::path::{Path, PathBuf};

use glam::{DQuat, DVec3};

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

/// Seconds after 2000-01-01T00:00:00Z for an ISO 8601 UTC timestamp (`YYYY-MM-DDThh:mm:ss[.fff][Z]`, the form
/// PDS labels and LROC index tables use); the inverse of [`iso_utc_from_j2000_seconds`]. `None` when malformed.
pub fn j2000_seconds_from_iso_utc(text: &str) -> Option<f64> {
    let text = text.trim().trim_matches('"').trim_end_matches('Z');
    let (date, time) = text.split_once('T')?;
    let mut d = date.splitn(3, '-').map(|p| p.parse::<i64>().ok());
    let (year, month, day) = (d.next()??, d.next()??, d.next()??);
    let mut t = time.splitn(3, ':');
    let (hour, minute) = (
        t.next()?.parse::<i64>().ok()?,
        t.next()?.parse::<i64>().ok()?,
    );
    let second = t.next()?.parse::<f64>().ok()?;
    let valid = (1..=12).contains(&month)
        && (1..=31).contains(&day)
        && (0..24).contains(&hour)
        && (0..60).contains(&minute)
        && (0.0..61.0).contains(&second);
    if !valid {
        return None;
    }
    // Days-from-civil (H. Hinnant), then shift the epoch from 1970-01-01 to 2000-01-01 (day 10957).
    let y = year - (month <= 2) as i64;
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let mp = (month + 9) % 12;
    let doy = (153 * mp + 2) / 5 + day - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    let days = era * 146_097 + doe - 719_468 - 10_957;
    Some((days * 86_400 + hour * 3600 + minute * 60) as f64 + second)
}

/// TAI − UTC (leap seconds) in effect at `utc_seconds` after 2000-01-01T00:00:00Z, from the IERS bulletins
/// (naif0012.tls). LRO data start in 2009; no leap second has been announced after 2017-01-01.
fn tai_minus_utc_s(utc_seconds: f64) -> f64 {
    // (first UTC second of the new offset, after 2000-01-01T00:00:00Z; TAI − UTC from then on).
    const STEPS: [(f64, f64); 5] = [
        (189_388_800.0, 33.0), // 2006-01-01
        (284_083_200.0, 34.0), // 2009-01-01
        (394_329_600.0, 35.0), // 2012-07-01
        (488_937_600.0, 36.0), // 2015-07-01
        (536_457_600.0, 37.0), // 2017-01-01
    ];
    STEPS
        .iter()
        .rev()
        .find(|(from, _)| utc_seconds >= *from)
        .map_or(32.0, |&(_, offset)| offset)
}

/// 2000-01-01T12:00:00 TT is 11:58:55.816 UTC: 43,135.816 s after 2000-01-01T00:00:00Z (when TAI − UTC was 32 s).
const J2000_EPOCH_UTC_S: f64 = 43_200.0 - 32.184 - 32.0;

/// SPICE ephemeris time (TDB seconds past the J2000 epoch, as in ALE ISDs) of a UTC instant given as seconds after
/// 2000-01-01T00:00:00Z without leap seconds (the timestamps of [`iso_utc_from_j2000_seconds`]). TDB is taken as
/// TT: they differ by at most 1.7 ms, which moves an orbiter at 1.6 km/s by under 3 m along its track.
pub fn ephemeris_time_from_utc_seconds(utc_seconds: f64) -> f64 {
    utc_seconds - J2000_EPOCH_UTC_S + (tai_minus_utc_s(utc_seconds) - 32.0)
}

/// The inverse of [`ephemeris_time_from_utc_seconds`] (exact away from the leap second itself).
pub fn utc_seconds_from_ephemeris_time(et: f64) -> f64 {
    let guess = et + J2000_EPOCH_UTC_S;
    et + J2000_EPOCH_UTC_S - (tai_minus_utc_s(guess - (tai_minus_utc_s(guess) - 32.0)) - 32.0)
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
        // The J2000 epoch is 11:58:55.816 UTC; SPICE str2et('2010-01-01T00:00:00') = 315,576,066.1839 (TDB; TT
        // differs by ≤ 1.7 ms, the stated approximation).
        let epoch = j2000_seconds_from_iso_utc("2000-01-01T11:58:55.816").unwrap();
        assert!(ephemeris_time_from_utc_seconds(epoch).abs() < 1e-9);
        let utc_2010 = j2000_seconds_from_iso_utc("2010-01-01T00:00:00").unwrap();
        let et = ephemeris_time_from_utc_seconds(utc_2010);
        assert!((et - 315_576_066.183_9).abs() < 2e-3, "{et}");
        for utc in [utc_2010, 5.0e8, 6.0e8, 1.0e6] {
            let back = utc_seconds_from_ephemeris_time(ephemeris_time_from_utc_seconds(utc));
            assert!((back - utc).abs() < 1e-6, "{utc}: {back}");
        }
    }
}

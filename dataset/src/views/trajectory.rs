//! Camera trajectories for `g2r-train render`: CSV files with a header naming one of two row formats.
//!
//! - `x,y,z,q0,qx,qy,qz`: body-fixed position in metres and the unit quaternion (scalar first) that rotates
//!   camera-frame vectors into the body-fixed frame. Camera frame: +z along the boresight, +x to the image's right,
//!   +y toward the image's bottom (the computer-vision convention).
//! - `lon,lat,alt,yaw,pitch,roll`: planetocentric degrees, metres above the 1,737,400 m sphere, and degrees.
//!   With all three angles 0 the camera looks straight down with north at the image top; `yaw` turns the view
//!   clockwise seen from above (east at the top for 90°), `pitch` tilts the boresight off nadir toward the image
//!   top, `roll` turns the image about the boresight.
//!
//! Blank lines and lines starting with `#` are ignored. Every error names the file, the line and the fix.

use std::path::Path;

use crate::science::crs::{body_fixed_from_lonlat, enu_axes};
use anyhow::{bail, Context, Result};
use glam::{DMat3, DQuat, DVec3};

/// One camera pose: position and camera→body-fixed rotation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    pub position_body_m: DVec3,
    pub camera_to_body: DQuat,
}

const XYZ_QUAT: [&str; 7] = ["x", "y", "z", "q0", "qx", "qy", "qz"];
const LONLAT_YPR: [&str; 6] = ["lon", "lat", "alt", "yaw", "pitch", "roll"];

/// The pose of a `lon,lat,alt,yaw,pitch,roll` row (see the module docs for the angle conventions).
pub fn pose_from_lonlat(lon: f64, lat: f64, alt: f64, yaw: f64, pitch: f64, roll: f64) -> Pose {
    let (east, north, up) = enu_axes(lon, lat);
    // Nadir camera in ENU: boresight down, image right = east, image bottom = south.
    let nadir = DMat3::from_cols(east, -north, -up);
    // Yaw about the local vertical (clockwise from above = negative about up), then pitch about the camera's x
    // axis (boresight toward the image top), then roll about the boresight.
    let yaw_rot = DQuat::from_axis_angle(up, -yaw.to_radians());
    let camera = DQuat::from_mat3(&nadir);
    let pitched = camera * DQuat::from_rotation_x(pitch.to_radians());
    let rolled = pitched * DQuat::from_rotation_z(roll.to_radians());
    Pose {
        position_body_m: body_fixed_from_lonlat(lon, lat, alt),
        camera_to_body: (yaw_rot * rolled).normalize(),
    }
}

/// Parse a trajectory file.
pub fn read_trajectory(path: &Path) -> Result<Vec<Pose>> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("{}: cannot read the trajectory file", path.display()))?;
    parse_trajectory(&text).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))
}

/// Parse trajectory text (see the module docs).
pub fn parse_trajectory(text: &str) -> Result<Vec<Pose>> {
    // Comment lines (`#`) and blank lines are skipped; fields are trimmed; rows of the wrong length are
    // reported below with their line number rather than by the reader.
    let mut reader = csv::ReaderBuilder::new()
        .comment(Some(b'#'))
        .trim(csv::Trim::All)
        .flexible(true)
        .from_reader(text.as_bytes());
    let header = reader.headers()?.clone();
    if header.iter().all(str::is_empty) {
        bail!("empty trajectory: write a header `x,y,z,q0,qx,qy,qz` or `lon,lat,alt,yaw,pitch,roll` and one row per view");
    }
    // The reader's positions do not count comment lines: number the lines it reads as records here (one record
    // per non-empty line that is not a comment, as the reader splits them).
    let record_lines: Vec<usize> = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
        .map(|(i, _)| i + 1)
        .collect();
    let line_of = |record: usize| record_lines.get(record).copied().unwrap_or(0);
    let header_line = line_of(0);
    let columns: Vec<String> = header.iter().map(str::to_lowercase).collect();
    let header = header.iter().collect::<Vec<_>>().join(",");
    let format = if columns == XYZ_QUAT {
        0
    } else if columns == LONLAT_YPR {
        1
    } else {
        bail!(
            "line {header_line}: header `{header}` is neither `x,y,z,q0,qx,qy,qz` (body-fixed m + quaternion) nor \
             `lon,lat,alt,yaw,pitch,roll` (degrees, metres, degrees)"
        );
    };
    let mut poses = Vec::new();
    for (index, record) in reader.records().enumerate() {
        let record = record?;
        if record.iter().all(str::is_empty) {
            continue;
        }
        let line = line_of(index + 1);
        let row = record.iter().collect::<Vec<_>>().join(",");
        let values: Vec<f64> = record
            .iter()
            .map(str::parse::<f64>)
            .collect::<Result<_, _>>()
            .map_err(|_| {
                anyhow::anyhow!("line {line}: `{row}` has a value that is not a number")
            })?;
        if values.len() != columns.len() || values.iter().any(|v| !v.is_finite()) {
            bail!(
                "line {line}: expected {} finite numbers ({}), got `{row}`",
                columns.len(),
                columns.join(",")
            );
        }
        let pose = if format == 0 {
            let q = DQuat::from_xyzw(values[4], values[5], values[6], values[3]);
            if (q.length() - 1.0).abs() > 1e-3 {
                bail!(
                    "line {line}: quaternion (q0,qx,qy,qz) has norm {:.4}, expected 1: normalise it",
                    q.length()
                );
            }
            Pose {
                position_body_m: DVec3::new(values[0], values[1], values[2]),
                camera_to_body: q.normalize(),
            }
        } else {
            let (lon, lat) = (values[0], values[1]);
            if !(-90.0..=90.0).contains(&lat) {
                bail!("line {line}: latitude {lat} outside [-90, 90] degrees");
            }
            if values[2] <= 0.0 {
                bail!(
                    "line {line}: altitude {} m must be above the surface sphere",
                    values[2]
                );
            }
            pose_from_lonlat(lon, lat, values[2], values[3], values[4], values[5])
        };
        poses.push(pose);
    }
    if poses.is_empty() {
        bail!("the header has no rows under it: add one row per view");
    }
    Ok(poses)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: DVec3, b: DVec3) -> bool {
        (a - b).length() < 1e-9
    }

    #[test]
    fn nadir_pose_looks_down_with_north_up_and_yaw_pitch_roll_turn_as_documented() {
        let (east, north, up) = enu_axes(-11.36, -43.31);
        let p = pose_from_lonlat(-11.36, -43.31, 50_000.0, 0.0, 0.0, 0.0);
        let q = p.camera_to_body;
        assert!(close(q * DVec3::Z, -up), "boresight down");
        assert!(close(q * DVec3::X, east), "image right = east");
        assert!(close(q * -DVec3::Y, north), "image top = north");
        assert!(
            (p.position_body_m.length() - (crate::science::crs::MOON_RADIUS_M + 50_000.0)).abs()
                < 1e-6
        );
        // Yaw 90°: east at the image top.
        let q = pose_from_lonlat(-11.36, -43.31, 50_000.0, 90.0, 0.0, 0.0).camera_to_body;
        assert!(close(q * -DVec3::Y, east));
        // Pitch 30°: boresight tilted from nadir toward the image top (north), 30° off the vertical.
        let q = pose_from_lonlat(-11.36, -43.31, 50_000.0, 0.0, 30.0, 0.0).camera_to_body;
        let b = q * DVec3::Z;
        assert!((b.dot(-up) - 30f64.to_radians().cos()).abs() < 1e-12);
        assert!(b.dot(north) > 0.49 && b.dot(east).abs() < 1e-12);
        // Roll 90° about the boresight: image right = south (x turned toward +y).
        let q = pose_from_lonlat(-11.36, -43.31, 50_000.0, 0.0, 0.0, 90.0).camera_to_body;
        assert!(close(q * DVec3::Z, -up));
        assert!(close(q * DVec3::X, -north));
    }

    #[test]
    fn both_formats_parse_from_hand_made_files() {
        let xyz = "# two views\nx,y,z,q0,qx,qy,qz\n1737400, 0, 50000, 1, 0, 0, 0\n\n1737500,10,20,0,1,0,0\n";
        let poses = parse_trajectory(xyz).unwrap();
        assert_eq!(poses.len(), 2);
        assert_eq!(
            poses[0].position_body_m,
            DVec3::new(1_737_400.0, 0.0, 50_000.0)
        );
        assert!(close(poses[1].camera_to_body * DVec3::Y, -DVec3::Y)); // 180° about x
        let ypr = "LON, LAT, ALT, YAW, PITCH, ROLL\n-11.36,-43.31,50000,0,0,0\n-11.30,-43.30,40000,10,25,0\n";
        let poses = parse_trajectory(ypr).unwrap();
        assert_eq!(poses.len(), 2);
        assert_eq!(
            poses[0],
            pose_from_lonlat(-11.36, -43.31, 50_000.0, 0.0, 0.0, 0.0)
        );
    }

    #[test]
    fn bad_files_name_the_line_and_the_fix() {
        let cases = [
            ("", "empty trajectory"),
            ("a,b,c\n1,2,3\n", "line 1: header `a,b,c` is neither"),
            (
                "# comment\n\na,b,c\n1,2,3\n",
                "line 3: header `a,b,c` is neither",
            ),
            ("x,y,z,q0,qx,qy,qz\n", "no rows"),
            (
                "x,y,z,q0,qx,qy,qz\n1,2,3,1,0,0\n",
                "line 2: expected 7 finite numbers",
            ),
            (
                "x,y,z,q0,qx,qy,qz\n1,2,3,1,0,0,oops\n",
                "line 2: `1,2,3,1,0,0,oops` has a value that is not a number",
            ),
            (
                "x,y,z,q0,qx,qy,qz\n1,2,3,2,0,0,0\n",
                "norm 2.0000, expected 1",
            ),
            (
                "lon,lat,alt,yaw,pitch,roll\n0,95,1000,0,0,0\n",
                "latitude 95 outside",
            ),
            (
                "lon,lat,alt,yaw,pitch,roll\n0,5,-3,0,0,0\n",
                "must be above the surface",
            ),
            (
                "lon,lat,alt,yaw,pitch,roll\n0,5,NaN,0,0,0\n",
                "finite numbers",
            ),
        ];
        for (text, message) in cases {
            let err = parse_trajectory(text).unwrap_err().to_string();
            assert!(err.contains(message), "{text:?}: {err}");
        }
    }
}

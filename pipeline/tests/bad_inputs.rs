//! Bad input is part of the product (docs/design.md, Bad input): each kind gives a one-line error naming the file and the fix,
//! a non-zero exit, and no finished-looking output (no dataset manifest.json).

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

use dataset::science::crs::LunarCrs;
use dataset::science::raster::{
    read_raster, write_geotiff, write_raster, BandOut, BandValues, RasterLayout,
};

/// A tiny world generated once for all cases.
fn world() -> &'static Path {
    static WORLD: OnceLock<PathBuf> = OnceLock::new();
    WORLD.get_or_init(|| {
        let out = Path::new(env!("CARGO_TARGET_TMPDIR")).join("bad-inputs-world");
        pipeline::synth::generate(&pipeline::synth::config::tiny(), 3, &out, true)
            .expect("tiny world")
    })
}

/// A case directory with a copy of the world's DEM and orthos, and a manifest pointing at them.
fn case() -> (tempfile::TempDir, PathBuf) {
    let tmp = tempfile::tempdir().unwrap();
    for sub in ["dem", "ortho"] {
        std::fs::create_dir_all(tmp.path().join(sub)).unwrap();
        for entry in std::fs::read_dir(world().join(sub)).unwrap().flatten() {
            std::fs::copy(entry.path(), tmp.path().join(sub).join(entry.file_name())).unwrap();
        }
    }
    // The world's files sit in dem/ and ortho/ here, not under world/.
    let manifest = tmp.path().join("m.toml");
    let text = pipeline::manifest::tiny_manifest_toml(1, 1.0).replace("world/", "");
    std::fs::write(&manifest, text).unwrap();
    (tmp, manifest)
}

fn first_ortho(dir: &Path) -> (PathBuf, PathBuf) {
    let mut metas: Vec<PathBuf> = std::fs::read_dir(dir.join("ortho"))
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "json"))
        .collect();
    metas.sort();
    (metas[0].with_extension("tif"), metas[0].clone())
}

/// Run the pipeline; assert a one-line error mentioning every `needles`, exit 1 and no published manifest.
fn assert_refused(dir: &Path, manifest: &Path, needles: &[&str]) {
    let out = Command::new(env!("CARGO_BIN_EXE_g2r-pipeline"))
        .arg("run")
        .arg(manifest)
        .output()
        .unwrap();
    assert_eq!(
        out.status.code(),
        Some(1),
        "exit code; stderr: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stderr = String::from_utf8_lossy(&out.stderr);
    let errors: Vec<&str> = stderr.lines().filter(|l| l.starts_with("error:")).collect();
    assert_eq!(errors.len(), 1, "exactly one error line:\n{stderr}");
    // Nothing else but structured log lines: no GDAL chatter, no multi-line snippets.
    let other: Vec<&str> = stderr
        .lines()
        .filter(|l| !l.starts_with("error:") && !l.contains(" INFO ") && !l.contains(" WARN "))
        .collect();
    assert!(other.is_empty(), "stray stderr lines: {other:?}");
    for needle in needles {
        assert!(
            errors[0].contains(needle),
            "error line lacks '{needle}': {}",
            errors[0]
        );
    }
    assert!(
        !dir.join("out/dataset/manifest.json").exists(),
        "nothing finished-looking"
    );
}

/// Replace `from` by `to` in a text file (a manifest) in place.
fn edit_text(path: &Path, from: &str, to: &str) {
    let text = std::fs::read_to_string(path).unwrap();
    assert!(text.contains(from), "{} has no '{from}'", path.display());
    std::fs::write(path, text.replace(from, to)).unwrap();
}

fn rewrite_json(path: &Path, edit: impl FnOnce(&mut serde_json::Value)) {
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    edit(&mut v);
    std::fs::write(path, serde_json::to_string_pretty(&v).unwrap()).unwrap();
}

#[test]
fn missing_dem_file() {
    let (tmp, m) = case();
    std::fs::remove_file(tmp.path().join("dem/dem.tif")).unwrap();
    assert_refused(tmp.path(), &m, &["dem.tif", "inputs.dem"]);
}

#[test]
fn unreadable_raster() {
    let (tmp, m) = case();
    std::fs::write(tmp.path().join("dem/dem.tif"), b"not a tiff at all").unwrap();
    assert_refused(tmp.path(), &m, &["dem.tif", "GDAL-readable"]);
}

#[test]
fn raster_without_crs() {
    let (tmp, m) = case();
    let path = tmp.path().join("dem/dem.tif");
    let dem = read_raster(&path).unwrap();
    std::fs::remove_file(&path).unwrap();
    let driver = gdal::DriverManager::get_driver_by_name("GTiff").unwrap();
    let mut ds = driver
        .create_with_band_type::<f32, _>(&path, dem.width, dem.height, 1)
        .unwrap();
    ds.set_geo_transform(&dem.transform.to_gdal()).unwrap();
    drop(ds);
    assert_refused(tmp.path(), &m, &["dem.tif", "no CRS", "gdal_edit"]);
}

#[test]
fn crs_not_lunar() {
    let (tmp, m) = case();
    let path = tmp.path().join("dem/dem.tif");
    let mut dem = read_raster(&path).unwrap();
    dem.crs =
        LunarCrs::new("+proj=eqc +lat_ts=-43.31 +lon_0=-11.36 +ellps=WGS84 +units=m +no_defs");
    write_raster(&path, &dem, &[]).unwrap();
    assert_refused(
        tmp.path(),
        &m,
        &["dem.tif", "not the lunar sphere", "gdalwarp"],
    );
}

#[test]
fn ortho_not_overlapping_the_dem() {
    let (tmp, m) = case();
    let (tif, _) = first_ortho(tmp.path());
    let mut ortho = read_raster(&tif).unwrap();
    ortho.transform.origin_x += 100_000.0;
    write_raster(&tif, &ortho, &[]).unwrap();
    assert_refused(
        tmp.path(),
        &m,
        &[
            &tif.file_name().unwrap().to_string_lossy(),
            "does not overlap",
        ],
    );
}

#[test]
fn ortho_coarser_than_the_dem() {
    let (tmp, m) = case();
    let (tif, _) = first_ortho(tmp.path());
    let ortho = read_raster(&tif).unwrap();
    let mut t = ortho.transform;
    t.pixel_width = 10.0;
    t.pixel_height = -10.0;
    let layout = RasterLayout {
        width: 50,
        height: 50,
        transform: t,
        crs: &ortho.crs,
        nodata: -1.0,
    };
    write_geotiff(
        &tif,
        &layout,
        &[BandOut {
            values: BandValues::Constant(0.1),
            description: "I/F",
        }],
        &[],
    )
    .unwrap();
    assert_refused(
        tmp.path(),
        &m,
        &[&tif.file_name().unwrap().to_string_lossy(), "coarser"],
    );
}

#[test]
fn all_nodata_dem() {
    let (tmp, m) = case();
    let path = tmp.path().join("dem/dem.tif");
    let mut dem = read_raster(&path).unwrap();
    dem.data.iter_mut().for_each(|v| *v = f32::NAN);
    write_raster(&path, &dem, &[]).unwrap();
    assert_refused(tmp.path(), &m, &["dem.tif", "nodata"]);
}

#[test]
fn nan_laden_dem_without_nodata_value() {
    let (tmp, m) = case();
    let path = tmp.path().join("dem/dem.tif");
    let dem = read_raster(&path).unwrap();
    // Raw NaNs (no nodata value declared) in two thirds of the rows.
    let values: Vec<f32> = dem
        .data
        .iter()
        .enumerate()
        .map(|(i, &v)| {
            if !(i / dem.width).is_multiple_of(3) {
                f32::NAN
            } else {
                v
            }
        })
        .collect();
    std::fs::remove_file(&path).unwrap();
    let driver = gdal::DriverManager::get_driver_by_name("GTiff").unwrap();
    let mut ds = driver
        .create_with_band_type::<f32, _>(&path, dem.width, dem.height, 1)
        .unwrap();
    ds.set_geo_transform(&dem.transform.to_gdal()).unwrap();
    ds.set_spatial_ref(
        &gdal::spatial_ref::SpatialRef::from_definition(&dem.crs.definition).unwrap(),
    )
    .unwrap();
    let mut band = ds.rasterband(1).unwrap();
    band.write(
        (0, 0),
        (dem.width, dem.height),
        &mut gdal::raster::Buffer::new((dem.width, dem.height), values),
    )
    .unwrap();
    drop(ds);
    assert_refused(tmp.path(), &m, &["dem.tif", "NaN"]);
}

#[test]
fn metadata_missing_a_field() {
    let (tmp, m) = case();
    let (_, json) = first_ortho(tmp.path());
    rewrite_json(&json, |v| {
        v.as_object_mut().unwrap().remove("sun_position_body_m");
    });
    assert_refused(
        tmp.path(),
        &m,
        &[
            &json.file_name().unwrap().to_string_lossy(),
            "missing field",
            "sun_position_body_m",
        ],
    );
}

#[test]
fn sun_below_the_horizon() {
    let (tmp, m) = case();
    let (_, json) = first_ortho(tmp.path());
    rewrite_json(&json, |v| {
        let sun: Vec<f64> = v["sun_position_body_m"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| -x.as_f64().unwrap())
            .collect();
        v["sun_position_body_m"] = serde_json::json!(sun);
    });
    assert_refused(
        tmp.path(),
        &m,
        &[
            &json.file_name().unwrap().to_string_lossy(),
            "below the horizon",
        ],
    );
}

#[test]
fn ortho_without_metadata() {
    let (tmp, m) = case();
    let (_, json) = first_ortho(tmp.path());
    std::fs::remove_file(&json).unwrap();
    assert_refused(tmp.path(), &m, &["has no acquisition metadata"]);
}

#[test]
fn positions_in_kilometres_not_metres() {
    let (tmp, m) = case();
    let (_, json) = first_ortho(tmp.path());
    rewrite_json(&json, |v| {
        let start: Vec<f64> = v["spacecraft_start_body_m"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap() / 1000.0)
            .collect();
        v["spacecraft_start_body_m"] = serde_json::json!(start);
    });
    assert_refused(
        tmp.path(),
        &m,
        &[&json.file_name().unwrap().to_string_lossy(), "units metres"],
    );
}

#[test]
fn pipeline_manifest_missing_a_field() {
    let (tmp, m) = case();
    edit_text(&m, "coverage = 1.0\n", "");
    assert_refused(tmp.path(), &m, &["m.toml", "coverage"]);
}

#[test]
fn shard_size_that_cuts_a_row_group() {
    // Shards are copied as whole 256-row groups: 300 rows per shard would split one.
    let (tmp, m) = case();
    edit_text(&m, "rows_per_shard = 40", "rows_per_shard = 300");
    assert_refused(
        tmp.path(),
        &m,
        &["m.toml", "rows_per_shard = 300", "multiple of 256"],
    );
}

#[test]
fn object_store_url_where_a_local_path_belongs() {
    // It would otherwise be joined onto the manifest's folder as the relative path `s3:/bucket/out`.
    let (tmp, m) = case();
    edit_text(&m, "dir = \"out\"", "dir = \"s3://bucket/out\"");
    assert_refused(
        tmp.path(),
        &m,
        &[
            "m.toml",
            "output.dir",
            "s3://bucket/out",
            "g2r-dataset upload",
        ],
    );
    assert!(
        !tmp.path().join("s3:").exists(),
        "no local folder named after the URL"
    );
}

#[test]
fn context_cell_size_that_is_not_positive() {
    let (tmp, m) = case();
    edit_text(
        &m,
        "sun_disk_samples = 2\n",
        "sun_disk_samples = 2\ncontext_gsd_m = 0.0\n",
    );
    assert_refused(
        tmp.path(),
        &m,
        &["m.toml", "context_gsd_m = 0", "positive cell size"],
    );
}

#[test]
fn duplicate_ortho_id() {
    let (tmp, m) = case();
    let (_, json) = first_ortho(tmp.path());
    let copy = json.with_file_name("Zcopy.json");
    std::fs::copy(&json, &copy).unwrap();
    assert_refused(tmp.path(), &m, &["Zcopy.json", "already used", "unique"]);
}

#[test]
fn unknown_stage_name() {
    let (tmp, m) = case();
    let out = Command::new(env!("CARGO_BIN_EXE_g2r-pipeline"))
        .arg("run")
        .arg(&m)
        .args(["--until", "projekt"])
        .output()
        .unwrap();
    // A usage error, refused by the argument parser before anything runs (exit 2, as for every bad flag).
    assert_eq!(out.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("'projekt'")
            && stderr.contains("ingest, erode, sample, split, project, publish"),
        "{stderr}"
    );
    assert!(!tmp.path().join("out/dataset/manifest.json").exists());
}

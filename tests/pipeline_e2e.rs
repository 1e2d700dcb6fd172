//! The stage pipeline end to end on a tiny synthetic world: published shards are byte-reproducible, runs are
//! incremental, an interrupted run resumes to the same bytes, the shards read with pyarrow and polars, and a build
//! split into partitions and merged publishes the same bytes as one process.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use pipeline::manifest::PipelineManifest;
use pipeline::runner::Staleness;

fn world(dir: &Path) -> PathBuf {
    pipeline::synth::generate(
        &g2r_tests::tiny_world_config(),
        5,
        &dir.join("world"),
        false,
    )
    .unwrap()
}

fn manifest(dir: &Path, coverage: f64) -> PathBuf {
    let path = dir.join("tiny.toml");
    std::fs::write(&path, pipeline::manifest::tiny_manifest_toml(9, coverage)).unwrap();
    path
}

fn run(manifest_path: &Path, until: Option<&str>) -> Vec<&'static str> {
    let m = PipelineManifest::load(manifest_path).unwrap();
    pipeline::stages::pipeline(&m, indicatif::ProgressBar::hidden())
        .unwrap()
        .run(until, &[])
        .unwrap()
}

fn status(manifest_path: &Path) -> Vec<(&'static str, Staleness)> {
    let m = PipelineManifest::load(manifest_path).unwrap();
    pipeline::stages::pipeline(&m, indicatif::ProgressBar::hidden())
        .unwrap()
        .status()
        .unwrap()
}

/// Every file of the published dataset with its bytes.
fn published(dir: &Path) -> BTreeMap<String, Vec<u8>> {
    std::fs::read_dir(dir.join("out/dataset"))
        .unwrap()
        .flatten()
        .map(|e| {
            (
                e.file_name().to_string_lossy().into_owned(),
                std::fs::read(e.path()).unwrap(),
            )
        })
        .collect()
}

#[test]
fn pipeline_is_reproducible_incremental_and_readable() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    world(dir);
    let m = manifest(dir, 2.0);
    assert!(status(&m).iter().all(|(_, s)| *s == Staleness::NeverRun));
    assert_eq!(run(&m, None).len(), 6);
    assert!(
        status(&m).iter().all(|(_, s)| *s == Staleness::UpToDate),
        "{:?}",
        status(&m)
    );
    assert!(run(&m, None).is_empty(), "a second run has nothing to do");
    let first = published(dir);
    let shards: Vec<&String> = first.keys().filter(|k| k.ends_with(".parquet")).collect();
    assert!(shards.iter().any(|s| s.starts_with("train-")), "{shards:?}");

    // A clean rebuild, interrupted after `sample` and resumed, gives byte-identical shards and manifest.
    let lm = PipelineManifest::load(&m).unwrap();
    pipeline::stages::pipeline(&lm, indicatif::ProgressBar::hidden())
        .unwrap()
        .clean()
        .unwrap();
    std::fs::remove_dir_all(dir.join("out/dataset")).unwrap();
    assert_eq!(run(&m, Some("sample")), vec!["ingest", "erode", "sample"]);
    assert_eq!(run(&m, None), vec!["split", "project", "publish"]);
    let second = published(dir);
    assert_eq!(
        first.keys().collect::<Vec<_>>(),
        second.keys().collect::<Vec<_>>()
    );
    for (name, bytes) in &first {
        assert!(
            bytes == &second[name],
            "{name} differs between two clean runs"
        );
    }
    let verify =
        dataset::contract::manifest::DatasetManifest::load(&dir.join("out/dataset/manifest.json"))
            .unwrap();
    assert!(verify.verify(&dir.join("out/dataset")).is_empty());

    // Re-publishing gives the same manifest bytes (its lock hash covers only the upstream stages).
    let lm = PipelineManifest::load(&m).unwrap();
    let runner = pipeline::stages::pipeline(&lm, indicatif::ProgressBar::hidden()).unwrap();
    assert_eq!(runner.run(None, &["publish"]).unwrap(), vec!["publish"]);
    assert_eq!(published(dir), first);
    // A deleted shard is not "up to date": publish is stale and rebuilds the same bytes.
    let shard = dir
        .join("out/dataset")
        .join(first.keys().find(|k| k.ends_with(".parquet")).unwrap());
    std::fs::remove_file(&shard).unwrap();
    assert!(
        matches!(status(&m)[5].1, Staleness::OutputChanged(ref why) if why.contains("missing")),
        "{:?}",
        status(&m)[5]
    );
    assert_eq!(run(&m, None), vec!["publish"]);
    assert_eq!(published(dir), first);

    // A parameter change makes exactly that stage and its successors stale, and says why.
    let m2 = manifest(dir, 3.0);
    let st = status(&m2);
    assert_eq!(
        &st[..3],
        &[
            ("ingest", Staleness::UpToDate),
            ("erode", Staleness::UpToDate),
            ("sample", Staleness::ParamsChanged)
        ]
    );
    assert!(
        st[3..]
            .iter()
            .all(|(_, s)| *s == Staleness::UpstreamStale("sample")),
        "{st:?}"
    );

    // The shards read with pyarrow and polars, no custom code; columns and shapes as documented.
    let script = r#"
import sys, glob, pyarrow.parquet as pq, polars as pl
files = sorted(glob.glob(sys.argv[1] + "/*.parquet"))
t = pq.read_table(files[0])
assert t.column("dem")[0].values.to_numpy().shape == (130 * 130,)
assert t.column("image")[0].values.to_numpy().shape == (128 * 128,)
assert set(t.column("split").to_pylist()) <= {"train", "val", "test"}
df = pl.read_parquet(files[0])
assert df.height == t.num_rows and "sun_dir_enu" in df.columns
assert len(df["sun_lit"][0]) == 128 * 128
n = sum(pq.ParquetFile(f).metadata.num_rows for f in files)
# The summary's tallies (polars group-bys in the publish stage) against a count of the shards' own rows.
import json, collections
summary = json.load(open(sys.argv[1] + "/summary.json"))
per_ortho, per_tile = collections.defaultdict(dict), collections.Counter()
for f in files:
    t = pq.read_table(f, columns=["ortho_id", "split", "tile_id"])
    for o, s, tile in zip(*(t.column(c).to_pylist() for c in ["ortho_id", "split", "tile_id"])):
        per_ortho[o][s] = per_ortho[o].get(s, 0) + 1
        per_tile[tile] += 1
assert summary["per_ortho"] == per_ortho, (summary["per_ortho"], dict(per_ortho))
assert summary["per_tile"] == dict(per_tile), (summary["per_tile"], dict(per_tile))
assert len(per_tile) > 1
print("rows", n)
"#;
    let out = Command::new(g2r_tests::python())
        .arg("-c")
        .arg(script)
        .arg(dir.join("out/dataset"))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    let total: u64 = verify.split_counts.values().sum();
    assert_eq!(
        String::from_utf8_lossy(&out.stdout).trim(),
        format!("rows {total}")
    );
}

/// A build directory beside the tiny world: the world linked in, the tiny manifest, output in `out/` (the same
/// relative paths as any other, so locks and published manifests can be compared byte for byte).
fn build_dir(dir: &Path, name: &str) -> PathBuf {
    let build = dir.join(name);
    std::fs::create_dir_all(&build).unwrap();
    std::os::unix::fs::symlink(dir.join("world"), build.join("world")).unwrap();
    manifest(&build, 8.0)
}

/// Run one partition as `g2r-pipeline run --partition` does; its run record lands in the partition's directory.
fn run_partition(manifest_path: &Path, part: &str, until: Option<&str>) -> Vec<&'static str> {
    let m = PipelineManifest::load(manifest_path).unwrap();
    let part: pipeline::partition::Partition = part.parse().unwrap();
    let outcome = pipeline::jobs::run(
        &m,
        pipeline::jobs::RunScope::Partition(part),
        until,
        &[],
        indicatif::ProgressBar::hidden(),
    )
    .unwrap();
    if !outcome.stages.is_empty() {
        assert_eq!(
            outcome.record,
            Some(pipeline::partition::dir(&m, part).join("run-record.json"))
        );
    }
    outcome.stages.iter().map(|stage| stage.name).collect()
}

/// Merge `count` partitions and publish as `run --merge` does (the merge is the run record's first stage); the
/// error as one line.
fn merge(manifest_path: &Path, count: usize) -> Result<Vec<&'static str>, String> {
    let m = PipelineManifest::load(manifest_path).unwrap();
    let outcome = pipeline::jobs::run(
        &m,
        pipeline::jobs::RunScope::Merge(count),
        None,
        &[],
        indicatif::ProgressBar::hidden(),
    )
    .map_err(|e| format!("{e:#}"))?;
    assert_eq!(outcome.stages[0].name, "merge");
    assert_eq!(outcome.record, Some(m.out_dir().join("run-record.json")));
    // One hash memo for the command: the partitions' checks, adopt and the publish run read each file once.
    let hashing = outcome.hashing;
    assert!(hashing.distinct_files > 0, "{hashing:?}");
    assert_eq!(hashing.files_hashed, hashing.distinct_files, "{hashing:?}");
    Ok(outcome.stages[1..].iter().map(|stage| stage.name).collect())
}

#[test]
fn partitioned_builds_publish_the_same_bytes_as_one_process() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    world(dir);
    let single = build_dir(dir, "single");
    assert_eq!(run(&single, None).len(), 6);
    let reference = published(&dir.join("single"));
    // Several row groups in a split, so the merge both copies whole groups and re-cuts them at part boundaries.
    let train_shards = reference.keys().filter(|k| k.starts_with("train-")).count();
    assert!(train_shards >= 3, "{:?}", reference.keys());
    let single_lock = std::fs::read(dir.join("single/out/pipeline.lock.json")).unwrap();

    // The tiny world has three strips: one, two and three partitions.
    for count in 1..=3 {
        let m = build_dir(dir, &format!("partitions-{count}"));
        for index in 0..count {
            assert_eq!(
                run_partition(&m, &format!("{index}/{count}"), None),
                vec!["ingest", "erode", "sample", "split", "project"]
            );
        }
        assert!(
            !dir.join(format!("partitions-{count}/out/dataset")).exists(),
            "partitions publish nothing"
        );
        assert_eq!(merge(&m, count).unwrap(), vec!["publish"]);
        let lock =
            std::fs::read_to_string(dir.join(format!("partitions-{count}/out/pipeline.lock.json")))
                .unwrap();
        assert_eq!(
            lock,
            String::from_utf8(single_lock.clone()).unwrap(),
            "the merge records the same lock as one process"
        );
        let merged = published(&dir.join(format!("partitions-{count}")));
        assert_eq!(
            merged.keys().collect::<Vec<_>>(),
            reference.keys().collect::<Vec<_>>()
        );
        for (name, bytes) in &reference {
            assert!(
                bytes == &merged[name],
                "{name}: N = {count} differs from one process"
            );
        }
        assert!(
            status(&m).iter().all(|(_, s)| *s == Staleness::UpToDate),
            "after a merge the single-process runner has nothing to do: {:?}",
            status(&m)
        );
    }

    // A partition that never ran, then one killed after split: the merge names it and publishes nothing; the
    // rerun completes it and the merge gives the same bytes.
    let m = build_dir(dir, "interrupted");
    run_partition(&m, "0/2", None);
    let err = merge(&m, 2).unwrap_err();
    assert!(
        err.contains("partition 1/2 is not finished") && err.contains("never run"),
        "{err}"
    );
    run_partition(&m, "1/2", Some("split"));
    let err = merge(&m, 2).unwrap_err();
    assert!(
        err.contains("partition 1/2 is not finished (project"),
        "{err}"
    );
    assert!(
        !dir.join("interrupted/out/dataset").exists(),
        "nothing published"
    );
    assert_eq!(run_partition(&m, "1/2", None), vec!["project"]);
    assert_eq!(merge(&m, 2).unwrap(), vec!["publish"]);
    assert_eq!(published(&dir.join("interrupted")), reference);
}

#[test]
fn a_crater_catalogue_frames_every_sample_and_a_missing_one_is_named() {
    let tmp = tempfile::tempdir().unwrap();
    world(tmp.path());
    let dem = dataset::science::raster::read_raster(&tmp.path().join("world/dem/dem.tif")).unwrap();
    let (x0, y0, x1, y1) = dem.transform.bounds(dem.width, dem.height);
    let centre = ((x0 + x1) / 2.0, (y0 + y1) / 2.0);
    let radius_m = (x1 - x0) / 4.0;
    let (lon, lat) = dem.crs.to_lonlat_deg(centre.0, centre.1).unwrap();
    std::fs::write(
        tmp.path().join("craters.csv"),
        format!(
            "lon_deg,lat_deg,diameter_m\n{lon:.12},{lat:.12},{}\n",
            2.0 * radius_m
        ),
    )
    .unwrap();
    let with_catalogue = |catalogue: &str| {
        pipeline::manifest::tiny_manifest_toml(9, 2.0)
            .replace(
                "ortho_dir = \"world/ortho\"",
                &format!("ortho_dir = \"world/ortho\"\ncrater_catalogue = \"{catalogue}\""),
            )
            .replace(
                "[project]",
                "[project]\ncrater_frame_min_diameter_m = 100.0",
            )
    };
    let path = tmp.path().join("tiny.toml");
    std::fs::write(&path, with_catalogue("craters.csv")).unwrap();
    run(&path, None);
    let read_samples = |dataset: &Path| {
        let mut samples = Vec::new();
        for entry in std::fs::read_dir(dataset).unwrap().flatten() {
            if entry.path().extension().is_some_and(|e| e == "parquet") {
                let file = dataset::contract::shard::ShardFile::open(&entry.path()).unwrap();
                for group in 0..file.row_group_sizes().len() {
                    for batch in file.read_batches(group, None, true).unwrap() {
                        samples
                            .extend(dataset::contract::schema::batch_to_samples(&batch).unwrap());
                    }
                }
            }
        }
        samples.sort_by(|a, b| a.sample_id.cmp(&b.sample_id));
        samples
    };
    let samples = read_samples(&tmp.path().join("out/dataset"));
    assert!(samples.len() > 10, "{} samples", samples.len());
    for s in &samples {
        let crater = s
            .crater
            .unwrap_or_else(|| panic!("{} has no crater frame", s.sample_id));
        // The tiny world's map is true to scale at its centre: ρ is the map distance over the radius.
        let rho = (s.center_x_m - centre.0).hypot(s.center_y_m - centre.1) / radius_m;
        assert!(
            (crater.rho - rho).abs() < 1e-6 * rho.max(1.0),
            "{}: {crater:?}, ρ {rho}",
            s.sample_id
        );
        assert!(
            crater.relative_height_m.is_finite(),
            "{}: {crater:?}",
            s.sample_id
        );
        // One crater frames every crop: one relief, published with each (schema 1.4).
        let relief = samples[0].crater.and_then(|c| c.relief_to_diameter);
        assert!(
            relief.is_some_and(|r| r > 0.0 && r.is_finite()) && crater.relief_to_diameter == relief,
            "{}: {crater:?}",
            s.sample_id
        );
    }
    // Framed by draws of the catalogue with a real one's errors: the same samples, placed in moved frames, and
    // the manifest says so.
    let with_errors = tmp.path().join("tiny-error.toml");
    std::fs::write(
        &with_errors,
        with_catalogue("craters.csv")
            .replace("dir = \"out\"", "dir = \"out-error\"")
            .replace(
                "[project]",
                "[project]\ncrater_catalogue_error = { centre_sd_m = 100.0, diameter_log_sd = 0.05, \
                 missed_fraction = 0.0, false_craters = 0.0, draws = 4 }",
            ),
    )
    .unwrap();
    run(&with_errors, None);
    let drawn = read_samples(&tmp.path().join("out-error/dataset"));
    let ids = |s: &[dataset::contract::schema::Sample]| {
        s.iter().map(|s| s.sample_id.clone()).collect::<Vec<_>>()
    };
    assert_eq!(ids(&drawn), ids(&samples));
    let moved = samples
        .iter()
        .zip(&drawn)
        .filter(|(a, b)| (a.crater.unwrap().rho - b.crater.unwrap().rho).abs() > 1e-6)
        .count();
    assert!(
        moved * 10 >= samples.len() * 9,
        "{moved} of {} moved",
        samples.len()
    );
    let manifest: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(tmp.path().join("out-error/dataset/manifest.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(manifest["crater_frame"]["catalogue_error"]["draws"], 4);
    let exact: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(tmp.path().join("out/dataset/manifest.json")).unwrap(),
    )
    .unwrap();
    assert!(exact["crater_frame"].get("catalogue_error").is_none());
    // A catalogue that is not there is named, with the manifest key to fix.
    std::fs::write(&path, with_catalogue("missing.csv")).unwrap();
    let m = PipelineManifest::load(&path).unwrap();
    let err = pipeline::stages::pipeline(&m, indicatif::ProgressBar::hidden())
        .err()
        .expect("a missing catalogue is refused")
        .to_string();
    assert!(
        err.contains("missing.csv") && err.contains("inputs.crater_catalogue"),
        "{err}"
    );
}

#[test]
fn a_unit_map_gives_every_context_window_its_highland_fraction_and_a_bad_one_is_named() {
    let tmp = tempfile::tempdir().unwrap();
    let mut config = g2r_tests::tiny_world_config();
    config.unit_map = Some(pipeline::synth::config::UnitMapConfig {
        gsd_m: 100.0,
        generalisation_m: 1000.0,
        displacement_m: 400.0,
        displacement_wavelength_m: 4000.0,
    });
    pipeline::synth::generate(&config, 5, &tmp.path().join("world"), false).unwrap();
    let map_path = tmp
        .path()
        .join("world")
        .join(dataset::contract::world::UNIT_MAP);
    let map = dataset::science::raster::read_raster(&map_path).unwrap();
    assert!(map.data.iter().all(|&v| v == 0.0 || v == 1.0));
    let path = tmp.path().join("tiny.toml");
    std::fs::write(
        &path,
        pipeline::manifest::tiny_manifest_toml(9, 2.0).replace(
            "ortho_dir = \"world/ortho\"",
            "ortho_dir = \"world/ortho\"\nunit_map = \"world/map/units.tif\"",
        ),
    )
    .unwrap();
    run(&path, None);
    let m = PipelineManifest::load(&path).unwrap();
    let mut checked = 0;
    for entry in std::fs::read_dir(tmp.path().join("out/dataset"))
        .unwrap()
        .flatten()
    {
        if entry.path().extension().is_none_or(|e| e != "parquet") {
            continue;
        }
        let file = dataset::contract::shard::ShardFile::open(&entry.path()).unwrap();
        for sample in file.read_all().unwrap() {
            let context = sample.context.unwrap();
            let highland = context
                .highland
                .expect("every window carries the map's units");
            let g = context.gsd_m;
            assert_eq!(g, m.project.context_gsd_m);
            // The independent expectation: the mean of the map pixels whose centres lie in each cell, for the
            // cells the map covers whole (100 m pixels in 512 m cells: the windows' blocks are the pixels).
            let t = &map.transform;
            for (k, &got) in highland.iter().enumerate() {
                let (i, j) = ((k / 32) as f64, (k % 32) as f64);
                let (x0, y1) = (
                    sample.center_x_m + (j - 16.0) * g,
                    sample.center_y_m + (16.0 - i) * g,
                );
                let (c0, r0) = t.map_to_pixel(x0, y1);
                let (c1, r1) = t.map_to_pixel(x0 + g, y1 - g);
                // Pixel-centre coordinates: the centres in [c0, c1) × [r0, r1).
                let cols = c0.ceil() as i64..c1.ceil() as i64;
                let rows = r0.ceil() as i64..r1.ceil() as i64;
                let inside = |n: i64, len: usize| n >= 0 && (n as usize) < len;
                let whole = cols.clone().all(|c| inside(c, map.width))
                    && rows.clone().all(|r| inside(r, map.height));
                if !whole {
                    continue;
                }
                let (mut sum, mut n) = (0.0, 0);
                for r in rows.clone() {
                    for c in cols.clone() {
                        sum += f64::from(map.get(c as usize, r as usize));
                        n += 1;
                    }
                }
                assert!(
                    (f64::from(got) - sum / n as f64).abs() < 1e-5,
                    "{} cell {k}: {got} against {}",
                    sample.sample_id,
                    sum / n as f64
                );
                checked += 1;
            }
        }
    }
    assert!(checked > 1000, "{checked} cells checked");
    // A map of class codes, not fractions, is refused with the file and the fix.
    let bad_path = tmp.path().join("codes.tif");
    let codes: Vec<f32> = map.data.iter().map(|v| v + 1.0).collect();
    dataset::science::raster::write_geotiff(
        &bad_path,
        &dataset::science::raster::RasterLayout {
            width: map.width,
            height: map.height,
            transform: map.transform,
            crs: &map.crs,
            nodata: -1.0,
        },
        &[dataset::science::raster::BandOut {
            values: dataset::science::raster::BandValues::Grid(&codes),
            description: "unit code",
        }],
        &[],
    )
    .unwrap();
    let dem = dataset::science::raster::read_raster(&tmp.path().join("world/dem/dem.tif")).unwrap();
    let err = dataset::contract::context::read_unit_map(&bad_path, &dem)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("codes.tif") && err.contains("[0, 1]") && !err.contains('\n'),
        "{err}"
    );
}

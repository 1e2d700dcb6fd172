//! `[output] publish_to = "s3://…"`: the pipeline copies the dataset it built to object storage, byte for byte, with
//! the manifest last; a rerun with nothing stale finds it there and copies nothing; a bucket that refuses the write
//! fails in one line and keeps the build's run record, and a rerun once the bucket exists publishes the same bytes; a prefix
//! that holds another dataset is refused. Against an S3 server on 127.0.0.1 (moto, started on a free loopback
//! port and stopped by PID; `.ci/setup` installs `moto[server]` into .venv).

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use dataset::storage::RemoteDir;
use dataset::testing::s3::Moto;

/// The tests that talk to a bucket point this process's AWS_* variables at their own moto server, so they take
/// turns.
static ONE_SERVER_AT_A_TIME: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Start moto and point this process's S3 settings at it, holding the turn until the test ends.
fn moto_for_this_test() -> (std::sync::MutexGuard<'static, ()>, Moto) {
    let turn = ONE_SERVER_AT_A_TIME
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    let moto = Moto::start();
    for (key, value) in moto.env() {
        std::env::set_var(key, value);
    }
    (turn, moto)
}

/// Retries bounded so a refused write fails in seconds.
const RETRIES: [(&str, &str); 2] = [
    ("G2R_STORE_MAX_RETRIES", "1"),
    ("G2R_STORE_RETRY_TIMEOUT_S", "10"),
];

/// A tiny world and a manifest building it into `dir/out`, copied to `url`.
fn build_dir(dir: &Path, url: &str) -> PathBuf {
    pipeline::synth::generate(
        &pipeline::synth::config::tiny(),
        3,
        &dir.join("world"),
        true,
    )
    .expect("tiny world");
    tiny_manifest(dir, 1.0, &format!("publish_to = \"{url}\""))
}

/// `dir/m.toml`: the tiny manifest at `coverage` with `output_line` added to its `[output]` table.
fn tiny_manifest(dir: &Path, coverage: f64, output_line: &str) -> PathBuf {
    let manifest = dir.join("m.toml");
    let text = pipeline::manifest::tiny_manifest_toml(1, coverage)
        .replace("dir = \"out\"", &format!("dir = \"out\"\n{output_line}"));
    std::fs::write(&manifest, text).unwrap();
    manifest
}

fn run(manifest: &Path, moto: &Moto) -> Output {
    Command::new(env!("CARGO_BIN_EXE_g2r-pipeline"))
        .arg("run")
        .arg(manifest)
        .envs(moto.env())
        .envs(RETRIES)
        .output()
        .unwrap()
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// The one `error:` line of a failed run.
fn error_line(out: &Output) -> String {
    assert_eq!(out.status.code(), Some(1), "{}", stderr(out));
    let text = stderr(out);
    let errors: Vec<&str> = text.lines().filter(|l| l.starts_with("error:")).collect();
    assert_eq!(errors.len(), 1, "{text}");
    errors[0].to_string()
}

/// The names of the files in `dir`, sorted.
fn names_under(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

/// Every file of the local dataset, and the same names read from `url`.
fn local_and_remote(dataset: &Path, url: &str) -> Vec<(String, Vec<u8>, Vec<u8>)> {
    let remote = RemoteDir::open(url).unwrap();
    names_under(dataset)
        .into_iter()
        .map(|name| {
            let local = std::fs::read(dataset.join(&name)).unwrap();
            let copied = remote.get(&name).unwrap();
            (name, local, copied)
        })
        .collect()
}

#[test]
fn a_built_dataset_is_copied_to_its_bucket_once_and_a_refused_copy_is_rerun() {
    let (_turn, moto) = moto_for_this_test();
    let tmp = tempfile::tempdir().unwrap();
    // The bucket does not exist yet: the store refuses the copy.
    let url = "s3://published/tiny";
    let manifest = build_dir(tmp.path(), url);
    let refused = error_line(&run(&manifest, &moto));
    assert!(refused.contains("s3://published/tiny/"), "{refused}");
    // The build's timings were kept although the copy failed.
    assert!(tmp.path().join("out/run-record.json").exists());

    // Once the bucket exists, a rerun (every stage up to date) copies the same bytes.
    assert_eq!(moto.request("PUT", "/published"), 200);
    let out = run(&manifest, &moto);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(
        stderr(&out).contains("dataset copied to object storage"),
        "{}",
        stderr(&out)
    );
    let dataset = tmp.path().join("out/dataset");
    let files = local_and_remote(&dataset, url);
    assert!(files.iter().any(|(name, ..)| name.ends_with(".parquet")));
    assert!(files.iter().any(|(name, ..)| name == "manifest.json"));
    for (name, local, copied) in &files {
        assert!(local == copied, "{name}: the copy differs from the build");
    }

    // Run again: nothing stale, the dataset is there already, nothing is copied.
    let out = run(&manifest, &moto);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(
        stderr(&out).contains("already published there"),
        "{}",
        stderr(&out)
    );

    // A prefix holding another dataset's manifest is refused, and left as it was.
    let other = RemoteDir::open("s3://published/other").unwrap();
    other
        .put("manifest.json", b"{\"name\": \"other\"}".to_vec())
        .unwrap();
    let text = std::fs::read_to_string(&manifest)
        .unwrap()
        .replace(url, "s3://published/other");
    std::fs::write(&manifest, text).unwrap();
    let refused = error_line(&run(&manifest, &moto));
    assert!(
        refused.contains("s3://published/other") && refused.contains("already published"),
        "{refused}"
    );
    assert_eq!(
        other.get("manifest.json").unwrap(),
        b"{\"name\": \"other\"}".to_vec()
    );
}

#[test]
fn publish_to_and_exchange_must_name_object_storage() {
    let tmp = tempfile::tempdir().unwrap();
    for (field, line) in [
        ("output.publish_to", "publish_to = \"copies/tiny\""),
        ("output.exchange", "exchange = \"shared/build\""),
    ] {
        let manifest = tiny_manifest(tmp.path(), 1.0, line);
        let error = format!(
            "{:#}",
            pipeline::manifest::PipelineManifest::load(&manifest).unwrap_err()
        );
        assert!(
            error.contains("m.toml") && error.contains(field) && error.contains("s3://"),
            "{error}"
        );
    }
}

/// A folder standing for one machine: the tiny world (generated once, in `world`) linked in, and a manifest whose
/// partitions meet through `exchange`.
fn machine(tmp: &Path, name: &str, exchange: &str) -> PathBuf {
    let dir = tmp.join(name);
    std::fs::create_dir_all(&dir).unwrap();
    std::os::unix::fs::symlink(tmp.join("world"), dir.join("world")).unwrap();
    tiny_manifest(&dir, 2.0, &format!("exchange = \"{exchange}\""))
}

fn run_with(manifest: &Path, moto: &Moto, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_g2r-pipeline"))
        .arg("run")
        .arg(manifest)
        .args(args)
        .envs(moto.env())
        .envs(RETRIES)
        .output()
        .unwrap()
}

fn dataset_files(manifest: &Path) -> Vec<(String, Vec<u8>)> {
    let dataset = manifest.parent().unwrap().join("out/dataset");
    names_under(&dataset)
        .into_iter()
        .map(|name| {
            let bytes = std::fs::read(dataset.join(&name)).unwrap();
            (name, bytes)
        })
        .collect()
}

/// A run that succeeded and logged `text`.
fn succeeds_saying(out: &Output, text: &str) {
    assert!(
        out.status.success() && stderr(out).contains(text),
        "{}",
        stderr(out)
    );
}

/// Two partitions on two machines that share no folder, and a merge on a third, meet only through the bucket; the
/// merge publishes the bytes one process publishes. A merge before a partition's copy is complete (no marker:
/// not run yet, or being replaced) fails naming it and publishes nothing; once the partition reruns, it succeeds.
#[test]
fn partitions_without_a_shared_file_system_meet_through_the_exchange() {
    let (_turn, moto) = moto_for_this_test();
    assert_eq!(moto.request("PUT", "/build"), 200);
    let tmp = tempfile::tempdir().unwrap();
    pipeline::synth::generate(
        &pipeline::synth::config::tiny(),
        3,
        &tmp.path().join("world"),
        true,
    )
    .expect("tiny world");
    let exchange = "s3://build/tiny";
    let [single, first, second, merger] =
        ["single", "first", "second", "merger"].map(|name| machine(tmp.path(), name, exchange));
    let out = run_with(&single, &moto, &[]);
    assert!(out.status.success(), "{}", stderr(&out));

    succeeds_saying(
        &run_with(&first, &moto, &["--partition", "0/2"]),
        "partition copied to the exchange",
    );
    let missing = error_line(&run_with(&merger, &moto, &["--merge", "2"]));
    assert!(
        missing.contains("partition 1/2")
            && missing.contains("s3://build/tiny/partitions/2/1/complete.json"),
        "{missing}"
    );
    assert!(!merger.parent().unwrap().join("out/dataset").exists());

    let out = run_with(&second, &moto, &["--partition", "1/2"]);
    assert!(out.status.success(), "{}", stderr(&out));
    // A rerun finds its copy in place and sends nothing.
    succeeds_saying(
        &run_with(&second, &moto, &["--partition", "1/2"]),
        "partition already in the exchange",
    );
    // A copy being replaced has no marker: the merge waits for it.
    let copy = RemoteDir::open("s3://build/tiny/partitions/2/1").unwrap();
    copy.delete(pipeline::exchange::MARKER).unwrap();
    let replacing = error_line(&run_with(&merger, &moto, &["--merge", "2"]));
    assert!(replacing.contains("partition 1/2"), "{replacing}");
    succeeds_saying(
        &run_with(&second, &moto, &["--partition", "1/2"]),
        "partition copied to the exchange",
    );

    let out = run_with(&merger, &moto, &["--merge", "2"]);
    assert!(out.status.success(), "{}", stderr(&out));
    let (merged, reference) = (dataset_files(&merger), dataset_files(&single));
    assert!(merged.iter().any(|(name, _)| name.ends_with(".parquet")));
    assert_eq!(
        merged.iter().map(|(name, _)| name).collect::<Vec<_>>(),
        reference.iter().map(|(name, _)| name).collect::<Vec<_>>()
    );
    for ((name, a), (_, b)) in merged.iter().zip(&reference) {
        assert!(
            a == b,
            "{name}: the merge through the exchange differs from one process"
        );
    }
}

/// A file larger than one part goes up as a multipart upload and comes back whole, checked by its blake3.
#[test]
fn large_files_go_up_in_parts_and_come_back_whole() {
    let (_turn, moto) = moto_for_this_test();
    assert_eq!(moto.request("PUT", "/parts"), 200);
    let tmp = tempfile::tempdir().unwrap();
    let (from, to) = (tmp.path().join("big.bin"), tmp.path().join("back.bin"));
    // 40 MiB of varied bytes: two parts of 32 MiB and 8 MiB.
    let bytes: Vec<u8> = (0..40u64 << 20)
        .map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8)
        .collect();
    std::fs::write(&from, &bytes).unwrap();
    let remote = RemoteDir::open("s3://parts/x").unwrap();
    assert_eq!(
        remote.put_file("big.bin", &from).unwrap(),
        bytes.len() as u64
    );
    assert_eq!(remote.size("big.bin").unwrap(), bytes.len() as u64);
    let blake3 = remote
        .get_to_file("big.bin", bytes.len() as u64, &to)
        .unwrap();
    assert_eq!(blake3, blake3::hash(&bytes).to_hex().to_string());
    assert!(std::fs::read(&to).unwrap() == bytes);
}

/// Assert that the datasets of two manifests hold the same files with the same bytes, except that their
/// `manifest.json` may differ in `pipeline_lock_blake3` (each lock names the inputs where its build read them);
/// returns the files of `built`.
fn same_dataset_but_the_lock(built: &Path, reference: &Path) -> Vec<(String, Vec<u8>)> {
    let (built, reference) = (dataset_files(built), dataset_files(reference));
    assert!(built.iter().any(|(name, _)| name.ends_with(".parquet")));
    assert_eq!(
        built.iter().map(|(name, _)| name).collect::<Vec<_>>(),
        reference.iter().map(|(name, _)| name).collect::<Vec<_>>()
    );
    let without_lock = |bytes: &[u8]| {
        let mut manifest: serde_json::Value = serde_json::from_slice(bytes).unwrap();
        let lock = manifest
            .as_object_mut()
            .unwrap()
            .remove("pipeline_lock_blake3");
        assert!(lock.is_some(), "the manifest records its lock");
        manifest
    };
    for ((name, a), (_, b)) in built.iter().zip(&reference) {
        if name == "manifest.json" {
            assert_eq!(without_lock(a), without_lock(b));
        } else {
            assert!(
                a == b,
                "{name}: built from the bucket, it differs from the local build"
            );
        }
    }
    built
}

/// The tiny world's DEM and ortho folder put in the bucket `lunar` under `world/`.
fn upload_world(world: &Path) {
    let dem = RemoteDir::open("s3://lunar/world/dem").unwrap();
    dem.put_file("dem.tif", &world.join("dem/dem.tif")).unwrap();
    let orthos = RemoteDir::open("s3://lunar/world/ortho").unwrap();
    for entry in std::fs::read_dir(world.join("ortho")).unwrap().flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        orthos.put_file(&name, &entry.path()).unwrap();
    }
}

/// Inputs in a bucket (the DEM as an object, the orthos as a prefix) publish the bytes the same inputs in local
/// folders publish. A rerun fetches nothing; an object replaced in the bucket is fetched again and the stages that
/// read it rerun; the copy of a withdrawn ortho is removed; a DEM object that is not there fails in one line naming
/// it, before any stage runs.
#[test]
fn inputs_in_a_bucket_build_the_bytes_local_inputs_build() {
    let (_turn, moto) = moto_for_this_test();
    assert_eq!(moto.request("PUT", "/lunar"), 200);
    let tmp = tempfile::tempdir().unwrap();
    let world = tmp.path().join("world");
    pipeline::synth::generate(&pipeline::synth::config::tiny(), 3, &world, true)
        .expect("tiny world");
    let local = tmp.path().join("local");
    std::fs::create_dir_all(&local).unwrap();
    std::os::unix::fs::symlink(&world, local.join("world")).unwrap();
    let local = tiny_manifest(&local, 1.0, "");
    let out = run_with(&local, &moto, &[]);
    assert!(out.status.success(), "{}", stderr(&out));

    upload_world(&world);
    let ortho_objects = names_under(&world.join("ortho")).len();
    let remote_dir = tmp.path().join("remote");
    std::fs::create_dir_all(&remote_dir).unwrap();
    let remote = remote_dir.join("m.toml");
    let text = pipeline::manifest::tiny_manifest_toml(1, 1.0)
        .replace("\"world/dem/dem.tif\"", "\"s3://lunar/world/dem/dem.tif\"")
        .replace("\"world/ortho\"", "\"s3://lunar/world/ortho/\"");
    std::fs::write(&remote, &text).unwrap();
    // Before any run, status says what is missing and how it arrives.
    let status = Command::new(env!("CARGO_BIN_EXE_g2r-pipeline"))
        .arg("status")
        .arg(&remote)
        .output()
        .unwrap();
    assert!(
        !status.status.success() && error_line(&status).contains("not fetched yet"),
        "{}",
        stderr(&status)
    );

    succeeds_saying(
        &run_with(&remote, &moto, &[]),
        &format!("objects={}", ortho_objects + 1),
    );
    let reference = same_dataset_but_the_lock(&remote, &local);
    // The lock says what the build read: the objects, by URL.
    let lock = std::fs::read_to_string(remote_dir.join("out/pipeline.lock.json")).unwrap();
    let first_ortho = &names_under(&world.join("ortho"))[0];
    assert!(
        lock.contains("\"s3://lunar/world/dem/dem.tif\"")
            && lock.contains(&format!("\"s3://lunar/world/ortho/{first_ortho}\""))
            && !lock.contains("out/inputs"),
        "{lock}"
    );
    let rerun = run_with(&remote, &moto, &[]);
    succeeds_saying(&rerun, "objects=0");
    assert!(stderr(&rerun).contains(&format!("current={}", ortho_objects + 1)));

    // Withdraw one ortho (its metadata and image): both copies go, and the stages rerun without it.
    let orthos = RemoteDir::open("s3://lunar/world/ortho").unwrap();
    let (names, _): (Vec<String>, Vec<_>) = orthos.list().unwrap().into_iter().unzip();
    let metadata = names.iter().find(|n| n.ends_with(".json")).unwrap().clone();
    let meta: serde_json::Value = serde_json::from_slice(&orthos.get(&metadata).unwrap()).unwrap();
    let image = meta["image_file"].as_str().unwrap().to_string();
    orthos.delete(&metadata).unwrap();
    orthos.delete(&image).unwrap();
    let out = run_with(&remote, &moto, &[]);
    succeeds_saying(&out, "removed=2");
    let copies = remote_dir.join("out/inputs/ortho");
    assert!(!copies.join(&metadata).exists() && !copies.join(&image).exists());
    assert!(
        stderr(&out).contains("ingest"),
        "the stages rerun without the withdrawn ortho: {}",
        stderr(&out)
    );
    // Put it back with the same bytes: fetched again, and the build is the local one's again.
    orthos
        .put_file(&metadata, &world.join("ortho").join(&metadata))
        .unwrap();
    orthos
        .put_file(&image, &world.join("ortho").join(&image))
        .unwrap();
    succeeds_saying(&run_with(&remote, &moto, &[]), "objects=2");
    assert_eq!(dataset_files(&remote), reference);

    let missing = remote_dir.join("missing.toml");
    std::fs::write(
        &missing,
        text.replace("dem/dem.tif", "dem/nothing.tif")
            .replace("dir = \"out\"", "dir = \"out-missing\""),
    )
    .unwrap();
    let error = error_line(&run_with(&missing, &moto, &[]));
    assert!(
        error.contains("s3://lunar/world/dem/nothing.tif") && error.contains("inputs.dem"),
        "{error}"
    );
    assert!(!remote_dir.join("out-missing/stages").exists());
}

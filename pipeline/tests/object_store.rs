//! `[output] publish_to = "s3://…"`: the pipeline copies the dataset it built to object storage, byte for byte, with
//! the manifest last; a rerun with nothing stale finds it there and copies nothing; a bucket that refuses the write
//! fails in one line and keeps the build's run record, and a rerun once the bucket exists publishes the same bytes; a prefix
//! that holds another dataset is refused. Against an S3 server on 127.0.0.1 (moto, started on a free loopback
//! port and stopped by PID; `.ci/setup` installs `moto[server]` into .venv).

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use dataset::storage::RemoteDir;
use dataset::testing::s3::Moto;

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
    let manifest = dir.join("m.toml");
    let text = pipeline::manifest::tiny_manifest_toml(1, 1.0).replace(
        "dir = \"out\"",
        &format!("dir = \"out\"\npublish_to = \"{url}\""),
    );
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

/// Every file of the local dataset, and the same names read from `url`.
fn local_and_remote(dataset: &Path, url: &str) -> Vec<(String, Vec<u8>, Vec<u8>)> {
    let remote = RemoteDir::open(url).unwrap();
    let mut names: Vec<String> = std::fs::read_dir(dataset)
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
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
    let moto = Moto::start();
    for (key, value) in moto.env() {
        std::env::set_var(key, value);
    }
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
fn publish_to_must_name_object_storage() {
    let tmp = tempfile::tempdir().unwrap();
    let manifest = tmp.path().join("m.toml");
    let text = pipeline::manifest::tiny_manifest_toml(1, 1.0).replace(
        "dir = \"out\"",
        "dir = \"out\"\npublish_to = \"copies/tiny\"",
    );
    std::fs::write(&manifest, text).unwrap();
    let error = format!(
        "{:#}",
        pipeline::manifest::PipelineManifest::load(&manifest).unwrap_err()
    );
    assert!(
        error.contains("m.toml") && error.contains("output.publish_to") && error.contains("s3://"),
        "{error}"
    );
}

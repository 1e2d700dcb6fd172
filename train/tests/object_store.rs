//! Datasets in object storage, against an S3 server on 127.0.0.1 (moto, started on a free loopback port and stopped
//! by PID; `.ci/setup` installs `moto[server]` into .venv):
//! - a published dataset uploaded, verified there, and a short `g2r-train fit --data s3://…` whose `metrics.jsonl`
//!   equals the local-folder run's byte for byte; a second upload to the same prefix is refused (the manifest is a
//!   conditional put), and an upload the bucket refuses leaves no manifest and succeeds when run again;
//! - a network that fails mid-transfer, through a proxy that cuts connections at a chosen byte
//!   ([`dataset::testing::s3::CuttingProxy`]): a link that drops once, mid-upload or mid-shard during `fit`, is
//!   retried (a GET resumes from the byte it reached) and gives the same bytes as a healthy link; a link that keeps
//!   dropping ends in a one-line error naming the object, with no manifest published, and a rerun on a healthy link
//!   gives the same bytes as if nothing had failed. Retries are bounded through `G2R_STORE_MAX_RETRIES` and
//!   `G2R_STORE_RETRY_TIMEOUT_S`, so a lasting fault fails in seconds, not object_store's default three minutes.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::Mutex;

use dataset::storage::{upload_dataset, verify_remote, RemoteDir};
use dataset::testing::s3::{CuttingProxy, Direction, Moto};

/// Both tests point this process's S3 environment at their own server: one at a time.
static SERIAL: Mutex<()> = Mutex::new(());

/// Retries bounded so a lasting fault fails fast; a single cut is still retried.
const RETRIES: [(&str, &str); 2] = [
    ("G2R_STORE_MAX_RETRIES", "2"),
    ("G2R_STORE_RETRY_TIMEOUT_S", "20"),
];

/// Point this process's S3 settings at `port` (moto or a proxy in front of it).
fn use_endpoint(port: u16) {
    for (key, value) in Moto::env_for(port) {
        std::env::set_var(key, value);
    }
    for (key, value) in RETRIES {
        std::env::set_var(key, value);
    }
}

/// A published dataset of synthetic samples (40 train, 12 val) in `tmp/dataset`.
fn published_dataset(tmp: &Path) -> PathBuf {
    let local = tmp.join("dataset");
    train::testing::write_synthetic_dataset(
        &local,
        train::testing::synthetic_samples(40, 5),
        train::testing::synthetic_samples(12, 6),
    );
    local
}

/// A short fit from `data` (a folder or a URL) with S3 at `endpoint_port`.
fn fit(data: &str, out: &Path, endpoint_port: u16) -> Output {
    Command::new(env!("CARGO_BIN_EXE_g2r-train"))
        .args(["fit", "--data", data, "--out"])
        .arg(out)
        .args([
            "--model", "h1", "--width", "4", "--batch", "4", "--epochs", "2",
        ])
        .args(["--max-train-samples", "16", "--max-val-samples", "8"])
        .args(["--lr", "1e-3", "--lr-schedule", "constant", "--window", "2"])
        .args(["--no-dropout", "--seed", "7"])
        .envs(Moto::env_for(endpoint_port))
        .envs(RETRIES)
        .output()
        .expect("running g2r-train")
}

fn assert_fit(data: &str, out: &Path, endpoint_port: u16) {
    let output = fit(data, out, endpoint_port);
    assert!(
        output.status.success(),
        "fit --data {data}: {}",
        String::from_utf8_lossy(&output.stderr)
    );
}

fn metrics(run: &Path) -> Vec<u8> {
    std::fs::read(run.join("metrics.jsonl")).expect("a finished run has metrics.jsonl")
}

/// Every published file in the bucket equals the local one, byte for byte.
fn assert_same_objects(local: &Path, remote: &RemoteDir) {
    assert_eq!(verify_remote(remote).unwrap(), Vec::<String>::new());
    for entry in std::fs::read_dir(local).unwrap().flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        assert!(
            remote.get(&name).unwrap() == std::fs::read(entry.path()).unwrap(),
            "{name} differs in {}",
            remote.url()
        );
    }
}

#[test]
fn a_dataset_in_s3_verifies_and_trains_to_the_same_metrics_as_local_files() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let local = published_dataset(tmp.path());
    let moto = Moto::start();
    assert_eq!(moto.request("PUT", "/g2r"), 200, "creating the bucket");
    use_endpoint(moto.port);
    let url = "s3://g2r/datasets/synthetic";
    let remote = RemoteDir::open(url).unwrap();
    let uploaded = upload_dataset(&local, &remote).unwrap();
    assert!(uploaded > 0);
    assert_eq!(verify_remote(&remote).unwrap(), Vec::<String>::new());

    // Published once: a second upload to the prefix is refused and changes nothing.
    let again = format!("{:#}", upload_dataset(&local, &remote).unwrap_err());
    assert!(again.contains("already published"), "{again}");
    // The conditional put itself refuses an existing manifest, whoever checked before.
    let conditional = format!(
        "{:#}",
        remote.put_new("manifest.json", b"{}".to_vec()).unwrap_err()
    );
    assert!(conditional.contains("already exists"), "{conditional}");
    assert_eq!(verify_remote(&remote).unwrap(), Vec::<String>::new());

    // A corrupted shard in the bucket is caught.
    let shard = std::fs::read_dir(&local)
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .find(|n| n.starts_with("train-"))
        .unwrap();
    let corrupt = RemoteDir::open("s3://g2r/datasets/corrupt").unwrap();
    upload_dataset(&local, &corrupt).unwrap();
    let mut bytes = std::fs::read(local.join(&shard)).unwrap();
    bytes[100] ^= 0xff;
    corrupt.put(&shard, bytes).unwrap();
    let problems = verify_remote(&corrupt).unwrap();
    assert!(
        problems.len() == 1 && problems[0].contains(&shard) && problems[0].contains("blake3"),
        "{problems:?}"
    );

    // A bucket that does not exist refuses the first write: an error naming it, and no manifest anywhere.
    let missing = RemoteDir::open("s3://no-such-bucket/x").unwrap();
    let refused = format!("{:#}", upload_dataset(&local, &missing).unwrap_err());
    assert!(refused.contains("s3://no-such-bucket/x/"), "{refused}");
    assert!(missing.size("manifest.json").is_err());
    // Once the bucket exists, uploading again publishes it whole.
    assert_eq!(moto.request("PUT", "/no-such-bucket"), 200);
    upload_dataset(&local, &missing).unwrap();
    assert_eq!(verify_remote(&missing).unwrap(), Vec::<String>::new());

    // The same fit from local files and from the bucket.
    assert_fit(
        local.to_str().unwrap(),
        &tmp.path().join("run-local"),
        moto.port,
    );
    assert_fit(url, &tmp.path().join("run-s3"), moto.port);
    assert!(!metrics(&tmp.path().join("run-local")).is_empty());
    assert!(
        metrics(&tmp.path().join("run-local")) == metrics(&tmp.path().join("run-s3")),
        "metrics.jsonl differs between local files and S3"
    );
}

#[test]
fn a_link_that_drops_mid_transfer_is_retried_or_fails_cleanly_and_a_rerun_gives_the_same_bytes() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let local = published_dataset(tmp.path());
    let largest_shard = std::fs::read_dir(&local)
        .unwrap()
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().ends_with(".parquet"))
        .map(|e| e.metadata().unwrap().len())
        .max()
        .unwrap();
    // Well inside a shard's body, past any request or response that is not one.
    let mid_shard = (largest_shard / 2) as usize;
    assert!(mid_shard > 64 * 1024, "shards of {largest_shard} bytes");
    let moto = Moto::start();
    assert_eq!(moto.request("PUT", "/g2r"), 200, "creating the bucket");

    // An upload over a link that always drops mid-shard: one line naming the object, and no manifest.
    let always = CuttingProxy::start(moto.port, Direction::Requests, mid_shard, usize::MAX);
    use_endpoint(always.port);
    let url = "s3://g2r/faults/always";
    let error = format!(
        "{:#}",
        upload_dataset(&local, &RemoteDir::open(url).unwrap()).unwrap_err()
    );
    assert!(always.cuts() > 0, "the proxy never cut a connection");
    eprintln!("upload over a dropping link: {error}");
    assert!(
        error.contains(url) && error.contains(".parquet") && !error.contains('\n'),
        "{error}"
    );
    use_endpoint(moto.port);
    let healthy = RemoteDir::open(url).unwrap();
    assert!(
        healthy.size("manifest.json").is_err(),
        "a failed upload left a manifest: readers would see a dataset"
    );
    // The rerun on a healthy link publishes it whole.
    upload_dataset(&local, &healthy).unwrap();
    assert_same_objects(&local, &healthy);

    // An upload over a link that drops once: retried, published whole.
    let once = CuttingProxy::start(moto.port, Direction::Requests, mid_shard, 1);
    use_endpoint(once.port);
    let url_once = "s3://g2r/faults/once";
    upload_dataset(&local, &RemoteDir::open(url_once).unwrap()).unwrap();
    assert_eq!(once.cuts(), 1);
    use_endpoint(moto.port);
    assert_same_objects(&local, &RemoteDir::open(url_once).unwrap());

    // Training from the bucket over a link that drops once mid-shard: the same metrics as from local files.
    assert_fit(
        local.to_str().unwrap(),
        &tmp.path().join("run-local"),
        moto.port,
    );
    let once = CuttingProxy::start(moto.port, Direction::Responses, mid_shard, 1);
    assert_fit(url, &tmp.path().join("run-once"), once.port);
    assert_eq!(once.cuts(), 1, "the read was not cut");
    assert!(
        metrics(&tmp.path().join("run-once")) == metrics(&tmp.path().join("run-local")),
        "metrics.jsonl after a resumed read differs from the local-file run"
    );

    // Over a link that drops every connection after an eighth of a shard: each retry resumes the read where the
    // last stopped, so it still makes progress, but not enough within two retries. A non-zero exit with one line
    // naming the shard; the rerun on a healthy link trains to the same metrics.
    let always = CuttingProxy::start(moto.port, Direction::Responses, mid_shard / 4, usize::MAX);
    let output = fit(url, &tmp.path().join("run-always"), always.port);
    assert!(
        !output.status.success(),
        "fit succeeded over a link that always drops"
    );
    let stderr = String::from_utf8_lossy(&output.stderr);
    let last = stderr.lines().last().unwrap_or_default();
    eprintln!("fit over a dropping link: {last}");
    assert!(
        last.contains(url)
            && last.contains(".parquet")
            && last.contains("the network or the store failed"),
        "the error does not name the shard and the cause: {stderr}"
    );
    assert_fit(url, &tmp.path().join("run-rerun"), moto.port);
    assert!(metrics(&tmp.path().join("run-rerun")) == metrics(&tmp.path().join("run-local")));
}

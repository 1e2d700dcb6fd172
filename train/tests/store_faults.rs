//! A network that fails mid-transfer, between this project and an S3 server on 127.0.0.1 (moto), through a proxy
//! that cuts connections at a chosen byte ([`dataset::testing::s3::CuttingProxy`]):
//! - a link that drops once, mid-upload or mid-shard during `fit --data s3://…`: object_store retries (a GET resumes
//!   from the byte it reached), and the result is the same bytes as on a healthy link;
//! - a link that keeps dropping: a one-line error naming the object, no manifest published (a reader sees no
//!   dataset), and a rerun on a healthy link gives the same bytes as if nothing had failed.
//!
//! Retries are bounded through `G2R_STORE_MAX_RETRIES` and `G2R_STORE_RETRY_TIMEOUT_S` so that a lasting fault
//! fails in seconds, not object_store's default three minutes. Needs `moto[server]` (`.ci/setup`).

use std::path::Path;
use std::process::{Command, Output};

use dataset::storage::{upload_dataset, verify_remote, RemoteDir};
use dataset::testing::s3::{CuttingProxy, Direction, Moto};

/// Retries bounded so a lasting fault fails fast; a single cut is still retried.
const RETRIES: [(&str, &str); 2] = [
    ("G2R_STORE_MAX_RETRIES", "2"),
    ("G2R_STORE_RETRY_TIMEOUT_S", "20"),
];

/// Point this process's S3 settings at `port` (moto or a proxy in front of it). The only test in this binary: the
/// process environment is this test's.
fn use_endpoint(port: u16) {
    for (key, value) in Moto::env_for(port) {
        std::env::set_var(key, value);
    }
    for (key, value) in RETRIES {
        std::env::set_var(key, value);
    }
}

fn fit(data: &str, out: &Path, endpoint_port: u16) -> Output {
    Command::new(env!("CARGO_BIN_EXE_g2r-train"))
        .args(["fit", "--data", data, "--out"])
        .arg(out)
        .args([
            "--model", "h1", "--width", "4", "--batch", "4", "--epochs", "1",
        ])
        .args([
            "--max-train-samples",
            "16",
            "--max-val-samples",
            "8",
            "--lr",
            "1e-3",
        ])
        .args([
            "--lr-schedule",
            "constant",
            "--window",
            "2",
            "--no-dropout",
            "--seed",
            "7",
        ])
        .envs(Moto::env_for(endpoint_port))
        .envs(RETRIES)
        .output()
        .expect("running g2r-train")
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
fn a_link_that_drops_mid_transfer_is_retried_or_fails_cleanly_and_a_rerun_gives_the_same_bytes() {
    let tmp = tempfile::tempdir().unwrap();
    let local = tmp.path().join("dataset");
    train::testing::write_synthetic_dataset(
        &local,
        train::testing::synthetic_samples(40, 5),
        train::testing::synthetic_samples(12, 6),
    );
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
    let output = fit(
        local.to_str().unwrap(),
        &tmp.path().join("run-local"),
        moto.port,
    );
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let once = CuttingProxy::start(moto.port, Direction::Responses, mid_shard, 1);
    let output = fit(url, &tmp.path().join("run-once"), once.port);
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
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
    let output = fit(url, &tmp.path().join("run-rerun"), moto.port);
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    assert!(metrics(&tmp.path().join("run-rerun")) == metrics(&tmp.path().join("run-local")));
}

//! Training straight from object storage: a published dataset uploaded to an S3 server on 127.0.0.1 (moto), verified
//! there, and a short `g2r-train fit --data s3://…` whose `metrics.jsonl` equals the local-folder run's byte for
//! byte. A second upload to the same prefix is refused (the manifest is a conditional put), and an upload the
//! bucket refuses leaves no manifest and succeeds when run again.
//!
//! Needs `moto[server]` in the project's Python (`.ci/setup` installs it into .venv). The server is started on a free
//! loopback port and stopped by PID.

use std::path::Path;
use std::process::Command;

use dataset::storage::{upload_dataset, verify_remote, RemoteDir};
use dataset::testing::s3::Moto;

fn fit(data: &str, out: &Path, env: &[(&'static str, String)]) {
    let output = Command::new(env!("CARGO_BIN_EXE_g2r-train"))
        .args(["fit", "--data", data, "--out"])
        .arg(out)
        .args([
            "--model",
            "h1",
            "--width",
            "4",
            "--batch",
            "4",
            "--epochs",
            "2",
            "--max-train-samples",
            "16",
            "--max-val-samples",
            "8",
            "--lr",
            "1e-3",
            "--lr-schedule",
            "constant",
            "--window",
            "2",
            "--no-dropout",
            "--seed",
            "7",
        ])
        .envs(env.iter().map(|(k, v)| (*k, v.as_str())))
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "fit --data {data}: {}",
        String::from_utf8_lossy(&output.stderr)
    );
}

#[test]
fn a_dataset_in_s3_verifies_and_trains_to_the_same_metrics_as_local_files() {
    let tmp = tempfile::tempdir().unwrap();
    let local = tmp.path().join("dataset");
    train::testing::write_synthetic_dataset(
        &local,
        train::testing::synthetic_samples(40, 5),
        train::testing::synthetic_samples(12, 6),
    );

    let moto = Moto::start();
    assert_eq!(moto.request("PUT", "/g2r"), 200, "creating the bucket");
    // The only test in this binary: the process environment is this test's.
    for (key, value) in moto.env() {
        std::env::set_var(key, value);
    }
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
    let env = moto.env();
    fit(local.to_str().unwrap(), &tmp.path().join("run-local"), &env);
    fit(url, &tmp.path().join("run-s3"), &env);
    let metrics = |run: &str| std::fs::read(tmp.path().join(run).join("metrics.jsonl")).unwrap();
    assert!(!metrics("run-local").is_empty());
    assert!(
        metrics("run-local") == metrics("run-s3"),
        "metrics.jsonl differs between local files and S3"
    );
}

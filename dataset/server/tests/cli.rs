//! `g2r-dataset` contract: help, schema listing, verification failures exit non-zero naming the file.

use std::process::Command;

fn dataset_cli() -> Command {
    Command::new(env!("CARGO_BIN_EXE_g2r-dataset"))
}

#[test]
fn help_and_schema() {
    let out = dataset_cli().arg("--help").output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    for word in [
        "schema",
        "inspect",
        "verify",
        "publish",
        "serve",
        "load-test",
    ] {
        assert!(text.contains(word), "{text}");
    }
    let out = dataset_cli().arg("schema").output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success());
    for column in [
        "`dem`",
        "`image`",
        "`valid`",
        "`sun_lit`",
        "`sun_dir_enu`",
        "`camera_pos_enu`",
    ] {
        assert!(text.contains(column), "schema lacks {column}");
    }
}

#[test]
fn verify_without_manifest_fails_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let out = dataset_cli()
        .arg("verify")
        .arg(dir.path())
        .output()
        .unwrap();
    assert_ne!(out.status.code(), Some(0));
    assert!(String::from_utf8_lossy(&out.stderr).contains("manifest.json"));
}

/// A one-shard dataset in `dir/dataset`.
fn small_dataset(root: &std::path::Path) -> std::path::PathBuf {
    let dir = root.join("dataset");
    let rows: Vec<_> = (0..5).map(dataset::testing::synthetic_sample).collect();
    let split = serde_json::json!({ "dropped_straddling_splits": 2, "tile_size_m": 2560.0, "guard_band_m": 0.0 });
    dataset::testing::write_dataset(&dir, "cli-fixture", &[("train", vec![rows])], split).unwrap();
    dir
}

#[test]
fn publish_rewrites_card_and_croissant_only_when_every_shard_verifies() {
    let root = tempfile::tempdir().unwrap();
    let dir = small_dataset(root.path());
    let card = std::fs::read_to_string(dir.join("README.md")).unwrap();
    let croissant = std::fs::read(dir.join("croissant.json")).unwrap();
    std::fs::remove_file(dir.join("README.md")).unwrap();
    std::fs::remove_file(dir.join("croissant.json")).unwrap();
    let out = dataset_cli().arg("publish").arg(&dir).output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(
        std::fs::read_to_string(dir.join("README.md")).unwrap(),
        card
    );
    assert_eq!(
        std::fs::read(dir.join("croissant.json")).unwrap(),
        croissant
    );
    assert!(card.contains("2 sampled crops straddling splits were dropped before projection"));

    // A tampered shard: refused, named, and nothing (re)written.
    let shard = dir.join("train-00000-of-00001.parquet");
    let mut bytes = std::fs::read(&shard).unwrap();
    bytes[100] ^= 0xff;
    std::fs::write(&shard, bytes).unwrap();
    std::fs::remove_file(dir.join("README.md")).unwrap();
    let out = dataset_cli().arg("publish").arg(&dir).output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_ne!(out.status.code(), Some(0));
    assert!(
        stderr.contains("train-00000-of-00001.parquet") && stderr.contains("nothing written"),
        "{stderr}"
    );
    assert!(!dir.join("README.md").exists());
    let out = dataset_cli().arg("verify").arg(&dir).output().unwrap();
    assert_ne!(out.status.code(), Some(0));
}

#[test]
fn serve_refuses_a_directory_it_cannot_serve_faithfully() {
    let root = tempfile::tempdir().unwrap();
    let out = dataset_cli()
        .args(["serve", "--addr", "127.0.0.1:0"])
        .arg(root.path())
        .output()
        .unwrap();
    assert_ne!(out.status.code(), Some(0));
    assert!(String::from_utf8_lossy(&out.stderr).contains("no manifest.json"));

    let dir = small_dataset(root.path());
    let shard = dir.join("train-00000-of-00001.parquet");
    let bytes = std::fs::read(&shard).unwrap();
    std::fs::write(&shard, &bytes[..bytes.len() / 2]).unwrap();
    let out = dataset_cli()
        .args(["serve", "--addr", "127.0.0.1:0"])
        .arg(&dir)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_ne!(out.status.code(), Some(0));
    assert!(
        stderr.contains("train-00000-of-00001.parquet") && stderr.contains("re-publish"),
        "{stderr}"
    );
}

//! `g2r-dataset` contract: help, schema listing, verification failures exit non-zero naming the file.

use std::process::Command;

fn dataset_cli() -> Command {
    Command::new(env!("CARGO_BIN_EXE_g2r-dataset"))
}

#[test]
fn help_and_schema() {
    let out = dataset_cli().arg("--help").output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    for word in ["schema", "inspect", "verify"] {
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

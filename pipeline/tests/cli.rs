//! The binary's contract: explanatory --help, one-line errors naming the fix, non-zero exit on bad input.

use std::process::Command;

fn pipeline() -> Command {
    Command::new(env!("CARGO_BIN_EXE_g2r-pipeline"))
}

#[test]
fn help_explains_every_subcommand_and_option() {
    let out = pipeline().arg("--help").output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success() && text.contains("synth"), "{text}");
    let out = pipeline().args(["synth", "--help"]).output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    for word in [
        "--preset",
        "tycho-full",
        "--seed",
        "--out",
        "--force",
        "--config",
        "truth/",
    ] {
        assert!(text.contains(word), "synth --help lacks {word}:\n{text}");
    }
}

#[test]
fn unknown_preset_is_a_one_line_error_with_the_fix() {
    let dir = tempfile::tempdir().unwrap();
    let out = pipeline()
        .args(["synth", "--preset", "mars", "--out"])
        .arg(dir.path().join("w"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    let line = err
        .lines()
        .find(|l| l.starts_with("error:"))
        .expect("an error line");
    assert!(
        line.contains("mars") && line.contains("demo") && line.contains("tycho-full"),
        "{err}"
    );
    assert!(!dir.path().join("w").exists() && !dir.path().join("w.partial").exists());
}

#[test]
fn bad_config_file_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("world.toml");
    std::fs::write(&config, "[world]\nname = \"x\"\n").unwrap();
    let out = pipeline()
        .args(["synth", "--config"])
        .arg(&config)
        .arg("--out")
        .arg(dir.path().join("w"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("world.toml") && err.contains("missing field"),
        "{err}"
    );
    let out = pipeline()
        .args(["synth", "--config"])
        .arg(dir.path().join("nope.toml"))
        .arg("--out")
        .arg(dir.path().join("w"))
        .output()
        .unwrap();
    assert!(String::from_utf8_lossy(&out.stderr).contains("nope.toml"));
}

/// Nonsense partition counts are refused by clap in one line naming the flag, before the manifest is read.
#[test]
fn nonsense_partition_counts_name_the_flag() {
    // `--merge=-2`: clap reads a separate `-2` as a flag, not a value.
    for (args, flag) in [
        (["--merge", "0"], "--merge"),
        (["--merge=-2", "--force=publish"], "--merge"),
        (["--merge", "two"], "--merge"),
        (["--partition", "4/4"], "--partition"),
        (["--partition", "0/0"], "--partition"),
    ] {
        let out = pipeline()
            .args(["run", "no-such-manifest.toml"])
            .args(args)
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(2), "{args:?}");
        let err = String::from_utf8_lossy(&out.stderr);
        let line = err
            .lines()
            .find(|l| l.starts_with("error:"))
            .expect("an error line");
        assert!(line.contains(flag), "{args:?}: {err}");
        assert!(
            !err.contains("no-such-manifest"),
            "{args:?} read the manifest: {err}"
        );
    }
}

//! A replica that fails mid-run (`fit --replicas`, [`train::replicas`]). Its own test binary: the failure
//! leaves this process unable to start another replicated fit, by design.

use std::path::PathBuf;
use std::sync::Arc;

use dataset::contract::schema::Split;
use train::data::{LocalSource, SampleSource};
use train::fit_config::FitConfig;
use train::training::fit_replicated;

mod support;

use support::{config, load, tensors, Ad};

/// A published dataset whose train shards stop reading once `broken_after` exists (a run's first checkpoint).
struct BreaksAfter {
    inner: LocalSource,
    broken_after: PathBuf,
}

impl SampleSource for BreaksAfter {
    fn describe(&self) -> String {
        self.inner.describe()
    }
    fn manifest(&self) -> &dataset::contract::manifest::DatasetManifest {
        self.inner.manifest()
    }
    fn row_groups(
        &self,
        split: Split,
    ) -> anyhow::Result<Vec<dataset::contract::planner::RowGroupRef>> {
        self.inner.row_groups(split)
    }
    fn read_row_group(
        &self,
        group: &dataset::contract::planner::RowGroupRef,
    ) -> anyhow::Result<Vec<dataset::contract::schema::Sample>> {
        if group.shard.contains("train") && self.broken_after.exists() {
            anyhow::bail!("{}: disk gone (injected)", group.shard);
        }
        self.inner.read_row_group(group)
    }
}

/// A replica that fails mid-run ends the fit with an error naming it, and the process starts no other
/// replicated fit (its waiting replicas could reach the next one's all-reduce); the checkpoint before stays
/// whole, and `g2r-train fit --resume` in a new process ends with the network of a run that never failed, bit
/// for bit.
#[test]
fn a_failing_replica_ends_the_fit_with_its_error_and_a_resume_ends_as_an_unbroken_run() {
    let tmp = tempfile::tempdir().unwrap();
    let local = train::testing::synthetic_source(tmp.path(), 300, 4);
    let cfg = FitConfig {
        epochs: 2,
        ..config()
    };
    let device = Default::default();
    let two = [device, device];
    let unbroken = tmp.path().join("unbroken");
    fit_replicated::<Ad>(local.clone(), &cfg, &unbroken, false, None, &two, false).unwrap();

    let run = tmp.path().join("run");
    let breaking: Arc<dyn SampleSource> = Arc::new(BreaksAfter {
        inner: LocalSource::open(tmp.path()).unwrap(),
        broken_after: run.join("last"),
    });
    let err = fit_replicated::<Ad>(breaking, &cfg, &run, false, None, &two, false).unwrap_err();
    let text = format!("{err:#}");
    assert!(
        text.contains("replica") && text.contains("of 2") && text.contains("disk gone"),
        "{text}"
    );
    let cursor: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("last/cursor.json")).unwrap())
            .unwrap();
    assert_eq!(
        cursor["epoch"], 1,
        "the checkpoint of epoch 0 is the last one"
    );
    let again = fit_replicated::<Ad>(local, &cfg, &run, true, None, &two, false)
        .unwrap_err()
        .to_string();
    assert!(again.contains("start a new process"), "{again}");

    // The same run's flags, resumed by the binary.
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_g2r-train"))
        .args(["fit", "--data"])
        .arg(tmp.path())
        .arg("--out")
        .arg(&run)
        .args([
            "--model",
            "m2",
            "--width",
            "4",
            "--batch",
            "4",
            "--epochs",
            "2",
            "--max-train-samples",
            "16",
            "--max-val-samples",
            "4",
            "--lr",
            "1e-3",
            "--lr-schedule",
            "constant",
            "--window",
            "2",
            "--no-dropout",
            "--ema",
            "0.9",
            "--seed",
            "5",
            "--replicas",
            "2",
            "--resume",
        ])
        .status()
        .unwrap();
    assert!(status.success());
    let (resumed, whole) = (tensors(&load(&run, &cfg)), tensors(&load(&unbroken, &cfg)));
    let differing: Vec<&str> = resumed
        .iter()
        .zip(&whole)
        .filter(|(a, b)| a.2 != b.2)
        .map(|(a, _)| a.0.as_str())
        .collect();
    assert!(
        differing.is_empty(),
        "{} tensors differ: {differing:?}",
        differing.len()
    );
    assert_eq!(
        std::fs::read_to_string(run.join("metrics.jsonl")).unwrap(),
        std::fs::read_to_string(unbroken.join("metrics.jsonl")).unwrap()
    );
}

//! What each `g2r-pipeline` command does once its arguments are parsed: choose the runner for the scope (whole,
//! one partition, or the merge of N), run it, write the run record; report status; clean; resolve a world config.
//! The binary only parses and dispatches, so every command is a library call a test or another tool can make.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};

use crate::manifest::PipelineManifest;
use crate::partition::{self, Partition};
use crate::runner::{self, StageRun};
use crate::stages::{self, Scope};
use crate::synth::{config, WorldConfig};

/// What `run` does: the whole pipeline, one partition of it, or the merge of N finished partitions and publish.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RunScope {
    Whole,
    Partition(Partition),
    Merge(usize),
}

/// The stages a `run` ran, with their times, and where its run record went (None when everything was up to date).
#[derive(Debug)]
pub struct RunOutcome {
    pub stages: Vec<StageRun>,
    pub seconds: f64,
    pub record: Option<PathBuf>,
    /// The files hashed to check and record the stages (at least once each; more often is wasted reading).
    pub hashing: runner::HashStats,
    /// What fetching the inputs given as URLs copied (all zero for local inputs).
    pub inputs: crate::inputs::Fetched,
}

/// Run the stale stages of `manifest` in `scope` (up to `until`, re-running `force` and what follows), and write
/// what was measured to `run-record.json` beside the outputs (the partition's directory for a partition), never
/// inside the dataset.
pub fn run(
    manifest: &PipelineManifest,
    scope: RunScope,
    until: Option<&str>,
    force: &[&str],
    progress: indicatif::ProgressBar,
) -> Result<RunOutcome> {
    if matches!(scope, RunScope::Partition(_)) && until == Some("publish") {
        bail!(
            "--until publish: a partition stops after project; publish with --merge N once every partition is done"
        );
    }
    let started = Instant::now();
    let inputs = crate::inputs::fetch(manifest)?;
    if !crate::inputs::urls(manifest).is_empty() {
        tracing::info!(
            objects = inputs.objects,
            bytes = inputs.bytes,
            removed = inputs.removed,
            current = inputs.current,
            "inputs fetched"
        );
    }
    let (runner, merged_seconds) = match scope {
        RunScope::Partition(part) => (
            stages::pipeline_scoped(manifest, Scope::Partition(part), progress)?,
            None,
        ),
        RunScope::Merge(count) => {
            let memo = std::sync::Arc::new(runner::HashMemo::for_one_command());
            if let Some(url) = &manifest.output.exchange {
                fetch_partitions(manifest, count, url, &memo)?;
            }
            let runner = stages::merge::merge(manifest, count, memo, progress)?;
            let seconds = started.elapsed().as_secs_f64();
            tracing::info!(
                partitions = count,
                seconds = format!("{seconds:.1}"),
                "partitions merged"
            );
            (runner, Some(seconds))
        }
        RunScope::Whole => (stages::pipeline(manifest, progress)?, None),
    };
    let mut ran = runner.run_timed(until, force)?;
    if let Some(seconds) = merged_seconds {
        ran.insert(
            0,
            StageRun {
                name: "merge",
                seconds,
                peak_rss_mib: runner::peak_rss_mib(),
            },
        );
    }
    // The copy to object storage comes after the run record: a refused copy keeps the build's timings, and the
    // rerun that retries it finds every stage up to date.
    let publishes =
        !matches!(scope, RunScope::Partition(_)) && matches!(until, None | Some("publish"));
    // A partition that reached its last stage goes to the exchange (when the manifest names one) after its run
    // record, which travels with it; a rerun with nothing stale retries only the copy.
    let exchange = match (scope, &manifest.output.exchange) {
        (RunScope::Partition(part), Some(url)) if matches!(until, None | Some("project")) => {
            Some((part, url))
        }
        _ => None,
    };
    let copy = || -> Result<()> {
        if let (true, Some(url)) = (publishes, &manifest.output.publish_to) {
            copy_to_object_storage(manifest, url)?;
        }
        if let Some((part, url)) = exchange {
            send_partition(manifest, part, url, &runner.hash_memo)?;
        }
        Ok(())
    };
    let seconds = started.elapsed().as_secs_f64();
    let hashing = runner.hash_memo.stats();
    if ran.is_empty() {
        copy()?;
        return Ok(RunOutcome {
            stages: ran,
            seconds,
            record: None,
            hashing,
            inputs,
        });
    }
    let record_path = match scope {
        RunScope::Partition(part) => partition::dir(manifest, part).join("run-record.json"),
        _ => manifest.out_dir().join("run-record.json"),
    };
    let record = serde_json::json!({
        "stages": ran,
        "seconds": seconds,
        "hashing": hashing,
        "inputs_fetched": inputs,
        "provenance": dataset::provenance::Provenance::capture(),
    });
    dataset::files::write_json_atomic(&record_path, &record)?;
    copy()?;
    Ok(RunOutcome {
        stages: ran,
        seconds,
        record: Some(record_path),
        hashing,
        inputs,
    })
}

/// `status`: one line per stage (up to date, or why not), then one per stray file under the scope's stages/.
pub fn status_lines(
    manifest: &PipelineManifest,
    partition: Option<Partition>,
) -> Result<Vec<String>> {
    let scope = match partition {
        Some(part) => Scope::Partition(part),
        None => Scope::Whole,
    };
    let runner = stages::pipeline_scoped(manifest, scope, indicatif::ProgressBar::hidden())?;
    let mut lines: Vec<String> = runner
        .status()?
        .into_iter()
        .map(|(stage, status)| format!("{stage:>8}: {status}"))
        .collect();
    let stage_dir = match partition {
        Some(part) => partition::dir(manifest, part).join("stages"),
        None => manifest.stage_dir(),
    };
    for (path, bytes) in runner.stray_files(&stage_dir)? {
        lines.push(format!(
            "   stray: {} ({bytes} B): no stage of this version writes it; `g2r-pipeline clean` removes it",
            path.display()
        ));
    }
    Ok(lines)
}

/// Copy the published dataset to `url` (`output.publish_to`) unless the same `manifest.json` is there already (its
/// shards, which it lists with their hashes, are then the same bytes; the card and the other documents are not
/// compared). A copy that fails part way leaves no manifest there; running the pipeline again (every stage up to
/// date) retries the copy.
fn copy_to_object_storage(manifest: &PipelineManifest, url: &str) -> Result<()> {
    let dir = manifest.out_dir().join("dataset");
    let remote = dataset::storage::RemoteDir::open(url)?;
    if dataset::storage::holds_dataset(&dir, &remote)? {
        tracing::info!(url, "the dataset is already published there");
        return Ok(());
    }
    let started = Instant::now();
    let bytes = dataset::storage::upload_dataset(&dir, &remote)?;
    tracing::info!(
        url,
        mib = bytes >> 20,
        seconds = format!("{:.1}", started.elapsed().as_secs_f64()),
        "dataset copied to object storage"
    );
    Ok(())
}

/// Copy finished partition `part` to the exchange (`output.exchange`), for a merge on another machine.
fn send_partition(
    manifest: &PipelineManifest,
    part: Partition,
    url: &str,
    memo: &runner::HashMemo,
) -> Result<()> {
    let started = Instant::now();
    let bytes = crate::exchange::send(manifest, part, url, memo)?;
    if bytes > 0 {
        tracing::info!(
            partition = %part,
            url = crate::exchange::prefix(url, part),
            mib = bytes >> 20,
            seconds = format!("{:.1}", started.elapsed().as_secs_f64()),
            "partition copied to the exchange"
        );
    }
    Ok(())
}

/// Fetch from the exchange (`output.exchange`) what the merge needs of each of `count` partitions and does not
/// hold already.
fn fetch_partitions(
    manifest: &PipelineManifest,
    count: usize,
    url: &str,
    memo: &runner::HashMemo,
) -> Result<()> {
    let started = Instant::now();
    let mut bytes = 0;
    for index in 0..count {
        bytes += crate::exchange::fetch(manifest, Partition { index, count }, url, memo)?;
    }
    tracing::info!(
        partitions = count,
        url,
        mib = bytes >> 20,
        seconds = format!("{:.1}", started.elapsed().as_secs_f64()),
        "partitions fetched from the exchange"
    );
    Ok(())
}

/// `clean`: remove every stage output, stray files under stages/, the published dataset, the partitions' outputs
/// and the lock. Returns how many stage files were removed.
pub fn clean(manifest: &PipelineManifest) -> Result<usize> {
    let runner = stages::pipeline(manifest, indicatif::ProgressBar::hidden())?;
    let mut removed = runner.clean()?;
    for (path, _) in runner.stray_files(&manifest.stage_dir())? {
        std::fs::remove_file(&path)
            .with_context(|| format!("{}: cannot remove it", path.display()))?;
        removed += 1;
    }
    // Shards are listed by the published manifest, not by the runner: remove them with it. Partitions' outputs
    // too (`run --partition`).
    for dir in [
        manifest.dataset_dir(),
        manifest.out_dir().join("partitions"),
    ] {
        if dir.exists() {
            std::fs::remove_dir_all(&dir)
                .with_context(|| format!("{}: cannot remove it", dir.display()))?;
        }
    }
    Ok(removed)
}

/// The world `synth` builds: the TOML file at `config_path` when given, else the named preset. Errors name the
/// file (or preset) and the line.
pub fn world_config(preset: &str, config_path: Option<&Path>) -> Result<WorldConfig> {
    let (text, source) = match config_path {
        Some(path) => (
            std::fs::read_to_string(path)
                .with_context(|| format!("reading world config {}", path.display()))?,
            path.display().to_string(),
        ),
        None => (
            config::preset(preset)
                .with_context(|| {
                    format!("unknown preset '{preset}': use demo, tycho-full or many-craters, or --config FILE")
                })?
                .to_string(),
            format!("preset {preset}"),
        ),
    };
    WorldConfig::from_toml(&text).map_err(|error| {
        anyhow::anyhow!(
            "{source}: invalid world config: {}",
            crate::manifest::toml_error_line(&text, &error)
        )
    })
}

/// Bytes of the files under `dir` (what `synth` reports having written).
pub fn tree_bytes(dir: &Path) -> u64 {
    dataset::files::files_under(dir)
        .map(|files| files.iter().map(|(_, bytes)| bytes).sum())
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_world_config_error_names_its_source() {
        let unknown = format!("{:#}", world_config("mars", None).unwrap_err());
        assert!(
            unknown.contains("'mars'") && unknown.contains("--config"),
            "{unknown}"
        );
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("world.toml");
        std::fs::write(&path, "not = [toml").unwrap();
        let bad = format!("{:#}", world_config("demo", Some(&path)).unwrap_err());
        assert!(
            bad.contains("world.toml") && bad.contains("invalid world config"),
            "{bad}"
        );
        for preset in ["demo", "tycho-full", "many-craters"] {
            let world = world_config(preset, None).unwrap();
            world.validate().unwrap();
        }
    }

    #[test]
    fn tree_bytes_sums_nested_files() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir(dir.path().join("a")).unwrap();
        std::fs::write(dir.path().join("x"), [0u8; 3]).unwrap();
        std::fs::write(dir.path().join("a/y"), [0u8; 5]).unwrap();
        assert_eq!(tree_bytes(dir.path()), 8);
        assert_eq!(tree_bytes(&dir.path().join("missing")), 0);
    }
}

//! The reduce of a partitioned build ([`crate::partition`]): check that every partition is finished, join their
//! outputs into the single-process layout in ortho order, cutting the sample files' row groups where one process
//! would have cut them, and record those stages in the lock as run, so that publish follows as in one process.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context};

use super::project::{Rejection, TrainDemStatistic};
use super::split::SplitSummary;
use super::{pipeline, pipeline_scoped, row_group_rows, Layout, Scope};
use crate::manifest::PipelineManifest;
use crate::partition::{dir, Partition};
use crate::runner::{HashMemo, Runner, Staleness};
use dataset::contract::shard::{EncodedRowGroups, ShardFile, ShardWriter};
use dataset::files::write_json_atomic;

/// The reduce: check that every partition of `count` is finished, join their outputs into the single-process
/// layout, record those stages in the manifest's lock as run, and return the single-process runner, whose `run`
/// then publishes. A missing or unfinished partition is an error naming it, and nothing is published.
///
/// `memo` is the command's ([`HashMemo::for_one_command`]), shared by every runner here and the one returned:
/// every partition checks the same DEM, and adopt and the publish run check the images and the merged outputs
/// again, and each file is read once.
pub fn merge(
    manifest: &PipelineManifest,
    count: usize,
    memo: std::sync::Arc<HashMemo>,
    progress: indicatif::ProgressBar,
) -> anyhow::Result<Runner<'static>> {
    let mut parts = Vec::with_capacity(count);
    for index in 0..count {
        let part = Partition { index, count };
        let mut runner = pipeline_scoped(
            manifest,
            Scope::Partition(part),
            indicatif::ProgressBar::hidden(),
        )?;
        runner.hash_memo = memo.clone();
        if let Some((stage, why)) = runner
            .status()?
            .into_iter()
            .find(|(_, status)| *status != Staleness::UpToDate)
        {
            bail!(
                "partition {part} is not finished ({stage}: {why}); run it again (`g2r-pipeline run MANIFEST --partition {part}`), then merge",
            );
        }
        parts.push(Layout::at(
            &dir(manifest, part).join("stages"),
            manifest.dataset_dir(),
        ));
    }
    let whole = Layout::of(manifest);
    let tables = |pick: fn(&Layout) -> &PathBuf| -> anyhow::Result<()> {
        let inputs: Vec<PathBuf> = parts.iter().map(|p| pick(p).clone()).collect();
        write_via_tmp(pick(&whole), |tmp| {
            super::table::concat_tables(&inputs, tmp)
        })
    };
    tables(|l| &l.orthos)?;
    tables(|l| &l.runs)?;
    tables(|l| &l.positions)?;
    tables(|l| &l.assignment)?;

    let summaries: Vec<SplitSummary> = parts
        .iter()
        .map(|p| read_json(&p.split_summary))
        .collect::<anyhow::Result<_>>()?;
    let first = summaries[0].clone();
    let summary = SplitSummary {
        dropped_straddling_splits: summaries.iter().map(|s| s.dropped_straddling_splits).sum(),
        ..first
    };
    write_json(&whole.split_summary, &summary)?;

    let group_rows = row_group_rows(manifest.publish.rows_per_shard);
    for (k, merged) in whole.split_samples.iter().enumerate() {
        progress.set_message(format!("merging {}", merged.display()));
        let inputs: Vec<&Path> = parts.iter().map(|p| p.split_samples[k].as_path()).collect();
        merge_samples(&inputs, group_rows, merged)?;
    }
    let mut rejections =
        std::collections::BTreeMap::<String, std::collections::BTreeMap<Rejection, u64>>::new();
    for part in &parts {
        rejections.extend(read_json::<std::collections::BTreeMap<_, _>>(
            &part.rejections,
        )?);
    }
    write_json(&whole.rejections, &rejections)?;
    let statistics = parts
        .iter()
        .map(|p| read_json::<TrainDemStatistic>(&p.train_dem))
        .collect::<anyhow::Result<Vec<_>>>()?;
    write_json(&whole.train_dem, &TrainDemStatistic::concat(statistics))?;

    let mut runner = pipeline(manifest, progress)?;
    runner.hash_memo = memo;
    runner.adopt(&["ingest", "erode", "sample", "split", "project"])?;
    Ok(runner)
}

/// Join sample files (consecutive parts of one split's rows) into one with row groups of `group_rows`, cut where
/// one process writing all the rows would cut them. Row groups that fall whole and aligned are copied as encoded;
/// the rows after a part whose last group was short are decoded and re-encoded.
pub fn merge_samples(parts: &[&Path], group_rows: usize, out: &Path) -> anyhow::Result<usize> {
    if let Some(parent) = out.parent() {
        std::fs::create_dir_all(parent)?;
    }
    let mut writer = ShardWriter::create_unhashed(out)?.with_row_group_rows(group_rows);
    for part in parts {
        let encoded = EncodedRowGroups::open(part)?;
        let file = ShardFile::open(part)?;
        for (group, rows) in encoded.row_group_sizes().into_iter().enumerate() {
            if writer.buffered_rows() == 0 && rows == group_rows {
                writer.append_encoded_row_group(&encoded, group)?;
            } else {
                for batch in file.read_batches(group, None, true)? {
                    writer.write_batch(&batch)?;
                }
            }
        }
    }
    Ok(writer.close()?)
}

/// Write `path` through its temporary name, so a merge killed midway leaves no finished-looking table.
fn write_via_tmp(
    path: &Path,
    write: impl FnOnce(&Path) -> anyhow::Result<()>,
) -> anyhow::Result<()> {
    if let Some(parent) = path.parent() {
        std::fs::create_dir_all(parent)?;
    }
    dataset::files::write_atomic(path, write)
        .with_context(|| format!("{}: cannot move into place", path.display()))
}

fn write_json<T: serde::Serialize>(path: &Path, value: &T) -> anyhow::Result<()> {
    if let Some(parent) = path.parent() {
        std::fs::create_dir_all(parent)?;
    }
    write_json_atomic(path, value).with_context(|| format!("{}: cannot write", path.display()))
}

fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> anyhow::Result<T> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("{}: cannot read", path.display()))?;
    serde_json::from_str(&text).with_context(|| {
        format!(
            "{}: not what the stage writes; rerun the partition",
            path.display()
        )
    })
}

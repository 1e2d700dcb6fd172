//! Partitions on machines that share no file system (a cloud batch queue, a cluster without shared scratch): with
//! `[output] exchange = "s3://…"` in the manifest, each finished partition copies its directory (stage outputs,
//! lock, run record) to `EXCHANGE/partitions/N/I/`, and the merge fetches from there whatever it does not already
//! hold. The object store is the shared file system; the merge itself is unchanged.
//!
//! A partition's copy ends with [`MARKER`] (every file's size and blake3), written last and removed first when a
//! rerun replaces the copy: the merge takes only a partition whose marker is there, and checks every file it
//! fetches against it, so it never merges half of one copy and half of another.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};

use crate::manifest::PipelineManifest;
use crate::partition::{self, Partition};
use crate::runner::HashMemo;
use dataset::files::tmp_path;
use dataset::storage::RemoteDir;

/// The last object of a partition's copy: what it holds.
pub const MARKER: &str = "complete.json";

/// Every file of a partition's directory, by path relative to it (`/`-separated).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
struct Listing {
    files: BTreeMap<String, FileEntry>,
}

#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
struct FileEntry {
    bytes: u64,
    blake3: String,
}

/// Where partition `part`'s copy lives under the exchange prefix `url`.
pub fn prefix(url: &str, part: Partition) -> String {
    format!(
        "{}/partitions/{}/{}",
        url.trim_end_matches('/'),
        part.count,
        part.index
    )
}

/// The files under `dir`, relative (`/`-separated) and sorted, leaving out unfinished `*.tmp` outputs.
fn finished_files_under(dir: &Path) -> Result<Vec<String>> {
    Ok(dataset::files::files_under(dir)?
        .into_iter()
        .filter(|(path, _)| path.extension().is_none_or(|e| e != "tmp"))
        .map(|(path, _)| {
            let relative = path.strip_prefix(dir).expect("listed under dir");
            relative
                .components()
                .map(|c| c.as_os_str().to_string_lossy().into_owned())
                .collect::<Vec<_>>()
                .join("/")
        })
        .collect())
}

/// Copy finished partition `part` to the exchange `url`: every file, then [`MARKER`] last. A copy already there
/// with the same marker is left as it is; another one loses its marker first, then is replaced. Returns the bytes
/// copied (0 when the copy was there). Hashes come from `memo`, the partition runner's, which holds its outputs'.
pub fn send(
    manifest: &PipelineManifest,
    part: Partition,
    url: &str,
    memo: &HashMemo,
) -> Result<u64> {
    let dir = partition::dir(manifest, part);
    let mut listing = Listing {
        files: BTreeMap::new(),
    };
    for name in finished_files_under(&dir)? {
        let path = dir.join(&name);
        let bytes = std::fs::metadata(&path)?.len();
        let blake3 = memo
            .hash(&path)
            .with_context(|| format!("{}: cannot read", path.display()))?;
        listing.files.insert(name, FileEntry { bytes, blake3 });
    }
    let marker = serde_json::to_vec_pretty(&listing)?;
    let remote = RemoteDir::open(&prefix(url, part))?;
    if remote.get_if_exists(MARKER)?.as_deref() == Some(&marker[..]) {
        tracing::info!(url = remote.url(), "partition already in the exchange");
        return Ok(0);
    }
    remote.delete(MARKER)?;
    let mut copied = 0;
    for name in listing.files.keys() {
        copied += remote.put_file(name, &dir.join(name))?;
    }
    remote.put(MARKER, marker)?;
    Ok(copied)
}

/// Make partition `part`'s directory hold its copy in the exchange `url`: each file the marker lists is fetched
/// unless the local one has its size and blake3, checked as it arrives, and renamed into place. A partition with
/// no marker there has not finished (or is being replaced): an error naming it, and nothing is merged.
/// Returns the bytes fetched. `memo` is the merge's: what is checked or fetched here is not read again there.
pub fn fetch(
    manifest: &PipelineManifest,
    part: Partition,
    url: &str,
    memo: &HashMemo,
) -> Result<u64> {
    let remote = RemoteDir::open(&prefix(url, part))?;
    let Some(marker) = remote.get_if_exists(MARKER)? else {
        bail!(
            "partition {part} is not in the exchange ({} is missing); run it (`g2r-pipeline run MANIFEST --partition {part}`), then merge",
            remote.url_of(MARKER)
        );
    };
    let listing: Listing = serde_json::from_slice(&marker)
        .with_context(|| format!("{}: not a partition listing", remote.url_of(MARKER)))?;
    let dir = partition::dir(manifest, part);
    let mut fetched = 0;
    for (name, entry) in &listing.files {
        let path: PathBuf = name.split('/').fold(dir.clone(), |p, c| p.join(c));
        let held = std::fs::metadata(&path).is_ok_and(|m| m.len() == entry.bytes)
            && memo.hash(&path).is_ok_and(|h| h == entry.blake3);
        if held {
            continue;
        }
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent)
                .with_context(|| format!("{}: cannot create", parent.display()))?;
        }
        let tmp = tmp_path(&path);
        let blake3 = remote.get_to_file(name, entry.bytes, &tmp)?;
        if blake3 != entry.blake3 {
            let _ = std::fs::remove_file(&tmp);
            bail!(
                "{}: its bytes are not the ones {MARKER} lists (is partition {part} being rerun?); merge again once it has finished",
                remote.url_of(name)
            );
        }
        std::fs::rename(&tmp, &path)
            .with_context(|| format!("{}: cannot write", path.display()))?;
        memo.remember(&path, blake3)?;
        fetched += entry.bytes;
    }
    Ok(fetched)
}

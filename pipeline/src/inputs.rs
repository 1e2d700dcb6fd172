//! Inputs in object storage: `inputs.dem` may name an object and `inputs.ortho_dir` a prefix (`s3://…`, `file://…`)
//! instead of local paths. Before any stage runs, `run` mirrors them into `OUTPUT/inputs/`: the DEM to
//! `inputs/dem/NAME`, every object directly under the ortho prefix to `inputs/ortho/`. The stages then read the
//! copies as they read local inputs, and the lock hashes their bytes as it hashes any input, so where an input came
//! from never changes a stage's output or makes one stale.
//!
//! Why copies and not GDAL's `/vsis3/`: the stages read the DEM and every ortho many times at random offsets
//! (erosion, sampling, one window per crop), and the lock reads each input whole to hash it; over HTTP each read is
//! a request. One sequential download per object is cheaper, and a node-local copy is what a cluster's scratch
//! disk is for.
//!
//! A rerun lists the prefix again and fetches only objects whose size or entity tag (ETag) changed; the copy of an
//! object no longer there is removed, so a withdrawn ortho does not linger. Each copy's object version is recorded
//! in `inputs/versions/`, written after the copy is in place and removed before it is replaced, so a fetch cut off
//! part way is redone, never trusted. Copies arrive under a name of their own process (`NAME.PID.tmp`) and are
//! renamed into place, so partitions sharing one output folder may fetch at the same time.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use dataset::storage::{is_url, ObjectVersion, RemoteDir};

use crate::manifest::PipelineManifest;

/// What one [`fetch`] did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct Fetched {
    /// Objects copied (new or changed since the last fetch).
    pub objects: usize,
    pub bytes: u64,
    /// Copies removed because their object is no longer under the prefix.
    pub removed: usize,
    /// Objects whose copy was already current.
    pub current: usize,
}

/// The folder the copies of URL inputs go to.
pub fn cache_dir(manifest: &PipelineManifest) -> PathBuf {
    manifest.out_dir().join("inputs")
}

/// The local path the stages read for `inputs.dem`: the file itself, or its copy when the manifest names a URL.
pub fn dem_path(manifest: &PipelineManifest) -> PathBuf {
    let dem = manifest.inputs.dem.to_string_lossy();
    if is_url(&dem) {
        let (_, name) = split_object_url(&dem);
        cache_dir(manifest).join("dem").join(name)
    } else {
        manifest.resolve(&manifest.inputs.dem)
    }
}

/// The local folder the stages read for `inputs.ortho_dir`: the folder itself, or the copy of the prefix.
pub fn ortho_dir(manifest: &PipelineManifest) -> PathBuf {
    if is_url(&manifest.inputs.ortho_dir.to_string_lossy()) {
        cache_dir(manifest).join("ortho")
    } else {
        manifest.resolve(&manifest.inputs.ortho_dir)
    }
}

/// The URL inputs of `manifest`, as (its field, the URL).
pub fn urls(manifest: &PipelineManifest) -> Vec<(&'static str, String)> {
    [
        ("inputs.dem", &manifest.inputs.dem),
        ("inputs.ortho_dir", &manifest.inputs.ortho_dir),
    ]
    .into_iter()
    .map(|(field, location)| (field, location.to_string_lossy().into_owned()))
    .filter(|(_, location)| is_url(location))
    .collect()
}

/// The folders of copies, each with the URL prefix it mirrors (for the lock's keys).
pub fn fetched_from(manifest: &PipelineManifest) -> Vec<(PathBuf, String)> {
    let cache = cache_dir(manifest);
    urls(manifest)
        .into_iter()
        .map(|(field, url)| match field {
            "inputs.dem" => (cache.join("dem"), split_object_url(&url).0.to_string()),
            _ => (cache.join("ortho"), url.trim_end_matches('/').to_string()),
        })
        .collect()
}

/// Bring the copies of `manifest`'s URL inputs up to date (nothing to do for local inputs).
pub fn fetch(manifest: &PipelineManifest) -> Result<Fetched> {
    let mut fetched = Fetched::default();
    let cache = cache_dir(manifest);
    let dem = manifest.inputs.dem.to_string_lossy();
    if is_url(&dem) {
        let (prefix, name) = split_object_url(&dem);
        let remote = RemoteDir::open(prefix)?;
        let version = remote.version(name).with_context(|| {
            format!("inputs.dem = \"{dem}\": check the URL and the AWS_* settings")
        })?;
        let mirror = Mirror::at(&cache, "dem");
        mirror.sync(&remote, &[(name.to_string(), version)], &mut fetched)?;
    }
    let ortho = manifest.inputs.ortho_dir.to_string_lossy();
    if is_url(&ortho) {
        let remote = RemoteDir::open(&ortho)?;
        let objects = remote.list()?;
        anyhow::ensure!(
            !objects.is_empty(),
            "inputs.ortho_dir = \"{ortho}\": no objects directly under this prefix; point it at the folder of orthos and their *.json metadata"
        );
        Mirror::at(&cache, "ortho").sync(&remote, &objects, &mut fetched)?;
    }
    Ok(fetched)
}

/// `s3://bucket/a/b.tif` → (`s3://bucket/a`, `b.tif`).
fn split_object_url(url: &str) -> (&str, &str) {
    let url = url.trim_end_matches('/');
    url.rsplit_once('/').unwrap_or(("", url))
}

/// One mirrored folder: the copies in `inputs/NAME/`, their objects' versions in `inputs/versions/NAME/`.
struct Mirror {
    copies: PathBuf,
    versions: PathBuf,
}

impl Mirror {
    fn at(cache: &Path, name: &str) -> Self {
        Self {
            copies: cache.join(name),
            versions: cache.join("versions").join(name),
        }
    }

    /// Make the copies hold exactly `objects` (names directly under `remote`, with their versions).
    fn sync(
        &self,
        remote: &RemoteDir,
        objects: &[(String, ObjectVersion)],
        fetched: &mut Fetched,
    ) -> Result<()> {
        for dir in [&self.copies, &self.versions] {
            std::fs::create_dir_all(dir)
                .with_context(|| format!("{}: cannot create", dir.display()))?;
        }
        let wanted: std::collections::BTreeSet<&str> =
            objects.iter().map(|(name, _)| name.as_str()).collect();
        for entry in std::fs::read_dir(&self.copies)
            .with_context(|| format!("{}: cannot list", self.copies.display()))?
        {
            let entry = entry?;
            let name = entry.file_name().to_string_lossy().into_owned();
            if !wanted.contains(name.as_str()) && !name.ends_with(".tmp") {
                self.forget(&name)?;
                std::fs::remove_file(entry.path())
                    .with_context(|| format!("{}: cannot remove", entry.path().display()))?;
                fetched.removed += 1;
            }
        }
        for (name, version) in objects {
            let copy = self.copies.join(name);
            if copy.exists() && self.recorded(name).as_ref() == Some(version) {
                fetched.current += 1;
                continue;
            }
            self.forget(name)?;
            let tmp = self
                .copies
                .join(format!("{name}.{}.tmp", std::process::id()));
            let fetch = remote.get_to_file(name, version.bytes, &tmp).and_then(|_| {
                std::fs::rename(&tmp, &copy)
                    .with_context(|| format!("{}: cannot write", copy.display()))
            });
            if let Err(e) = fetch {
                let _ = std::fs::remove_file(&tmp);
                return Err(e.context(format!(
                    "{}: cannot fetch the input; check the link and the AWS_* settings, then run again (copies already made are kept)",
                    remote.url_of(name)
                )));
            }
            let record = serde_json::to_vec(version)?;
            let path = self.version_path(name);
            std::fs::write(&path, record)
                .with_context(|| format!("{}: cannot write", path.display()))?;
            fetched.objects += 1;
            fetched.bytes += version.bytes;
        }
        Ok(())
    }

    fn version_path(&self, name: &str) -> PathBuf {
        self.versions.join(format!("{name}.json"))
    }

    fn recorded(&self, name: &str) -> Option<ObjectVersion> {
        let text = std::fs::read(self.version_path(name)).ok()?;
        serde_json::from_slice(&text).ok()
    }

    fn forget(&self, name: &str) -> Result<()> {
        let path = self.version_path(name);
        match std::fs::remove_file(&path) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                Err(e).with_context(|| format!("{}: cannot remove", path.display()))
            }
            _ => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_object_url_splits_into_its_prefix_and_name() {
        assert_eq!(
            split_object_url("s3://lunar/nac/dtm/dem.tif"),
            ("s3://lunar/nac/dtm", "dem.tif")
        );
        assert_eq!(split_object_url("s3://b/dem.tif/"), ("s3://b", "dem.tif"));
    }
}

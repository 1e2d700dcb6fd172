//! Manifests: what a published dataset (or a generated world) contains, with blake3 checksums of every file.
//!
//! Maps are `BTreeMap`s so serialised manifests never depend on hash-map iteration order.

use std::collections::BTreeMap;
use std::io;
use std::path::{Path, PathBuf};

use crate::contract::catalogue_error::CatalogueError;
use crate::contract::schema::SCHEMA_VERSION;
use crate::files::hash_file;

/// One Parquet shard of a published dataset.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct ShardEntry {
    /// File name relative to the dataset directory.
    pub path: String,
    pub bytes: u64,
    pub rows: u64,
    pub row_groups: u64,
    pub blake3: String,
}

/// Any other file listed with its checksum (rasters, metadata, truth maps).
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct FileEntry {
    pub path: String,
    pub bytes: u64,
    pub blake3: String,
}

impl FileEntry {
    pub fn of(root: &Path, relative: &str) -> io::Result<Self> {
        let full = root.join(relative);
        Ok(Self {
            path: relative.to_string(),
            bytes: std::fs::metadata(&full)?.len(),
            blake3: hash_file(&full)?,
        })
    }
}

/// `manifest.json` of a published dataset (docs/design.md, Data contract).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DatasetManifest {
    pub schema_version: String,
    pub name: String,
    pub license: String,
    pub seed: u64,
    /// Map CRS of the source rasters (PROJ/WKT definition).
    pub crs: String,
    pub split_counts: BTreeMap<String, u64>,
    pub shards: Vec<ShardEntry>,
    /// Dataset-wide DEM height std (after per-crop mean removal), from the train split only.
    pub dem_std_m: f64,
    pub pipeline_lock_blake3: String,
    /// The crater catalogue that framed the samples, when the pipeline was given one (absent otherwise, and in
    /// manifests written before it was recorded).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crater_frame: Option<CraterFrameSource>,
}

/// What framed a published dataset's samples (their crater columns, `crate::contract::crater_frame`): the
/// catalogue, by name and blake3, the smallest diameter that frames, and the catalogue's simulated errors when
/// the samples were framed with them. The dataset manifest records it, so that no reader is asked for it again.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CraterFrameSource {
    /// The catalogue's file name (`inputs.crater_catalogue`).
    pub catalogue: String,
    pub catalogue_blake3: String,
    /// Catalogued craters at least this wide frame the samples (`project.crater_frame_min_diameter_m`).
    pub min_diameter_m: f64,
    /// The simulated errors the samples were framed with, when they were (`project.crater_catalogue_error`,
    /// drawn from the dataset's seed; [`crate::contract::catalogue_error`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub catalogue_error: Option<CatalogueError>,
}

impl CraterFrameSource {
    /// The record of samples framed by the catalogue file `catalogue` (its name and blake3).
    pub fn of(
        catalogue: &Path,
        min_diameter_m: f64,
        catalogue_error: Option<CatalogueError>,
    ) -> anyhow::Result<Self> {
        use anyhow::Context;
        Ok(Self {
            catalogue: catalogue
                .file_name()
                .map(|name| name.to_string_lossy().into_owned())
                .unwrap_or_default(),
            catalogue_blake3: hash_file(catalogue)
                .with_context(|| format!("{}: cannot read the catalogue", catalogue.display()))?,
            min_diameter_m,
            catalogue_error,
        })
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ManifestError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: io::Error },
    #[error(
        "{path}: not a valid manifest ({source}); regenerate it with the pipeline's publish stage"
    )]
    Parse {
        path: PathBuf,
        source: serde_json::Error,
    },
    #[error("{path}: manifest schema {found} does not match this build's {SCHEMA_VERSION}; rebuild the dataset")]
    SchemaVersion { path: PathBuf, found: String },
    #[error("{dir}: no manifest.json: point at a published dataset directory (g2r-pipeline run writes OUT/dataset)")]
    NoManifest { dir: PathBuf },
}

/// The published dataset's index of shards and checksums; written last, it is what makes a dataset finished.
pub const MANIFEST_FILE: &str = "manifest.json";

impl DatasetManifest {
    /// The manifest of a published dataset directory (`dir/manifest.json`).
    pub fn load_dir(dir: &Path) -> Result<Self, ManifestError> {
        let path = dir.join(MANIFEST_FILE);
        if !path.exists() {
            return Err(ManifestError::NoManifest {
                dir: dir.to_path_buf(),
            });
        }
        Self::load(&path)
    }

    pub fn load(path: &Path) -> Result<Self, ManifestError> {
        let text = std::fs::read_to_string(path).map_err(|source| ManifestError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::parse(&text, path)
    }

    /// Parse manifest JSON that came from `origin` (a path or URL, for messages), checking the schema version.
    pub fn parse(text: &str, origin: &Path) -> Result<Self, ManifestError> {
        let path = origin;
        let manifest: Self = serde_json::from_str(text).map_err(|source| ManifestError::Parse {
            path: path.to_path_buf(),
            source,
        })?;
        if manifest.schema_version.split('.').next() != SCHEMA_VERSION.split('.').next() {
            return Err(ManifestError::SchemaVersion {
                path: path.to_path_buf(),
                found: manifest.schema_version,
            });
        }
        Ok(manifest)
    }

    /// Shard file names of one split, sorted: the fixed order every reader (trainer, server) lists rows in.
    pub fn split_shards(&self, split: impl std::fmt::Display) -> Vec<&str> {
        let prefix = format!("{split}-");
        let mut names: Vec<&str> = self
            .shards
            .iter()
            .map(|s| s.path.as_str())
            .filter(|p| p.starts_with(&prefix))
            .collect();
        names.sort_unstable();
        names
    }

    /// Check every shard's size and blake3 against the files in `dir`; returns one line per mismatch.
    pub fn verify(&self, dir: &Path) -> Vec<String> {
        let mut problems = Vec::new();
        for shard in &self.shards {
            let path = dir.join(&shard.path);
            match std::fs::metadata(&path) {
                Err(_) => problems.push(format!("{}: missing", path.display())),
                Ok(m) if m.len() != shard.bytes => problems.push(format!(
                    "{}: {} bytes, manifest says {} (truncated?)",
                    path.display(),
                    m.len(),
                    shard.bytes
                )),
                Ok(_) => match hash_file(&path) {
                    Ok(h) if h == shard.blake3 => {}
                    Ok(h) => problems.push(format!(
                        "{}: blake3 {h} does not match the manifest (tampered?)",
                        path.display()
                    )),
                    Err(e) => problems.push(format!("{}: {e}", path.display())),
                },
            }
        }
        problems
    }
}

#[cfg(test)]
mod tests {

    #[test]
    fn a_crater_frame_source_names_its_catalogue_by_file_name_and_blake3() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("here.csv");
        std::fs::write(&path, "lon_deg,lat_deg,diameter_m\n0,0,1000\n").unwrap();
        let source = CraterFrameSource::of(&path, 1000.0, None).unwrap();
        assert_eq!(source.catalogue, "here.csv");
        assert_eq!(source.catalogue_blake3, hash_file(&path).unwrap());
        assert_eq!(source.min_diameter_m, 1000.0);
        let json = serde_json::to_string(&source).unwrap();
        assert!(!json.contains("catalogue_error"), "{json}");
        let err = CraterFrameSource::of(&dir.path().join("missing.csv"), 1000.0, None).unwrap_err();
        assert!(format!("{err:#}").contains("missing.csv"), "{err:#}");
    }
    use super::*;
    use crate::files::write_json_atomic;

    #[test]
    fn verify_detects_tampering_and_truncation() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("a.parquet"), b"hello shard").unwrap();
        let entry = FileEntry::of(dir.path(), "a.parquet").unwrap();
        let manifest = DatasetManifest {
            schema_version: SCHEMA_VERSION.into(),
            name: "t".into(),
            license: "CC-BY-4.0".into(),
            seed: 1,
            crs: "x".into(),
            split_counts: BTreeMap::new(),
            shards: vec![ShardEntry {
                path: entry.path,
                bytes: entry.bytes,
                rows: 1,
                row_groups: 1,
                blake3: entry.blake3,
            }],
            dem_std_m: 1.0,
            pipeline_lock_blake3: String::new(),
            crater_frame: None,
        };
        assert!(manifest.verify(dir.path()).is_empty());
        std::fs::write(dir.path().join("a.parquet"), b"hello shard!").unwrap();
        assert!(manifest.verify(dir.path())[0].contains("truncated"));
        std::fs::write(dir.path().join("a.parquet"), b"hellO shard").unwrap();
        assert!(manifest.verify(dir.path())[0].contains("tampered"));
        let path = dir.path().join("manifest.json");
        write_json_atomic(&path, &manifest).unwrap();
        assert_eq!(DatasetManifest::load(&path).unwrap(), manifest);
    }
}

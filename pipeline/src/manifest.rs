//! The pipeline manifest (`manifests/*.toml`): inputs, output directory and every stage's parameters.
//! Relative paths are resolved against the manifest file's directory.

use std::path::{Path, PathBuf};

use anyhow::Context;
use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PipelineManifest {
    pub dataset: DatasetInfo,
    pub inputs: Inputs,
    pub output: Output,
    pub sample: SampleParams,
    pub project: ProjectParams,
    pub split: SplitParams,
    pub publish: PublishParams,
    /// Directory of the manifest file (not serialised; set by `load`).
    #[serde(skip)]
    pub base_dir: PathBuf,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DatasetInfo {
    pub name: String,
    pub license: String,
    pub seed: u64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Inputs {
    /// GeoTIFF DEM in a lunar CRS (heights above the 1737400 m sphere): a path, or an object's URL
    /// (`s3://bucket/dem.tif`; fetched by [`crate::inputs`]).
    pub dem: PathBuf,
    /// Directory of orthoimages (`*.tif`) each with its acquisition metadata (`*.json`): a path, or an
    /// object-storage prefix whose objects directly under it are the folder's files.
    pub ortho_dir: PathBuf,
    /// A crater catalogue CSV (`dataset::contract::crater_frame::read_catalogue`: `lon_deg,lat_deg,diameter_m`,
    /// or Robbins 2018's columns), a local path. With one, every sample carries its place in the frame of the
    /// nearest large crater (`crater_rho`, `crater_relative_height_m`); without, those columns hold NaN.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crater_catalogue: Option<PathBuf>,
    /// A mare/highland unit map (`dataset::contract::context::read_unit_map`: a GDAL raster in the DEM's CRS, 0
    /// mare, 1 highland, nodata unmapped), a local path. With one, every sample's context window carries the
    /// highland fraction of its cells (`context_highland`); without, that column holds NaN.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub unit_map: Option<PathBuf>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Output {
    /// Stage outputs go to `DIR/stages/`, the published dataset to `DIR/dataset/`, the lock to `DIR/pipeline.lock.json`.
    pub dir: PathBuf,
    /// Where the published dataset is copied once it is built: an object-storage prefix (`s3://bucket/prefix`),
    /// written as `g2r-dataset upload` writes it (shards, then `manifest.json` last with a conditional put). Not a
    /// stage parameter: where the dataset is copied does not change its bytes.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub publish_to: Option<String>,
    /// Where partitions meet the merge when they run on machines that share no file system: an object-storage
    /// prefix. Each finished partition copies its directory to `EXCHANGE/partitions/N/I/`, and `run --merge N`
    /// fetches from there what it does not hold ([`crate::exchange`]). Not a stage parameter either.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub exchange: Option<String>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SampleParams {
    /// Crops per ortho = ⌊coverage × eroded area / crop area⌋.
    pub coverage: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PublishParams {
    pub rows_per_shard: usize,
}

/// A pipeline manifest for a world made by `synth::config::tiny()` at `world/` next to it, output in `out/`:
/// small thresholds and tiles so a few dozen pairs come out in seconds (tests and smoke runs).
pub fn tiny_manifest_toml(seed: u64, coverage: f64) -> String {
    format!(
        r#"[dataset]
name = "g2r-tiny"
license = "CC-BY-4.0"
seed = {seed}
[inputs]
dem = "world/dem/dem.tif"
ortho_dir = "world/ortho"
[output]
dir = "out"
[sample]
coverage = {coverage:?}
[project]
min_valid_fraction = 0.9
max_shadowed_fraction = 0.6
max_occluded_fraction = 0.05
sun_disk_samples = 2
[split]
tile_size_m = 1300.0
val_fraction = 0.2
test_fraction = 0.2
guard_band_m = 0.0
[publish]
rows_per_shard = 40
"#
    )
}

/// A TOML error as one line: the message and where (TOML's own Display is a multi-line source snippet).
pub fn toml_error_line(text: &str, e: &toml::de::Error) -> String {
    match e.span() {
        Some(span) => format!(
            "{} (line {})",
            e.message().trim(),
            text[..span.start.min(text.len())].lines().count().max(1)
        ),
        None => e.message().trim().to_string(),
    }
}

impl PipelineManifest {
    pub fn load(path: &Path) -> anyhow::Result<Self> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("{}: cannot read the pipeline manifest", path.display()))?;
        let mut manifest: Self = toml::from_str(&text).map_err(|e| {
            anyhow::anyhow!(
                "{}: invalid pipeline manifest: {}",
                path.display(),
                toml_error_line(&text, &e)
            )
        })?;
        manifest.base_dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
        // A URL here would be joined onto the manifest's folder as a relative path (`s3:/bucket/…`): refused.
        // (Inputs may be URLs: `crate::inputs` fetches them.)
        let dir = manifest.output.dir.to_string_lossy();
        if dataset::storage::is_url(&dir) {
            anyhow::bail!(
                "{}: output.dir = \"{dir}\": the pipeline builds in a local folder; set output.dir to one and \
                 output.publish_to = \"URL\" (or run `g2r-dataset upload DIR/dataset URL`)",
                path.display()
            );
        }
        if let Some(url) = &manifest.output.publish_to {
            if !dataset::storage::is_url(url) {
                anyhow::bail!(
                    "{}: output.publish_to = \"{url}\": give an object-storage prefix such as s3://bucket/prefix (the local dataset is output.dir/dataset)",
                    path.display()
                );
            }
        }
        if let Some(url) = &manifest.output.exchange {
            if !dataset::storage::is_url(url) {
                anyhow::bail!(
                    "{}: output.exchange = \"{url}\": give an object-storage prefix such as s3://bucket/build (on a shared file system, leave it out: partitions write under output.dir)",
                    path.display()
                );
            }
        }
        let rows = manifest.publish.rows_per_shard;
        let group = dataset::contract::shard::ROW_GROUP_ROWS;
        if rows == 0 || (rows > group && !rows.is_multiple_of(group)) {
            anyhow::bail!(
                "{}: publish.rows_per_shard = {rows}: use 1 to {group} or a multiple of {group} (a shard is whole row groups of {group} rows)",
                path.display()
            );
        }
        for (field, local) in [
            ("crater_catalogue", &manifest.inputs.crater_catalogue),
            ("unit_map", &manifest.inputs.unit_map),
        ] {
            if let Some(local) = local
                .as_ref()
                .filter(|p| dataset::storage::is_url(&p.to_string_lossy()))
            {
                anyhow::bail!(
                    "{}: inputs.{field} = \"{}\": it is read from a local path; copy it next to the manifest",
                    path.display(),
                    local.display()
                );
            }
        }
        let min_diameter_m = manifest.project.crater_frame_min_diameter_m;
        if !(min_diameter_m.is_finite() && min_diameter_m > 0.0) {
            anyhow::bail!(
                "{}: project.crater_frame_min_diameter_m = {min_diameter_m}: use a positive diameter in metres (default {})",
                path.display(),
                dataset::contract::crater_frame::DEFAULT_MIN_DIAMETER_M
            );
        }
        if let Some(error) = &manifest.project.crater_catalogue_error {
            if manifest.inputs.crater_catalogue.is_none() {
                anyhow::bail!(
                    "{}: project.crater_catalogue_error simulates a catalogue's errors, but inputs.crater_catalogue names none: add the catalogue or drop the table",
                    path.display()
                );
            }
            if let Err(reason) = error.validate() {
                anyhow::bail!(
                    "{}: project.crater_catalogue_error: {reason}",
                    path.display()
                );
            }
        }
        let context_gsd_m = manifest.project.context_gsd_m;
        if !(context_gsd_m.is_finite() && context_gsd_m > 0.0) {
            anyhow::bail!(
                "{}: project.context_gsd_m = {context_gsd_m}: use a positive cell size in metres (default {})",
                path.display(),
                DEFAULT_CONTEXT_GSD_M
            );
        }
        Ok(manifest)
    }

    pub fn resolve(&self, p: &Path) -> PathBuf {
        if p.is_absolute() {
            p.to_path_buf()
        } else {
            self.base_dir.join(p)
        }
    }

    pub fn out_dir(&self) -> PathBuf {
        self.resolve(&self.output.dir)
    }
    pub fn stage_dir(&self) -> PathBuf {
        self.out_dir().join("stages")
    }
    pub fn dataset_dir(&self) -> PathBuf {
        self.out_dir().join("dataset")
    }
}
/// The project stage's rejection thresholds, shadow sampling, context window and crater frame (`stages::project`).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProjectParams {
    /// Reject crops with fewer usable image pixels than this share.
    pub min_valid_fraction: f64,
    /// Reject crops where more than this share of usable pixels sees less than half the sun.
    pub max_shadowed_fraction: f64,
    /// Reject crops where more than this share of pixels is hidden from the camera.
    pub max_occluded_fraction: f64,
    /// Elevation samples across the sun disk for soft shadows on the 5 m DEM.
    pub sun_disk_samples: usize,
    /// Cell size of each sample's context window (`dataset::contract::context`): 32 cells of 512 m see 16 km around the
    /// crop, enough to hold a crater of ~10–20 km across and its ejecta.
    #[serde(default = "default_context_gsd_m")]
    pub context_gsd_m: f64,
    /// Catalogued craters at least this wide frame the samples (`inputs.crater_catalogue`): the complex ones,
    /// whose walls hide a unit's level (`dataset::contract::crater_frame`).
    /// (Named `crater_min_diameter_m` before 2026-12: still read, it is not the synthetic world's smallest crater.)
    #[serde(
        default = "default_crater_frame_min_diameter_m",
        alias = "crater_min_diameter_m"
    )]
    pub crater_frame_min_diameter_m: f64,
    /// Frame the samples with draws of the catalogue carrying a real catalogue's errors, so that a network
    /// learning from the frame learns to expect them (`dataset::contract::catalogue_error`); the catalogue as it
    /// is without. Drawn from `dataset.seed`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crater_catalogue_error: Option<dataset::contract::catalogue_error::CatalogueError>,
}

fn default_crater_frame_min_diameter_m() -> f64 {
    dataset::contract::crater_frame::DEFAULT_MIN_DIAMETER_M
}

/// See [`ProjectParams::context_gsd_m`].
pub const DEFAULT_CONTEXT_GSD_M: f64 = 512.0;

fn default_context_gsd_m() -> f64 {
    DEFAULT_CONTEXT_GSD_M
}

/// The tile-based geographic split (`stages::split`).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SplitParams {
    pub tile_size_m: f64,
    /// Target shares of tiles (train is the rest).
    pub val_fraction: f64,
    pub test_fraction: f64,
    /// Extra margin around each footprint that must also lie in the sample's split, metres.
    pub guard_band_m: f64,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Manifests written before the rename still give the framing threshold, under its old name, and the two
    /// names are one setting (both at once are refused as a duplicate).
    #[test]
    fn the_old_name_of_the_crater_frame_threshold_is_still_read() {
        let with = |line: &str| {
            toml::from_str::<PipelineManifest>(
                &tiny_manifest_toml(1, 1.0).replace("[project]", &format!("[project]\n{line}")),
            )
        };
        let old = with("crater_min_diameter_m = 3000.0").unwrap();
        let new = with("crater_frame_min_diameter_m = 3000.0").unwrap();
        assert_eq!(old.project.crater_frame_min_diameter_m, 3000.0);
        assert_eq!(new.project.crater_frame_min_diameter_m, 3000.0);
        assert!(with("crater_min_diameter_m = 1.0\ncrater_frame_min_diameter_m = 2.0").is_err());
    }

    /// A catalogue's simulated errors need a catalogue and fields in range; each refusal names the key.
    #[test]
    fn catalogue_errors_need_a_catalogue_and_fields_in_range() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(
            dir.path().join("craters.csv"),
            "lon_deg,lat_deg,diameter_m\n",
        )
        .unwrap();
        let load = |catalogue: &str, error: &str| {
            let path = dir.path().join("m.toml");
            let text = tiny_manifest_toml(1, 1.0)
                .replace("[inputs]", &format!("[inputs]\n{catalogue}"))
                .replace(
                    "[project]",
                    &format!(
                        "[project]\ncrater_catalogue_error = {{ centre_sd_m = 300.0, diameter_log_sd = 0.05, {error} }}"
                    ),
                );
            std::fs::write(&path, text).unwrap();
            PipelineManifest::load(&path).map_err(|e| e.to_string())
        };
        let fields = "missed_fraction = 0.05, false_craters = 0.5, draws = 8";
        let catalogue = "crater_catalogue = \"craters.csv\"";
        let loaded = load(catalogue, fields).unwrap();
        assert_eq!(loaded.project.crater_catalogue_error.unwrap().draws, 8);
        let err = load("", fields).unwrap_err();
        assert!(err.contains("inputs.crater_catalogue"), "{err}");
        for bad in [
            "missed_fraction = 1.0, false_craters = 0.5, draws = 8",
            "missed_fraction = 0.05, false_craters = -1.0, draws = 8",
            "missed_fraction = 0.05, false_craters = 0.5, draws = 0",
        ] {
            let err = load(catalogue, bad).unwrap_err();
            assert!(
                err.contains("project.crater_catalogue_error"),
                "{bad}: {err}"
            );
        }
    }

    /// Every pipeline manifest shipped in `manifests/` parses (worlds are `world-*.toml`, checked by `synth`).
    #[test]
    fn every_shipped_pipeline_manifest_parses() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../manifests");
        let mut parsed = 0;
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            let name = path.file_name().unwrap().to_string_lossy().into_owned();
            if !name.ends_with(".toml") || name.starts_with("world-") {
                continue;
            }
            let text = std::fs::read_to_string(&path).unwrap();
            if let Err(e) = toml::from_str::<PipelineManifest>(&text) {
                panic!("{name}: {}", toml_error_line(&text, &e));
            }
            parsed += 1;
        }
        assert!(parsed >= 2, "{parsed}");
    }
}

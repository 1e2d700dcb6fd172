//! Acquisition metadata from the products LROC users hold: a USGS ALE image support data file ([`isd`]) or a row
//! of the LROC cumulative index ([`index`]), turned into the project's per-ortho acquisition JSON
//! (`dataset::contract::acquisition::AcquisitionMetadata`: Moon body-fixed frame, metres, the units in every key).
//!
//! Both importers end in [`finish`]: the ortho's ground sample distance comes from the ortho itself, the off-nadir
//! roll from the imported geometry, and the JSON is validated before it is written (atomically).

pub mod index;
pub mod isd;

use std::path::{Path, PathBuf};

use dataset::contract::acquisition::AcquisitionMetadata;
use glam::{DQuat, DVec3};

/// One-line import errors: the file, the key, and what was expected.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: not an ALE image support data file ({source})")]
    IsdSyntax {
        path: PathBuf,
        source: serde_json::Error,
    },
    #[error("{path}: {key}: {problem}")]
    Field {
        path: PathBuf,
        key: String,
        problem: String,
    },
    #[error("{path}: {problem}")]
    Invalid { path: PathBuf, problem: String },
    #[error(transparent)]
    Raster(#[from] dataset::science::raster::RasterError),
}

impl ImportError {
    pub(crate) fn field(path: &Path, key: &str, problem: impl Into<String>) -> Self {
        Self::Field {
            path: path.to_path_buf(),
            key: key.to_string(),
            problem: problem.into(),
        }
    }
}

/// The acquisition geometry an importer recovers, in the Moon body-fixed frame (metres).
#[derive(Debug, Clone)]
pub struct ImportedGeometry {
    pub product_id: String,
    pub camera_id: String,
    pub start_utc_s: f64,
    pub stop_utc_s: f64,
    pub sun_body_m: DVec3,
    pub spacecraft_start_body_m: DVec3,
    pub spacecraft_stop_body_m: DVec3,
    /// Camera frame → body-fixed at mid-strip; camera +z is the boresight.
    pub camera_to_body: DQuat,
    pub fov_deg: f64,
}

/// The project's metadata for `image` (its file name is stored relative to `out`'s directory), validated.
pub fn finish(
    geometry: &ImportedGeometry,
    image: &Path,
    out: &Path,
) -> Result<AcquisitionMetadata, ImportError> {
    let (_, info) = dataset::science::raster::open_lunar(image)?;
    let image_file = relative_to(image, out.parent().unwrap_or(Path::new(".")));
    let q = geometry.camera_to_body.normalize();
    let mut meta = AcquisitionMetadata {
        ortho_id: geometry.product_id.clone(),
        image_file,
        camera_id: geometry.camera_id.clone(),
        start_time_utc: dataset::contract::acquisition::iso_utc_from_j2000_seconds(
            geometry.start_utc_s,
        ),
        stop_time_utc: dataset::contract::acquisition::iso_utc_from_j2000_seconds(
            geometry.stop_utc_s,
        ),
        sun_position_body_m: geometry.sun_body_m.into(),
        spacecraft_start_body_m: geometry.spacecraft_start_body_m.into(),
        spacecraft_stop_body_m: geometry.spacecraft_stop_body_m.into(),
        camera_attitude_wxyz: [q.w, q.x, q.y, q.z],
        fov_deg: geometry.fov_deg,
        pixel_scale_m: info.transform.gsd_m(),
        roll_deg: 0.0,
    };
    // Measured from the imported geometry: an index or ISD states no roll of its own.
    meta.roll_deg = meta.off_nadir_roll_deg();
    meta.validate().map_err(|problem| ImportError::Invalid {
        path: out.to_path_buf(),
        problem: format!("imported metadata is not physical: {problem}"),
    })?;
    Ok(meta)
}

/// `path` relative to `dir` when it lies inside it, else absolute: the metadata JSON names its image relative to
/// itself.
fn relative_to(path: &Path, dir: &Path) -> String {
    let absolute = |p: &Path| std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf());
    let (path, dir) = (absolute(path), absolute(dir));
    path.strip_prefix(&dir)
        .map(Path::to_path_buf)
        .unwrap_or(path)
        .to_string_lossy()
        .into_owned()
}

/// Where an ortho's acquisition geometry comes from.
#[derive(Debug, Clone, Copy)]
pub enum Source<'a> {
    /// An ALE ISD JSON of the image.
    Isd(&'a Path),
    /// A cumulative index table (with its PDS3 label, found next to it when `None`) holding the image's row.
    Index {
        table: &'a Path,
        label: Option<&'a Path>,
    },
}

/// Import the metadata of orthoimage `image` (product `product_id`) and write it to `out` atomically. An existing
/// `out` is replaced only with `force`; on any error nothing is written.
pub fn import(
    source: Source,
    image: &Path,
    product_id: &str,
    out: &Path,
    force: bool,
) -> Result<AcquisitionMetadata, ImportError> {
    if out.exists() && !force {
        return Err(ImportError::Invalid {
            path: out.to_path_buf(),
            problem: "exists; pass --force to replace it".into(),
        });
    }
    let geometry = match source {
        Source::Isd(path) => isd::Isd::load(path)?.geometry(product_id),
        Source::Index { table, label } => {
            index::IndexTable::open(table, label)?.geometry(product_id)?
        }
    };
    let meta = finish(&geometry, image, out)?;
    dataset::files::write_json_atomic(out, &meta).map_err(|source| ImportError::Io {
        path: out.to_path_buf(),
        source,
    })?;
    Ok(meta)
}

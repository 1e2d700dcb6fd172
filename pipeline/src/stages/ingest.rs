//! Ingest: open the DEM and every ortho with GDAL, check what later stages rely on (lunar CRS, north-up, the same
//! CRS everywhere, overlap, resolution, metadata complete and physical, sun above the horizon), and write one row
//! per ortho. Bad input stops here with a one-line error naming the file and the fix.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use dataset::contract::acquisition::AcquisitionMetadata;
use dataset::science::crs::LocalFrame;
use dataset::science::raster::open_lunar;

use super::table::{f64s, read_table, strings, write_table, Col};

/// One ortho as the later stages see it.
#[derive(Debug, Clone)]
pub struct OrthoRecord {
    pub ortho_id: String,
    pub image_path: PathBuf,
    pub metadata_path: PathBuf,
    pub incidence_deg: f64,
}

/// The ortho metadata files of a directory, sorted by name (never directory-listing order).
pub fn metadata_files(ortho_dir: &Path) -> anyhow::Result<Vec<PathBuf>> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(ortho_dir)
        .with_context(|| {
            format!(
                "{}: cannot list the ortho directory; check inputs.ortho_dir in the manifest",
                ortho_dir.display()
            )
        })?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "json"))
        .collect();
    files.sort();
    // An image without metadata is an error, not a silent skip.
    let mut images: Vec<PathBuf> = std::fs::read_dir(ortho_dir)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "tif"))
        .collect();
    images.sort();
    for image in images {
        if !image.with_extension("json").exists() {
            bail!("{}: orthoimage has no acquisition metadata; add {} (fields: dataset::contract::acquisition::AcquisitionMetadata)", image.display(), image.with_extension("json").display());
        }
    }
    if files.is_empty() {
        bail!(
            "{}: no orthoimage metadata (*.json) found; point inputs.ortho_dir at the orthos",
            ortho_dir.display()
        );
    }
    Ok(files)
}

/// Validate the DEM and the orthos of `metadata` (their metadata files, in order) and write `orthos.parquet`.
pub fn run(dem_path: &Path, metadata: &[PathBuf], out: &Path) -> anyhow::Result<()> {
    let (dem_ds, dem) = open_lunar(dem_path)?;
    let dem_band = dem_ds.rasterband(1)?;
    let (dem_x0, dem_y0, dem_x1, dem_y1) = dem.transform.bounds(dem.width, dem.height);
    // An all-nodata DEM (or one that is NaN-laden) is useless: check a decimated read.
    let preview = dem_band.read_as::<f32>(
        (0, 0),
        (dem.width, dem.height),
        (dem.width.min(256), dem.height.min(256)),
        None,
    )?;
    let nodata = dem.nodata.map(|v| v as f32);
    let finite = preview
        .data()
        .iter()
        .filter(|v| v.is_finite() && Some(**v) != nodata)
        .count();
    if finite * 2 < preview.data().len() {
        bail!("{}: more than half of the DEM is nodata or NaN ({} of {} sampled cells valid); fill or crop it before ingesting", dem_path.display(), finite, preview.data().len());
    }
    if (dem.transform.pixel_width + dem.transform.pixel_height).abs()
        > 1e-9 * dem.transform.pixel_width
    {
        bail!("{}: DEM pixels are not square ({} × {} m); resample with gdalwarp -tr to square pixels", dem_path.display(), dem.transform.pixel_width, -dem.transform.pixel_height);
    }
    struct Row {
        ortho_id: String,
        metadata_file: String,
        image_file: String,
        incidence_deg: f64,
        roll_deg: f64,
        bounds: (f64, f64, f64, f64),
    }
    let mut table = Vec::new();
    for meta_path in metadata {
        let meta = AcquisitionMetadata::load(meta_path)?;
        if let Some(previous) = table.iter().find(|r: &&Row| r.ortho_id == meta.ortho_id) {
            bail!(
                "{}: ortho_id {} is already used by {}; ortho ids must be unique",
                meta_path.display(),
                meta.ortho_id,
                previous.metadata_file
            );
        }
        let image_path = meta_path.with_file_name(&meta.image_file);
        let (_, info) = open_lunar(&image_path)?;
        let (x0, y0, x1, y1) = info.transform.bounds(info.width, info.height);
        let probes = info.transform.corners(info.width, info.height);
        if !dem.crs.same_map(&info.crs, &probes)? {
            bail!("{}: CRS differs from the DEM's ({}); reproject with gdalwarp -t_srs to the DEM's CRS", image_path.display(), dem_path.display());
        }
        if info.transform.gsd_m() > dem.transform.gsd_m() + 1e-9 {
            bail!("{}: pixel size {} m is coarser than the DEM's {} m; orthos must be at least as fine as the DEM", image_path.display(), info.transform.gsd_m(), dem.transform.gsd_m());
        }
        if x1 <= dem_x0 || x0 >= dem_x1 || y1 <= dem_y0 || y0 >= dem_y1 {
            bail!(
                "{}: does not overlap the DEM {}; check that both are in the same area and CRS",
                image_path.display(),
                dem_path.display()
            );
        }
        let (cx, cy) = ((x0 + x1) / 2.0, (y0 + y1) / 2.0);
        let frame = LocalFrame::new(&dem.crs, cx, cy, 0.0)?;
        let sun = frame.sun_dir_enu(meta.sun_body());
        if sun.z <= 0.0 {
            bail!("{}: the sun is below the horizon at the image centre (incidence {:.1}°); check sun_position_body_m", meta_path.display(), sun.z.clamp(-1.0, 1.0).acos().to_degrees());
        }
        table.push(Row {
            ortho_id: meta.ortho_id.clone(),
            metadata_file: meta_path
                .file_name()
                .unwrap_or_default()
                .to_string_lossy()
                .into_owned(),
            image_file: meta.image_file.clone(),
            incidence_deg: sun.z.clamp(-1.0, 1.0).acos().to_degrees(),
            roll_deg: meta.roll_deg,
            bounds: (x0, y0, x1, y1),
        });
    }
    let strings = |f: fn(&Row) -> &String| Col::Str(table.iter().map(|r| f(r).clone()).collect());
    let numbers = |f: fn(&Row) -> f64| Col::F64(table.iter().map(f).collect());
    write_table(
        out,
        vec![
            ("ortho_id", strings(|r| &r.ortho_id)),
            ("metadata_file", strings(|r| &r.metadata_file)),
            ("image_file", strings(|r| &r.image_file)),
            ("incidence_deg", numbers(|r| r.incidence_deg)),
            ("roll_deg", numbers(|r| r.roll_deg)),
            ("min_x", numbers(|r| r.bounds.0)),
            ("min_y", numbers(|r| r.bounds.1)),
            ("max_x", numbers(|r| r.bounds.2)),
            ("max_y", numbers(|r| r.bounds.3)),
        ],
    )
}

/// Read back the ingest table.
pub fn read(path: &Path, ortho_dir: &Path) -> anyhow::Result<Vec<OrthoRecord>> {
    let batches = read_table(path)?;
    let (ids, metas, images, incidence) = (
        strings(&batches, "ortho_id")?,
        strings(&batches, "metadata_file")?,
        strings(&batches, "image_file")?,
        f64s(&batches, "incidence_deg")?,
    );
    Ok((0..ids.len())
        .map(|i| OrthoRecord {
            ortho_id: ids[i].clone(),
            image_path: ortho_dir.join(&images[i]),
            metadata_path: ortho_dir.join(&metas[i]),
            incidence_deg: incidence[i],
        })
        .collect())
}

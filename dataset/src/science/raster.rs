//! Georeferenced rasters: the pixel-centre convention and GeoTIFF IO through GDAL.
//!
//! **Pixel-centre convention (used everywhere):** pixel (col, row) covers the square whose top-left corner is the
//! geotransform applied to (col, row); its centre — where its value is defined — is the geotransform at
//! (col + 0.5, row + 0.5). Rows run north to south (negative y pixel size).

use std::path::{Path, PathBuf};

use gdal::raster::{Buffer, RasterCreationOptions};
use gdal::spatial_ref::SpatialRef;
use gdal::{Dataset, DriverManager, Metadata};
use rayon::prelude::*;

use crate::science::crs::{LunarCrs, MOON_RADIUS_M};

/// North-up affine georeferencing: origin is the top-left corner of pixel (0, 0).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct GeoTransform {
    pub origin_x: f64,
    pub origin_y: f64,
    pub pixel_width: f64,
    /// Negative for north-up rasters.
    pub pixel_height: f64,
}

impl GeoTransform {
    pub fn north_up(origin_x: f64, origin_y: f64, gsd_m: f64) -> Self {
        Self {
            origin_x,
            origin_y,
            pixel_width: gsd_m,
            pixel_height: -gsd_m,
        }
    }

    /// Map coordinates of the centre of pixel (col, row).
    pub fn pixel_center(&self, col: f64, row: f64) -> (f64, f64) {
        (
            self.origin_x + (col + 0.5) * self.pixel_width,
            self.origin_y + (row + 0.5) * self.pixel_height,
        )
    }

    /// Map coordinates of pixel *edge* (col, row): the corner of pixel (col, row), no +0.5.
    pub fn pixel_edge(&self, col: f64, row: f64) -> (f64, f64) {
        (
            self.origin_x + col * self.pixel_width,
            self.origin_y + row * self.pixel_height,
        )
    }

    /// Map extent `(min_x, min_y, max_x, max_y)` of a `width` × `height` raster on this grid (outer pixel edges).
    pub fn bounds(&self, width: usize, height: usize) -> (f64, f64, f64, f64) {
        let (xa, ya) = self.pixel_edge(0.0, 0.0);
        let (xb, yb) = self.pixel_edge(width as f64, height as f64);
        (xa.min(xb), ya.min(yb), xa.max(xb), ya.max(yb))
    }

    /// The four outer corners of a `width` × `height` raster on this grid, as map points: where two CRSs are
    /// compared ([`crate::science::crs::LunarCrs::same_map`]) before the raster is read in the other's map.
    pub fn corners(&self, width: usize, height: usize) -> [(f64, f64); 4] {
        let (x0, y0, x1, y1) = self.bounds(width, height);
        [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    }

    /// Continuous pixel coordinates (col, row) whose *centre* is at map (x, y): the inverse of [`Self::pixel_center`].
    pub fn map_to_pixel(&self, x: f64, y: f64) -> (f64, f64) {
        (
            (x - self.origin_x) / self.pixel_width - 0.5,
            (y - self.origin_y) / self.pixel_height - 0.5,
        )
    }

    /// Where this raster's pixel *edge* (col, row) (corner coordinates, no +0.5) falls in `other`'s pixel-edge
    /// coordinates: how cells of one north-up grid cover pixels of another in the same CRS.
    #[inline]
    pub fn edge_in(&self, other: &GeoTransform, col: f64, row: f64) -> (f64, f64) {
        (
            (self.origin_x + col * self.pixel_width - other.origin_x) / other.pixel_width,
            (self.origin_y + row * self.pixel_height - other.origin_y) / other.pixel_height,
        )
    }

    pub fn gsd_m(&self) -> f64 {
        self.pixel_width.abs()
    }

    pub fn to_gdal(&self) -> [f64; 6] {
        [
            self.origin_x,
            self.pixel_width,
            0.0,
            self.origin_y,
            0.0,
            self.pixel_height,
        ]
    }

    pub fn from_gdal(gt: &[f64; 6]) -> Option<Self> {
        (gt[2] == 0.0 && gt[4] == 0.0).then_some(Self {
            origin_x: gt[0],
            origin_y: gt[3],
            pixel_width: gt[1],
            pixel_height: gt[5],
        })
    }
}

/// A single-band f32 raster in memory, row-major, north-up.
#[derive(Debug, Clone)]
pub struct Raster {
    pub width: usize,
    pub height: usize,
    pub transform: GeoTransform,
    pub crs: LunarCrs,
    /// NaN marks nodata in memory; on disk it becomes [`Raster::nodata`].
    pub data: Vec<f32>,
    pub nodata: f32,
    pub description: String,
}

impl Raster {
    pub fn new(
        width: usize,
        height: usize,
        transform: GeoTransform,
        crs: LunarCrs,
        fill: f32,
    ) -> Self {
        Self {
            width,
            height,
            transform,
            crs,
            data: vec![fill; width * height],
            nodata: -32768.0,
            description: String::new(),
        }
    }

    #[inline]
    pub fn get(&self, col: usize, row: usize) -> f32 {
        self.data[row * self.width + col]
    }

    /// Bilinear sample at continuous pixel coordinates (pixel-centre convention), clamped at the edges.
    #[inline]
    pub fn bilinear(&self, col: f64, row: f64) -> f32 {
        bilinear(&self.data, self.width, self.height, col, row)
    }
}

/// Bilinear interpolation on a row-major grid at continuous (col, row) centre coordinates, clamped at the edges.
#[inline]
pub fn bilinear(data: &[f32], width: usize, height: usize, col: f64, row: f64) -> f32 {
    let c = col.clamp(0.0, (width - 1) as f64);
    let r = row.clamp(0.0, (height - 1) as f64);
    let (c0, r0) = (c.floor() as usize, r.floor() as usize);
    let (c1, r1) = ((c0 + 1).min(width - 1), (r0 + 1).min(height - 1));
    let (fc, fr) = ((c - c0 as f64) as f32, (r - r0 as f64) as f32);
    let top = data[r0 * width + c0] * (1.0 - fc) + data[r0 * width + c1] * fc;
    let bottom = data[r1 * width + c0] * (1.0 - fc) + data[r1 * width + c1] * fc;
    top * (1.0 - fr) + bottom * fr
}

#[derive(Debug, thiserror::Error)]
pub enum RasterError {
    #[error(
        "{path}: cannot open raster ({reason}); check the path and that it is a GDAL-readable file"
    )]
    Open { path: PathBuf, reason: String },
    #[error("{path}: has no CRS; assign a lunar one, e.g. gdal_edit.py -a_srs '+proj=eqc +R=1737400 ...' {path}")]
    NoCrs { path: PathBuf },
    #[error("{path}: CRS is not the lunar sphere (semi-major axis {semi_major_m} m, expected {MOON_RADIUS_M} m); reproject with gdalwarp -t_srs to a lunar CRS (IAU_2015:30100 family)")]
    NotLunar { path: PathBuf, semi_major_m: f64 },
    #[error("{path}: CRS {crs} is in {units}, not metres; project it onto a metric lunar grid, e.g. gdalwarp -t_srs '+proj=eqc +R=1737400 +units=m' (pixel sizes and heights are metres throughout)")]
    NotMetric {
        path: PathBuf,
        crs: String,
        units: String,
    },
    #[error("{path}: geotransform is rotated or missing; warp to a north-up grid with gdalwarp")]
    NotNorthUp { path: PathBuf },
    #[error("{path}: GDAL error ({reason})")]
    Gdal { path: PathBuf, reason: String },
}

fn gdal_err(path: &Path) -> impl Fn(gdal::errors::GdalError) -> RasterError + '_ {
    move |e| RasterError::Gdal {
        path: path.to_path_buf(),
        reason: e.to_string(),
    }
}

/// Check a GDAL spatial reference is on the lunar sphere, in a projection with metre units.
fn check_lunar(path: &Path, srs: &SpatialRef) -> Result<(), RasterError> {
    let semi_major_m = srs.semi_major().map_err(gdal_err(path))?;
    if (semi_major_m - MOON_RADIUS_M).abs() > 1.0 {
        return Err(RasterError::NotLunar {
            path: path.to_path_buf(),
            semi_major_m,
        });
    }
    let crs = srs.name().unwrap_or_else(|| "(unnamed)".into());
    if srs.is_geographic() || !srs.is_projected() {
        return Err(RasterError::NotMetric {
            path: path.to_path_buf(),
            crs,
            units: "degrees (a geographic CRS)".into(),
        });
    }
    if (srs.linear_units() - 1.0).abs() > 1e-12 {
        return Err(RasterError::NotMetric {
            path: path.to_path_buf(),
            crs,
            units: format!(
                "{} ({} m per unit)",
                srs.linear_units_name()
                    .unwrap_or_else(|| "unknown units".into()),
                srs.linear_units()
            ),
        });
    }
    Ok(())
}

/// Header of a GeoTIFF (no pixel data read): size, georeferencing, CRS and nodata of band 1.
#[derive(Debug, Clone)]
pub struct RasterInfo {
    pub width: usize,
    pub height: usize,
    pub transform: GeoTransform,
    pub crs: LunarCrs,
    pub nodata: Option<f64>,
}

/// Cap GDAL's block cache (default 5 % of RAM) at 64 MB, once per process, before the first block is read. This
/// crate reads and writes whole rasters, so every block passes through the cache exactly once: a large cache only
/// kept a second copy of each ortho (~300 MB on tycho-full) alive while it was read, raising peak RSS.
pub fn limit_gdal_block_cache() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        // Only fails on an interior NUL in key or value, which these constants do not have.
        let _ = gdal::config::set_config_option("GDAL_CACHEMAX", "64");
    });
}

/// Open a raster and validate what every stage relies on: a lunar CRS and a north-up geotransform.
pub fn open_lunar(path: &Path) -> Result<(Dataset, RasterInfo), RasterError> {
    limit_gdal_block_cache();
    if !path.exists() {
        return Err(RasterError::Open {
            path: path.to_path_buf(),
            reason: "file does not exist".into(),
        });
    }
    let ds = Dataset::open(path).map_err(|e| RasterError::Open {
        path: path.to_path_buf(),
        reason: e.to_string(),
    })?;
    let srs = ds.spatial_ref().map_err(|_| RasterError::NoCrs {
        path: path.to_path_buf(),
    })?;
    check_lunar(path, &srs)?;
    let gt = ds.geo_transform().map_err(|_| RasterError::NotNorthUp {
        path: path.to_path_buf(),
    })?;
    let transform = GeoTransform::from_gdal(&gt)
        .filter(|t| t.pixel_width > 0.0 && t.pixel_height < 0.0)
        .ok_or_else(|| RasterError::NotNorthUp {
            path: path.to_path_buf(),
        })?;
    let (width, height) = ds.raster_size();
    let nodata = ds.rasterband(1).map_err(gdal_err(path))?.no_data_value();
    let wkt = srs.to_wkt().map_err(gdal_err(path))?;
    Ok((
        ds,
        RasterInfo {
            width,
            height,
            transform,
            crs: LunarCrs::new(wkt),
            nodata,
        },
    ))
}

/// A dataset-level metadata item of a raster (GDAL's default domain), `None` when absent: how this project's own
/// GeoTIFFs say what they hold (e.g. `G2R_BRDF_MODEL` on `g2r-train infer` output), rather than in band text.
pub fn read_metadata_item(path: &Path, key: &str) -> Result<Option<String>, RasterError> {
    let ds = Dataset::open(path).map_err(|e| RasterError::Open {
        path: path.to_path_buf(),
        reason: e.to_string(),
    })?;
    Ok(ds.metadata_item(key, ""))
}

/// Read band 1 of a lunar raster (any format GDAL reads); nodata values become NaN and the band's scale and
/// offset are applied, so values are physical (I/F, metres) whatever the stored type.
pub fn read_raster(path: &Path) -> Result<Raster, RasterError> {
    Ok(read_bands(path)?.swap_remove(0))
}

/// Read every band of a lunar raster (band descriptions kept); nodata values become NaN, scale and offset are
/// applied.
pub fn read_bands(path: &Path) -> Result<Vec<Raster>, RasterError> {
    let (ds, info) = open_lunar(path)?;
    (1..=ds.raster_count())
        .map(|b| read_band(&ds, &info, path, b))
        .collect()
}

fn read_band(
    ds: &Dataset,
    info: &RasterInfo,
    path: &Path,
    index: usize,
) -> Result<Raster, RasterError> {
    let band = ds.rasterband(index).map_err(gdal_err(path))?;
    let window = ((0, 0), (info.width, info.height), (info.width, info.height));
    let description = band.description().unwrap_or_default();
    let raw_nodata = band.no_data_value();
    // Stored values are `physical = raw · scale + offset` (GDAL band scale/offset; e.g. LROC's Int16 "Scaled
    // I/F"); nodata is a raw value, so it is matched before scaling.
    let (scale, offset) = (band.scale().unwrap_or(1.0), band.offset().unwrap_or(0.0));
    let data: Vec<f32> = if scale == 1.0 && offset == 0.0 {
        let (_, mut data) = band
            .read_as::<f32>(window.0, window.1, window.2, None)
            .map_err(gdal_err(path))?
            .into_shape_and_vec();
        if let Some(nd) = raw_nodata.map(|v| v as f32) {
            data.iter_mut()
                .filter(|v| **v == nd)
                .for_each(|v| *v = f32::NAN);
        }
        data
    } else {
        // f64 holds every integer type's raw values exactly; the physical value is rounded to f32 once.
        let (_, raw) = band
            .read_as::<f64>(window.0, window.1, window.2, None)
            .map_err(gdal_err(path))?
            .into_shape_and_vec();
        raw.into_iter()
            .map(|v| {
                if Some(v) == raw_nodata {
                    f32::NAN
                } else {
                    (v * scale + offset) as f32
                }
            })
            .collect()
    };
    Ok(Raster {
        width: info.width,
        height: info.height,
        transform: info.transform,
        crs: info.crs.clone(),
        data,
        // Missing values are NaN in `data` from here on; the raw nodata value is kept for reference only when
        // it is also a physical value (no scale/offset), else NaN.
        nodata: match raw_nodata {
            Some(v) if scale == 1.0 && offset == 0.0 => v as f32,
            _ => f32::NAN,
        },
        description,
    })
}

/// One band to write: its values (NaN = nodata) and a description QGIS shows as the band name.
pub struct BandOut<'a> {
    pub values: BandValues<'a>,
    pub description: &'a str,
}

/// Pixel values of a band: a full grid, or one value everywhere (written with a fill, no buffer).
pub enum BandValues<'a> {
    Grid(&'a [f32]),
    Constant(f32),
}

/// Where a raster's pixels sit and how missing ones are written: everything of a GeoTIFF but its values.
#[derive(Debug, Clone)]
pub struct RasterLayout<'a> {
    pub width: usize,
    pub height: usize,
    pub transform: GeoTransform,
    pub crs: &'a LunarCrs,
    pub nodata: f32,
}

/// Write a tiled, DEFLATE-compressed Float32 GeoTIFF with CRS, nodata and band descriptions.
///
/// Written to `path.tmp` then renamed, so an interrupted write never leaves a finished-looking file.
pub fn write_geotiff(
    path: &Path,
    layout: &RasterLayout<'_>,
    bands: &[BandOut<'_>],
    metadata: &[(&str, String)],
) -> Result<(), RasterError> {
    let RasterLayout {
        width,
        height,
        transform,
        crs,
        nodata,
    } = layout.clone();
    let tmp = crate::files::tmp_path(path);
    limit_gdal_block_cache();
    let driver = DriverManager::get_driver_by_name("GTiff").map_err(gdal_err(path))?;
    let mut options = vec![
        "TILED=YES",
        "COMPRESS=DEFLATE",
        "PREDICTOR=3",
        "ZLEVEL=1",
        "BIGTIFF=IF_SAFER",
    ];
    // Several bands are stored band after band. GDAL's default for a new GTiff interleaves them pixel by pixel,
    // so every tile holds all bands: writing them one at a time, as below, makes GDAL compress each tile again
    // for every band (re-reading it once the block cache has let it go), and a band of one value never
    // compresses beside a varying one. One band is left as it was, so single-band files keep their bytes.
    if bands.len() > 1 {
        options.push("INTERLEAVE=BAND");
    }
    let options = RasterCreationOptions::from_iter(options);
    {
        let mut ds = driver
            .create_with_band_type_with_options::<f32, _>(
                &tmp,
                width,
                height,
                bands.len(),
                &options,
            )
            .map_err(gdal_err(path))?;
        ds.set_geo_transform(&transform.to_gdal())
            .map_err(gdal_err(path))?;
        let srs = SpatialRef::from_definition(&crs.definition).map_err(gdal_err(path))?;
        ds.set_spatial_ref(&srs).map_err(gdal_err(path))?;
        for (key, value) in metadata {
            ds.set_metadata_item(key, value, "")
                .map_err(gdal_err(path))?;
        }
        for (i, band_out) in bands.iter().enumerate() {
            let mut band = ds.rasterband(i + 1).map_err(gdal_err(path))?;
            band.set_no_data_value(Some(nodata as f64))
                .map_err(gdal_err(path))?;
            band.set_description(band_out.description)
                .map_err(gdal_err(path))?;
            match band_out.values {
                BandValues::Constant(v) => band.fill(v as f64, None).map_err(gdal_err(path))?,
                BandValues::Grid(data) => {
                    assert_eq!(
                        data.len(),
                        width * height,
                        "band {i} of {} has the wrong size",
                        path.display()
                    );
                    // Write in strips of rows so a large raster never needs a second full-size copy.
                    let strip = (4_000_000 / width.max(1)).max(1);
                    for row0 in (0..height).step_by(strip) {
                        let rows = strip.min(height - row0);
                        let values: Vec<f32> = data[row0 * width..(row0 + rows) * width]
                            .iter()
                            .map(|&v| if v.is_finite() { v } else { nodata })
                            .collect();
                        let mut buffer = Buffer::new((width, rows), values);
                        band.write((0, row0 as isize), (width, rows), &mut buffer)
                            .map_err(gdal_err(path))?;
                    }
                }
            }
        }
        ds.close().map_err(gdal_err(path))?;
    }
    std::fs::rename(&tmp, path).map_err(|e| RasterError::Gdal {
        path: path.to_path_buf(),
        reason: e.to_string(),
    })
}

/// Convenience: write a single-band [`Raster`].
pub fn write_raster(
    path: &Path,
    raster: &Raster,
    metadata: &[(&str, String)],
) -> Result<(), RasterError> {
    let layout = RasterLayout {
        width: raster.width,
        height: raster.height,
        transform: raster.transform,
        crs: &raster.crs,
        nodata: raster.nodata,
    };
    write_geotiff(
        path,
        &layout,
        &[BandOut {
            values: BandValues::Grid(&raster.data),
            description: &raster.description,
        }],
        metadata,
    )
}

/// Separable Gaussian blur (kernel ±3σ, edges clamped) of a row-major `w × h` grid: the world's DEM smoothing
/// and the novel-view renderer's PSF. Sums in f64; σ ≤ 0 returns the input.
pub fn gaussian_blur(data: &[f32], w: usize, h: usize, sigma: f64) -> Vec<f32> {
    if sigma <= 0.0 {
        return data.to_vec();
    }
    let radius = (3.0 * sigma).ceil() as i64;
    let kernel: Vec<f64> = (-radius..=radius)
        .map(|k| (-(k * k) as f64 / (2.0 * sigma * sigma)).exp())
        .collect();
    let norm: f64 = kernel.iter().sum();
    let mut tmp = vec![0f32; w * h];
    tmp.par_chunks_mut(w).enumerate().for_each(|(row, out)| {
        for (col, v) in out.iter_mut().enumerate() {
            let s: f64 = kernel
                .iter()
                .enumerate()
                .map(|(k, kv)| {
                    kv * data
                        [row * w + (col as i64 + k as i64 - radius).clamp(0, w as i64 - 1) as usize]
                        as f64
                })
                .sum();
            *v = (s / norm) as f32;
        }
    });
    let mut out = vec![0f32; w * h];
    out.par_chunks_mut(w)
        .enumerate()
        .for_each(|(row, out_row)| {
            for (col, v) in out_row.iter_mut().enumerate() {
                let s: f64 = kernel
                    .iter()
                    .enumerate()
                    .map(|(k, kv)| {
                        kv * tmp[(row as i64 + k as i64 - radius).clamp(0, h as i64 - 1) as usize
                            * w
                            + col] as f64
                    })
                    .sum();
                *v = (s / norm) as f32;
            }
        });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pixel_center_roundtrip() {
        let gt = GeoTransform::north_up(1000.0, 5000.0, 5.0);
        assert_eq!(gt.pixel_center(0.0, 0.0), (1002.5, 4997.5));
        let (c, r) = gt.map_to_pixel(1002.5 + 5.0 * 7.0, 4997.5 - 5.0 * 3.0);
        assert!((c - 7.0).abs() < 1e-12 && (r - 3.0).abs() < 1e-12);
    }

    #[test]
    fn bounds_are_the_outer_pixel_edges() {
        // 7 × 4 cells of 5 m, top-left corner at (1000, 5000): x spans 35 m, y spans 20 m downwards.
        let gt = GeoTransform::north_up(1000.0, 5000.0, 5.0);
        assert_eq!(gt.bounds(7, 4), (1000.0, 4980.0, 1035.0, 5000.0));
        // A south-up grid (positive pixel height) gives the same kind of extent, min before max.
        let south_up = GeoTransform {
            pixel_height: 5.0,
            ..gt
        };
        assert_eq!(south_up.bounds(7, 4), (1000.0, 5000.0, 1035.0, 5020.0));
    }

    #[test]
    fn bilinear_is_exact_on_planes() {
        let (w, h) = (6, 5);
        let data: Vec<f32> = (0..w * h)
            .map(|i| (2 * (i % w) + 3 * (i / w)) as f32)
            .collect();
        let v = bilinear(&data, w, h, 2.25, 1.5);
        assert!((v - (2.0 * 2.25 + 3.0 * 1.5) as f32).abs() < 1e-5);
    }

    #[test]
    fn geotiff_roundtrip_keeps_crs_transform_and_nodata() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.tif");
        let crs = LunarCrs::equirectangular(-43.3, -11.2);
        let mut raster = Raster::new(
            7,
            4,
            GeoTransform::north_up(-1000.0, -1_300_000.0, 5.0),
            crs,
            1.5,
        );
        raster.data[3] = f32::NAN;
        raster.description = "height_m".into();
        write_raster(&path, &raster, &[("UNITS", "m".into())]).unwrap();
        assert!(!crate::files::tmp_path(&path).exists());
        let back = read_raster(&path).unwrap();
        assert_eq!((back.width, back.height), (7, 4));
        assert_eq!(back.transform, raster.transform);
        assert!(back.data[3].is_nan() && back.data[4] == 1.5);
        assert_eq!(back.description, "height_m");
    }

    /// A multi-band raster is band-interleaved: four bands of one value beside a varying band keep the file under
    /// 1.05 × the varying band's alone (pixel interleaving made it grow with every band, as GDAL compressed each
    /// tile again per band), and every band reads back exactly as written.
    #[test]
    fn bands_of_one_value_cost_little_beside_a_varying_band() {
        let dir = tempfile::tempdir().unwrap();
        let crs = LunarCrs::equirectangular(-43.3, -11.2);
        let n = 1024;
        let layout = RasterLayout {
            width: n,
            height: n,
            transform: GeoTransform::north_up(0.0, 0.0, 2.5),
            crs: &crs,
            nodata: -1.0,
        };
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let varying: Vec<f32> = (0..n * n)
            .map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                0.3 + (state >> 40) as f32 / 16_777_216.0 * 0.01
            })
            .collect();
        let band = |values, description| BandOut {
            values,
            description,
        };
        let one = dir.path().join("one.tif");
        write_geotiff(&one, &layout, &[band(BandValues::Grid(&varying), "w")], &[]).unwrap();
        let five = dir.path().join("five.tif");
        let constants = [0.6f32, 2.0, 0.07, 23.0];
        let mut bands = vec![band(BandValues::Grid(&varying), "w")];
        bands.extend(
            constants
                .iter()
                .map(|&v| band(BandValues::Constant(v), "constant")),
        );
        write_geotiff(&five, &layout, &bands, &[]).unwrap();
        let size = |p: &Path| std::fs::metadata(p).unwrap().len() as f64;
        assert!(
            size(&five) < 1.05 * size(&one),
            "five bands {} B, the varying one alone {} B",
            size(&five),
            size(&one)
        );
        let ds = Dataset::open(&five).unwrap();
        assert_eq!(
            ds.metadata_item("INTERLEAVE", "IMAGE_STRUCTURE").as_deref(),
            Some("BAND")
        );
        let back = read_bands(&five).unwrap();
        assert_eq!(back.len(), 5);
        assert!(back[0].data == varying, "the varying band, bit for bit");
        for (b, &v) in back[1..].iter().zip(&constants) {
            assert!(b.data.iter().all(|&x| x == v));
        }
    }

    /// LROC CDR orthos store I/F as Int16 "Scaled I/F" (band scale 3.0518509475997199e-05); DEMs are sometimes
    /// integers with a scale and offset. Both must read back as physical values (to half a quantisation step)
    /// with their nodata as NaN, exactly like the float originals.
    #[test]
    fn integer_rasters_with_scale_offset_read_as_physical_values() {
        use gdal::raster::Buffer;
        use gdal::DriverManager;
        let dir = tempfile::tempdir().unwrap();
        let crs = LunarCrs::equirectangular(-43.3, -11.2);
        let transform = GeoTransform::north_up(-1000.0, -1_300_000.0, 5.0);
        let (w, h) = (9, 5);
        let write =
            |name: &str, raw: Vec<f64>, int16: bool, scale: f64, offset: f64, nodata: f64| {
                let path = dir.path().join(name);
                let driver = DriverManager::get_driver_by_name("GTiff").unwrap();
                let mut ds = if int16 {
                    driver
                        .create_with_band_type::<i16, _>(&path, w, h, 1)
                        .unwrap()
                } else {
                    driver
                        .create_with_band_type::<u16, _>(&path, w, h, 1)
                        .unwrap()
                };
                ds.set_geo_transform(&transform.to_gdal()).unwrap();
                ds.set_spatial_ref(&SpatialRef::from_definition(&crs.definition).unwrap())
                    .unwrap();
                let mut band = ds.rasterband(1).unwrap();
                band.set_scale(scale).unwrap();
                band.set_offset(offset).unwrap();
                band.set_no_data_value(Some(nodata)).unwrap();
                if int16 {
                    let mut buf = Buffer::new((w, h), raw.iter().map(|&v| v as i16).collect());
                    band.write((0, 0), (w, h), &mut buf).unwrap();
                } else {
                    let mut buf = Buffer::new((w, h), raw.iter().map(|&v| v as u16).collect());
                    band.write((0, 0), (w, h), &mut buf).unwrap();
                }
                path
            };
        let n = w * h;
        // I/F 0.01–0.14 as LROC stores it; pixel 7 is nodata (−32768).
        // 1/32767: LROC's published 3.0518509475997199e-05 rounded to f64.
        let scale = 1.0 / 32767.0;
        let truth: Vec<f64> = (0..n).map(|k| 0.01 + 0.003 * k as f64).collect();
        let mut raw: Vec<f64> = truth.iter().map(|v| (v / scale).round()).collect();
        raw[7] = -32768.0;
        let ortho = read_raster(&write("ortho.tif", raw, true, scale, 0.0, -32768.0)).unwrap();
        for (k, (&got, &want)) in ortho.data.iter().zip(&truth).enumerate() {
            if k == 7 {
                assert!(got.is_nan(), "nodata pixel becomes NaN");
            } else {
                let err = (got as f64 - want).abs();
                assert!(err <= scale / 2.0 + 1e-7, "pixel {k}: {got} vs {want}");
            }
        }
        // A UInt16 DEM: height = raw · 0.5 − 4000 m; 0 is nodata.
        let heights: Vec<f64> = (0..n).map(|k| -3500.0 + 37.25 * k as f64).collect();
        let mut raw: Vec<f64> = heights
            .iter()
            .map(|v| ((v + 4000.0) / 0.5).round())
            .collect();
        raw[0] = 0.0;
        let dem = read_raster(&write("dem.tif", raw, false, 0.5, -4000.0, 0.0)).unwrap();
        assert!(dem.data[0].is_nan());
        for (k, (&got, &want)) in dem.data.iter().zip(&heights).enumerate().skip(1) {
            assert!(
                (got as f64 - want).abs() <= 0.25,
                "height {k}: {got} vs {want}"
            );
        }
    }

    /// What cannot be interpreted is refused by name: no CRS, not the Moon, not metres.
    #[test]
    fn uninterpretable_georeferencing_is_refused_by_name() {
        use gdal::DriverManager;
        let dir = tempfile::tempdir().unwrap();
        let write = |name: &str, srs: Option<&str>, gsd: f64| {
            let path = dir.path().join(name);
            let driver = DriverManager::get_driver_by_name("GTiff").unwrap();
            let mut ds = driver
                .create_with_band_type::<f32, _>(&path, 4, 4, 1)
                .unwrap();
            ds.set_geo_transform(&GeoTransform::north_up(10.0, 20.0, gsd).to_gdal())
                .unwrap();
            if let Some(srs) = srs {
                ds.set_spatial_ref(&SpatialRef::from_proj4(srs).unwrap())
                    .unwrap();
            }
            path
        };
        let cases = [
            ("no-crs.tif", None, 5.0, "has no CRS"),
            (
                "earth.tif",
                Some("+proj=eqc +ellps=WGS84 +units=m"),
                5.0,
                "not the lunar sphere",
            ),
            (
                "degrees.tif",
                Some("+proj=longlat +R=1737400 +no_defs"),
                1e-4,
                "degrees",
            ),
            (
                "km.tif",
                Some("+proj=eqc +R=1737400 +units=km"),
                0.005,
                "not metres",
            ),
        ];
        for (name, srs, gsd, expected) in cases {
            let err = open_lunar(&write(name, srs, gsd)).unwrap_err().to_string();
            assert!(
                err.contains(name) && err.contains(expected),
                "{name}: {err}"
            );
        }
        // The same grid in metres opens.
        let ok = write("m.tif", Some("+proj=eqc +R=1737400 +units=m"), 5.0);
        assert_eq!(open_lunar(&ok).unwrap().1.transform.gsd_m(), 5.0);
    }
}

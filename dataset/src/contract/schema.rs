//! The sample schema: one Parquet row = one DEM–image pair. Declared once, here, and documented from here
//! (every field carries `description` and `unit` metadata that pyarrow shows as field metadata).

use std::collections::HashMap;
use std::sync::Arc;

use arrow::array::{
    Array, ArrayRef, FixedSizeListArray, Float32Array, Float64Array, RecordBatch, StringArray,
    UInt8Array,
};
use arrow::datatypes::{DataType, Field, Schema, SchemaRef};

use crate::contract::crater_frame::CraterPosition;

/// Bumped on any incompatible change; readers refuse other major versions.
/// 1.2: `context_dem` + `context_gsd_m` added (readers of 1.2 still read 1.1 shards, without context).
/// 1.3: `crater_rho` + `crater_relative_height_m` added, NaN where the dataset was built without a crater
/// catalogue (readers of 1.3 still read 1.1 and 1.2 shards, without a crater frame).
/// 1.4: `crater_relief_to_diameter` added (readers of 1.4 read 1.3 shards' frames without it).
/// 1.6: `context_highland` added, NaN where the dataset was built without a unit map (readers of 1.6 read older
/// shards without it). 1.5 was the crater frame refined to the rim, reverted before any dataset was published.
pub const SCHEMA_VERSION: &str = "1.6.0";
/// Crop edge in pixels (the network's input/output size).
pub const CROP_PX: usize = 128;
/// DEM edge in pixels: the crop plus a 1-pixel apron on every side, so border normals are exact.
pub const DEM_PX: usize = CROP_PX + 2;
/// Context window edge in cells ([`crate::contract::context`]).
pub const CONTEXT_PX: usize = 32;

/// A `DEM_PX`² crop's interior heights (the `CROP_PX`² cells inside the one-pixel apron), row-major: the cells the
/// image covers, over which the relief's mean and the train DEM statistic are taken.
pub fn crop_interior(dem_m: &[f32]) -> impl Iterator<Item = f64> + Clone + '_ {
    debug_assert_eq!(dem_m.len(), DEM_PX * DEM_PX);
    (1..=CROP_PX).flat_map(move |r| {
        dem_m[r * DEM_PX + 1..=r * DEM_PX + CROP_PX]
            .iter()
            .map(|&h| f64::from(h))
    })
}

/// A coarse, wide DEM window around the crop ([`crate::contract::context`]): what lies kilometres around it.
#[derive(Debug, Clone, PartialEq)]
pub struct ContextWindow {
    /// Cell size, metres.
    pub gsd_m: f64,
    /// CONTEXT_PX² area-mean heights above the sphere, metres, row-major north first, centred on the crop centre;
    /// NaN where less than half a cell has DEM.
    pub heights_m: Vec<f32>,
    /// The same cells' highland fraction (0 mare, 1 highland) from a site's unit map, NaN where less than half a
    /// cell is mapped; `None` when the dataset was built without a unit map (or read from a shard older than
    /// schema 1.6).
    pub highland: Option<Vec<f32>>,
}

/// Which part of a dataset a sample belongs to: tiles are assigned to one split, so no crop footprint touches two.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum Split {
    Train,
    Val,
    Test,
}

impl Split {
    /// In the order shards and tables list them.
    pub const ALL: [Split; 3] = [Split::Train, Split::Val, Split::Test];

    /// The name in shard names, the `split` column, manifests and command lines.
    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Val => "val",
            Split::Test => "test",
        }
    }
}

impl std::fmt::Display for Split {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Split {
    type Err = String;
    fn from_str(text: &str) -> Result<Self, String> {
        Split::ALL
            .into_iter()
            .find(|s| s.name() == text)
            .ok_or_else(|| format!("unknown split '{text}': use train, val or test"))
    }
}

/// One training sample. Tensors are row-major, north row first.
#[derive(Debug, Clone, PartialEq)]
pub struct Sample {
    /// Stable id: `{ortho_id}:{center_col}:{center_row}` in DEM pixels.
    pub sample_id: String,
    pub split: Split,
    pub tile_id: String,
    pub ortho_id: String,
    pub center_x_m: f64,
    pub center_y_m: f64,
    pub center_lon_deg: f64,
    pub center_lat_deg: f64,
    /// Footprint corners (NW, NE, SE, SW) as lon, lat pairs in degrees.
    pub footprint_lonlat_deg: [f64; 8],
    /// DEM_PX² heights above the lunar sphere, metres.
    pub dem_m: Vec<f32>,
    /// CROP_PX² reflectance (I/F), NaN-free (invalid pixels hold 0 and are masked by `valid`).
    pub image: Vec<f32>,
    /// CROP_PX² mask: 1 where the image pixel is usable.
    pub valid: Vec<u8>,
    /// CROP_PX² visible fraction of the sun disk, from the full DEM.
    pub sun_lit: Vec<f32>,
    pub sun_dir_enu: [f64; 3],
    pub camera_pos_enu_m: [f64; 3],
    /// Height above the sphere of the local ENU frame's origin (the crop centre), metres. DEM heights minus this
    /// are the ENU-relative heights the renderer uses (f32-safe, unlike absolute heights in body-fixed metres).
    pub enu_origin_height_m: f64,
    /// Map offset (dx, dy) in metres → (east, north) ground metres at the crop centre, row-major
    /// `[de/dx, de/dy, dn/dx, dn/dy]` (projection scale and meridian convergence; identity on a true-scale grid).
    pub map_to_en: [f64; 4],
    /// Camera attitude quaternion (w, x, y, z), body-fixed to camera.
    pub camera_att: [f64; 4],
    pub fov_deg: f64,
    pub gsd_m: f64,
    pub incidence_deg: f64,
    pub emission_deg: f64,
    pub phase_deg: f64,
    /// Acquisition time, ISO 8601 UTC, from the image metadata.
    pub acq_time: String,
    /// Pipeline code version and params hash that produced the row.
    pub provenance: String,
    /// The terrain around the crop. Always written; `None` when read from a schema 1.1 shard (or when only the
    /// metadata columns were read).
    pub context: Option<ContextWindow>,
    /// Where the crop lies in the frame of the nearest large catalogued crater ([`crate::contract::crater_frame`]);
    /// `None` when the dataset was built without a crater catalogue, or read from a shard older than schema 1.3.
    pub crater: Option<CraterPosition>,
}

impl Sample {
    /// Where the sample's pixels sit in its crop's ENU frame.
    pub fn crop_grid(&self) -> crate::science::geometry::CropGrid {
        crate::science::geometry::CropGrid {
            gsd_m: self.gsd_m,
            map_to_en: self.map_to_en,
            origin_height_m: self.enu_origin_height_m,
        }
    }

    /// Per-pixel geometry of the crop (scalar reference), from the stored heights, sun and camera.
    pub fn pixel_geometry(&self) -> Vec<crate::science::geometry::PixelGeometry> {
        let relative: Vec<f64> = self
            .dem_m
            .iter()
            .map(|&h| h as f64 - self.enu_origin_height_m)
            .collect();
        crate::science::geometry::crop_pixel_geometry(
            &relative,
            CROP_PX,
            &self.crop_grid(),
            self.sun_dir_enu.into(),
            self.camera_pos_enu_m.into(),
        )
    }
}

fn field(name: &str, data_type: DataType, description: &str, unit: &str) -> Field {
    Field::new(name, data_type, false).with_metadata(HashMap::from([
        ("description".to_string(), description.to_string()),
        ("unit".to_string(), unit.to_string()),
    ]))
}

fn fixed_list(item: DataType, len: usize) -> DataType {
    DataType::FixedSizeList(Arc::new(Field::new("item", item, false)), len as i32)
}

/// Float tensor columns (written with BYTE_STREAM_SPLIT).
pub const FLOAT_TENSOR_COLUMNS: [&str; 5] =
    ["dem", "image", "sun_lit", "context_dem", "context_highland"];

pub fn sample_schema() -> SchemaRef {
    let fields = vec![
        field(
            "sample_id",
            DataType::Utf8,
            "stable id: ortho_id:center_col:center_row (DEM pixels)",
            "",
        ),
        field("split", DataType::Utf8, "train | val | test", ""),
        field(
            "tile_id",
            DataType::Utf8,
            "geographic split tile containing the footprint",
            "",
        ),
        field("ortho_id", DataType::Utf8, "source orthoimage id", ""),
        field(
            "center_x",
            DataType::Float64,
            "crop centre, map x (pixel-centre convention)",
            "m",
        ),
        field("center_y", DataType::Float64, "crop centre, map y", "m"),
        field(
            "center_lon",
            DataType::Float64,
            "crop centre longitude, planetocentric",
            "deg",
        ),
        field(
            "center_lat",
            DataType::Float64,
            "crop centre latitude, planetocentric",
            "deg",
        ),
        field(
            "footprint_lonlat",
            fixed_list(DataType::Float64, 8),
            "footprint corners NW,NE,SE,SW as lon,lat",
            "deg",
        ),
        field(
            "dem",
            fixed_list(DataType::Float32, DEM_PX * DEM_PX),
            "130x130 heights above the 1737400 m sphere, 1-px apron, row-major north first",
            "m",
        ),
        field(
            "image",
            fixed_list(DataType::Float32, CROP_PX * CROP_PX),
            "128x128 reflectance I/F, 0 where not valid",
            "1",
        ),
        field(
            "valid",
            fixed_list(DataType::UInt8, CROP_PX * CROP_PX),
            "128x128 mask, 1 = usable pixel",
            "1",
        ),
        field(
            "sun_lit",
            fixed_list(DataType::Float32, CROP_PX * CROP_PX),
            "128x128 visible fraction of the sun disk from the full DEM",
            "1",
        ),
        field(
            "sun_dir_enu",
            fixed_list(DataType::Float64, 3),
            "unit vector toward the sun in the crop's local ENU frame",
            "1",
        ),
        field(
            "camera_pos_enu",
            fixed_list(DataType::Float64, 3),
            "camera position in the crop's local ENU frame",
            "m",
        ),
        field(
            "enu_origin_height_m",
            DataType::Float64,
            "height above the sphere of the local ENU frame origin (crop centre)",
            "m",
        ),
        field(
            "map_to_en",
            fixed_list(DataType::Float64, 4),
            "map offset to ground east/north at the crop centre: de/dx, de/dy, dn/dx, dn/dy",
            "1",
        ),
        field(
            "camera_att",
            fixed_list(DataType::Float64, 4),
            "camera attitude quaternion w,x,y,z (body-fixed to camera)",
            "1",
        ),
        field("fov_deg", DataType::Float64, "camera field of view", "deg"),
        field(
            "gsd_m",
            DataType::Float64,
            "crop ground sample distance",
            "m",
        ),
        field(
            "incidence_deg",
            DataType::Float64,
            "sun incidence at the crop centre on the sphere",
            "deg",
        ),
        field(
            "emission_deg",
            DataType::Float64,
            "emission at the crop centre on the sphere",
            "deg",
        ),
        field(
            "phase_deg",
            DataType::Float64,
            "phase angle at the crop centre",
            "deg",
        ),
        field(
            "acq_time",
            DataType::Utf8,
            "acquisition time, ISO 8601 UTC",
            "",
        ),
        field(
            "provenance",
            DataType::Utf8,
            "pipeline code version and params hash",
            "",
        ),
        field(
            "context_dem",
            fixed_list(DataType::Float32, CONTEXT_PX * CONTEXT_PX),
            "32x32 area-mean heights above the 1737400 m sphere around the crop centre, context_gsd_m cells, row-major north first, NaN where under half a cell has DEM",
            "m",
        ),
        field(
            "context_gsd_m",
            DataType::Float64,
            "context_dem cell size",
            "m",
        ),
        field(
            "crater_rho",
            DataType::Float64,
            "ground distance of the crop centre from the nearest catalogued large crater's centre, in its radii; NaN without a crater catalogue",
            "1",
        ),
        field(
            "crater_relative_height_m",
            DataType::Float64,
            "crop mean height minus that crater's azimuthal median DEM profile at crater_rho (at 3 radii past them); NaN without a crater catalogue",
            "m",
        ),
        field(
            "crater_relief_to_diameter",
            DataType::Float64,
            "that crater's relief (its profile's highest ring within 1.5 radii minus its lowest within 1) over its catalogued diameter, the depth/diameter measure of its wear; NaN without a crater catalogue",
            "1",
        ),
        field(
            "context_highland",
            fixed_list(DataType::Float32, CONTEXT_PX * CONTEXT_PX),
            "the context_dem cells' highland fraction (0 mare, 1 highland) from the site's unit map, NaN where under half a cell is mapped or without a unit map",
            "1",
        ),
    ];
    let metadata = HashMap::from([
        ("g2r.schema_version".to_string(), SCHEMA_VERSION.to_string()),
        ("g2r.crop_px".to_string(), CROP_PX.to_string()),
        ("g2r.dem_px".to_string(), DEM_PX.to_string()),
        ("g2r.context_px".to_string(), CONTEXT_PX.to_string()),
    ]);
    Arc::new(Schema::new_with_metadata(fields, metadata))
}

#[derive(Debug, thiserror::Error)]
pub enum SchemaError {
    #[error("column '{0}' is missing or has the wrong type")]
    Column(&'static str),
    #[error("tensor '{name}' has {got} values, expected {expected}")]
    TensorLength {
        name: &'static str,
        got: usize,
        expected: usize,
    },
    #[error(
        "sample '{0}' has no context window; every written sample carries one (dataset::contract::context)"
    )]
    MissingContext(String),
    #[error("sample '{sample}' has split '{split}'; a split is train, val or test")]
    Split { sample: String, split: String },
    #[error(transparent)]
    Arrow(#[from] arrow::error::ArrowError),
}

fn f64s(values: impl Iterator<Item = f64>) -> ArrayRef {
    Arc::new(Float64Array::from_iter_values(values))
}

fn strings<'a>(values: impl Iterator<Item = &'a str>) -> ArrayRef {
    Arc::new(StringArray::from_iter_values(values))
}

fn list_of(values: ArrayRef, len: usize, item: DataType) -> ArrayRef {
    Arc::new(FixedSizeListArray::new(
        Arc::new(Field::new("item", item, false)),
        len as i32,
        values,
        None,
    ))
}

fn check_len(name: &'static str, got: usize, expected: usize) -> Result<(), SchemaError> {
    (got == expected)
        .then_some(())
        .ok_or(SchemaError::TensorLength {
            name,
            got,
            expected,
        })
}

/// Build one record batch from samples (all tensors length-checked).
pub fn samples_to_batch(samples: &[Sample]) -> Result<RecordBatch, SchemaError> {
    for s in samples {
        check_len("dem", s.dem_m.len(), DEM_PX * DEM_PX)?;
        check_len("image", s.image.len(), CROP_PX * CROP_PX)?;
        check_len("valid", s.valid.len(), CROP_PX * CROP_PX)?;
        check_len("sun_lit", s.sun_lit.len(), CROP_PX * CROP_PX)?;
        let context = s
            .context
            .as_ref()
            .ok_or_else(|| SchemaError::MissingContext(s.sample_id.clone()))?;
        check_len(
            "context_dem",
            context.heights_m.len(),
            CONTEXT_PX * CONTEXT_PX,
        )?;
        if let Some(highland) = &context.highland {
            check_len("context_highland", highland.len(), CONTEXT_PX * CONTEXT_PX)?;
        }
    }
    let contexts = || samples.iter().filter_map(|s| s.context.as_ref());
    let f32_list = |get: fn(&Sample) -> &[f32], len: usize| {
        let flat: Vec<f32> = samples
            .iter()
            .flat_map(|s| get(s).iter().copied())
            .collect();
        list_of(Arc::new(Float32Array::from(flat)), len, DataType::Float32)
    };
    let f64_list = |get: fn(&Sample) -> &[f64], len: usize| {
        let flat: Vec<f64> = samples
            .iter()
            .flat_map(|s| get(s).iter().copied())
            .collect();
        list_of(Arc::new(Float64Array::from(flat)), len, DataType::Float64)
    };
    let valid: Vec<u8> = samples
        .iter()
        .flat_map(|s| s.valid.iter().copied())
        .collect();
    // NaN where a sample's window has no unit map (the column's "absent"), written in place: no per-row vector.
    let mut highland = Vec::with_capacity(samples.len() * CONTEXT_PX * CONTEXT_PX);
    for c in contexts() {
        match &c.highland {
            Some(window) => highland.extend_from_slice(window),
            None => highland.resize(highland.len() + CONTEXT_PX * CONTEXT_PX, f32::NAN),
        }
    }
    let columns: Vec<ArrayRef> = vec![
        strings(samples.iter().map(|s| s.sample_id.as_str())),
        strings(samples.iter().map(|s| s.split.name())),
        strings(samples.iter().map(|s| s.tile_id.as_str())),
        strings(samples.iter().map(|s| s.ortho_id.as_str())),
        f64s(samples.iter().map(|s| s.center_x_m)),
        f64s(samples.iter().map(|s| s.center_y_m)),
        f64s(samples.iter().map(|s| s.center_lon_deg)),
        f64s(samples.iter().map(|s| s.center_lat_deg)),
        f64_list(|s| &s.footprint_lonlat_deg, 8),
        f32_list(|s| &s.dem_m, DEM_PX * DEM_PX),
        f32_list(|s| &s.image, CROP_PX * CROP_PX),
        list_of(
            Arc::new(UInt8Array::from(valid)),
            CROP_PX * CROP_PX,
            DataType::UInt8,
        ),
        f32_list(|s| &s.sun_lit, CROP_PX * CROP_PX),
        f64_list(|s| &s.sun_dir_enu, 3),
        f64_list(|s| &s.camera_pos_enu_m, 3),
        f64s(samples.iter().map(|s| s.enu_origin_height_m)),
        f64_list(|s| &s.map_to_en, 4),
        f64_list(|s| &s.camera_att, 4),
        f64s(samples.iter().map(|s| s.fov_deg)),
        f64s(samples.iter().map(|s| s.gsd_m)),
        f64s(samples.iter().map(|s| s.incidence_deg)),
        f64s(samples.iter().map(|s| s.emission_deg)),
        f64s(samples.iter().map(|s| s.phase_deg)),
        strings(samples.iter().map(|s| s.acq_time.as_str())),
        strings(samples.iter().map(|s| s.provenance.as_str())),
        list_of(
            Arc::new(Float32Array::from(
                contexts()
                    .flat_map(|c| c.heights_m.iter().copied())
                    .collect::<Vec<f32>>(),
            )),
            CONTEXT_PX * CONTEXT_PX,
            DataType::Float32,
        ),
        f64s(contexts().map(|c| c.gsd_m)),
        f64s(samples.iter().map(|s| s.crater.map_or(f64::NAN, |c| c.rho))),
        f64s(
            samples
                .iter()
                .map(|s| s.crater.map_or(f64::NAN, |c| c.relative_height_m)),
        ),
        f64s(samples.iter().map(|s| {
            s.crater
                .and_then(|c| c.relief_to_diameter)
                .unwrap_or(f64::NAN)
        })),
        list_of(
            Arc::new(Float32Array::from(highland)),
            CONTEXT_PX * CONTEXT_PX,
            DataType::Float32,
        ),
    ];
    Ok(RecordBatch::try_new(sample_schema(), columns)?)
}

fn column<'a, T: 'static>(
    batch: &'a RecordBatch,
    name: &'static str,
) -> Result<&'a T, SchemaError> {
    batch
        .column_by_name(name)
        .and_then(|c| c.as_any().downcast_ref::<T>())
        .ok_or(SchemaError::Column(name))
}

fn list_values<'a, T: 'static>(
    batch: &'a RecordBatch,
    name: &'static str,
) -> Result<(&'a T, usize), SchemaError> {
    let list: &FixedSizeListArray = column(batch, name)?;
    let values = list
        .values()
        .as_any()
        .downcast_ref::<T>()
        .ok_or(SchemaError::Column(name))?;
    Ok((values, list.value_length() as usize))
}

/// Decode a record batch back into samples.
pub fn batch_to_samples(batch: &RecordBatch) -> Result<Vec<Sample>, SchemaError> {
    let mut samples = decode(batch)?;
    fill_tensors(batch, &mut samples)?;
    Ok(samples)
}

/// Decode the metadata columns only (a batch read with a projection that leaves out [`TENSOR_COLUMNS`]):
/// the samples' raster fields are empty. For indexes and listings that must not decode 215 KB per row.
pub fn batch_to_sample_metadata(batch: &RecordBatch) -> Result<Vec<Sample>, SchemaError> {
    decode(batch)
}

/// The columns [`fill_tensors`] reads: every per-pixel column, and the context window's cell size.
pub const TENSOR_FILL_COLUMNS: [&str; 7] = [
    "dem",
    "image",
    "valid",
    "sun_lit",
    "context_dem",
    "context_gsd_m",
    "context_highland",
];

/// Set the raster fields (and the context window) of `samples`, row `i` of `batch` into `samples[i]`, from a batch
/// that holds at least [`TENSOR_FILL_COLUMNS`] (a schema 1.1 batch has no context: the samples get none). With the
/// metadata from elsewhere (a server's index), a read of these columns alone gives the whole samples.
pub fn fill_tensors(batch: &RecordBatch, samples: &mut [Sample]) -> Result<(), SchemaError> {
    assert_eq!(
        batch.num_rows(),
        samples.len(),
        "one sample per row of the batch"
    );
    let (dem, dem_len) = list_values::<Float32Array>(batch, "dem")?;
    let (image, img_len) = list_values::<Float32Array>(batch, "image")?;
    let (valid, valid_len) = list_values::<UInt8Array>(batch, "valid")?;
    let (lit, lit_len) = list_values::<Float32Array>(batch, "sun_lit")?;
    check_len("dem", dem_len, DEM_PX * DEM_PX)?;
    check_len("image", img_len, CROP_PX * CROP_PX)?;
    check_len("valid", valid_len, CROP_PX * CROP_PX)?;
    check_len("sun_lit", lit_len, CROP_PX * CROP_PX)?;
    // Absent from schema 1.1 shards: those samples have no context.
    let context = match batch.column_by_name("context_dem") {
        Some(_) => {
            let (heights, len) = list_values::<Float32Array>(batch, "context_dem")?;
            check_len("context_dem", len, CONTEXT_PX * CONTEXT_PX)?;
            Some((heights, column::<Float64Array>(batch, "context_gsd_m")?))
        }
        None => None,
    };
    // Absent from shards older than schema 1.6; all NaN where the dataset was built without a unit map.
    let highland = match batch.column_by_name("context_highland") {
        Some(_) => {
            let (highland, len) = list_values::<Float32Array>(batch, "context_highland")?;
            check_len("context_highland", len, CONTEXT_PX * CONTEXT_PX)?;
            Some(highland)
        }
        None => None,
    };
    for (i, sample) in samples.iter_mut().enumerate() {
        sample.dem_m = slice_row(dem.values(), i, DEM_PX * DEM_PX);
        sample.image = slice_row(image.values(), i, CROP_PX * CROP_PX);
        sample.valid = slice_row(valid.values(), i, CROP_PX * CROP_PX);
        sample.sun_lit = slice_row(lit.values(), i, CROP_PX * CROP_PX);
        sample.context = context.map(|(heights, gsd)| ContextWindow {
            gsd_m: gsd.value(i),
            heights_m: slice_row(heights.values(), i, CONTEXT_PX * CONTEXT_PX),
            highland: highland
                .map(|h| slice_row(h.values(), i, CONTEXT_PX * CONTEXT_PX))
                .filter(|h: &Vec<f32>| h.iter().any(|v| v.is_finite())),
        });
    }
    Ok(())
}

/// Every per-pixel column; everything else is per-sample metadata.
pub const TENSOR_COLUMNS: [&str; 6] = [
    "dem",
    "image",
    "valid",
    "sun_lit",
    "context_dem",
    "context_highland",
];

/// The metadata of every row of `batch`: raster fields empty, no context window ([`fill_tensors`] sets them).
fn decode(batch: &RecordBatch) -> Result<Vec<Sample>, SchemaError> {
    let s = |name| column::<StringArray>(batch, name);
    let f = |name| column::<Float64Array>(batch, name);
    let (sample_id, split, tile_id, ortho_id, acq_time, provenance) = (
        s("sample_id")?,
        s("split")?,
        s("tile_id")?,
        s("ortho_id")?,
        s("acq_time")?,
        s("provenance")?,
    );
    let (cx, cy, clon, clat) = (
        f("center_x")?,
        f("center_y")?,
        f("center_lon")?,
        f("center_lat")?,
    );
    let origin_h = f("enu_origin_height_m")?;
    let (fov, gsd, inc, emi, pha) = (
        f("fov_deg")?,
        f("gsd_m")?,
        f("incidence_deg")?,
        f("emission_deg")?,
        f("phase_deg")?,
    );
    let (foot, _) = list_values::<Float64Array>(batch, "footprint_lonlat")?;
    // Absent from shards older than schema 1.3; NaN in datasets built without a crater catalogue.
    let crater = match (
        batch.column_by_name("crater_rho"),
        batch.column_by_name("crater_relative_height_m"),
    ) {
        (Some(_), Some(_)) => Some((f("crater_rho")?, f("crater_relative_height_m")?)),
        _ => None,
    };
    // Absent from shards older than schema 1.4.
    let relief = match batch.column_by_name("crater_relief_to_diameter") {
        Some(_) => Some(f("crater_relief_to_diameter")?),
        None => None,
    };
    let (sun, _) = list_values::<Float64Array>(batch, "sun_dir_enu")?;
    let (cam, _) = list_values::<Float64Array>(batch, "camera_pos_enu")?;
    let (att, _) = list_values::<Float64Array>(batch, "camera_att")?;
    let (jacobian, _) = list_values::<Float64Array>(batch, "map_to_en")?;
    let arr = |a: &Float64Array, i: usize, n: usize| a.values()[i * n..(i + 1) * n].to_vec();
    let splits = (0..batch.num_rows())
        .map(|i| {
            split
                .value(i)
                .parse::<Split>()
                .map_err(|_| SchemaError::Split {
                    sample: sample_id.value(i).to_string(),
                    split: split.value(i).to_string(),
                })
        })
        .collect::<Result<Vec<Split>, _>>()?;
    Ok((0..batch.num_rows())
        .map(|i| Sample {
            sample_id: sample_id.value(i).to_string(),
            split: splits[i],
            tile_id: tile_id.value(i).to_string(),
            ortho_id: ortho_id.value(i).to_string(),
            center_x_m: cx.value(i),
            center_y_m: cy.value(i),
            center_lon_deg: clon.value(i),
            center_lat_deg: clat.value(i),
            footprint_lonlat_deg: arr(foot, i, 8).try_into().expect("length checked by type"),
            dem_m: Vec::new(),
            image: Vec::new(),
            valid: Vec::new(),
            sun_lit: Vec::new(),
            sun_dir_enu: arr(sun, i, 3).try_into().expect("length checked by type"),
            camera_pos_enu_m: arr(cam, i, 3).try_into().expect("length checked by type"),
            enu_origin_height_m: origin_h.value(i),
            map_to_en: arr(jacobian, i, 4)
                .try_into()
                .expect("length checked by type"),
            camera_att: arr(att, i, 4).try_into().expect("length checked by type"),
            fov_deg: fov.value(i),
            gsd_m: gsd.value(i),
            incidence_deg: inc.value(i),
            emission_deg: emi.value(i),
            phase_deg: pha.value(i),
            acq_time: acq_time.value(i).to_string(),
            provenance: provenance.value(i).to_string(),
            context: None,
            crater: crater.and_then(|(rho, relative)| {
                (rho.value(i).is_finite() && relative.value(i).is_finite()).then(|| {
                    CraterPosition {
                        rho: rho.value(i),
                        relative_height_m: relative.value(i),
                        relief_to_diameter: relief.map(|r| r.value(i)).filter(|r| r.is_finite()),
                    }
                })
            }),
        })
        .collect())
}

fn slice_row<T: Copy>(values: &[T], row: usize, len: usize) -> Vec<T> {
    values[row * len..(row + 1) * len].to_vec()
}

/// A human-readable table of the schema (for `g2r-dataset schema` and the dataset card).
pub fn schema_markdown() -> String {
    let schema = sample_schema();
    let mut out = String::from("| column | type | unit | description |\n|---|---|---|---|\n");
    for f in schema.fields() {
        let md = f.metadata();
        out.push_str(&format!(
            "| `{}` | {} | {} | {} |\n",
            f.name(),
            f.data_type(),
            md.get("unit").map(String::as_str).unwrap_or(""),
            md.get("description").map(String::as_str).unwrap_or("")
        ));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::synthetic_sample;

    #[test]
    fn a_batch_without_newer_columns_reads_as_older_schemas_samples() {
        let samples = vec![synthetic_sample(1), synthetic_sample(2)];
        assert!(samples.iter().all(|s| s.crater.is_some()));
        assert!(samples
            .iter()
            .all(|s| s.context.as_ref().is_some_and(|c| c.highland.is_some())));
        let batch = samples_to_batch(&samples).unwrap();
        assert_eq!(batch_to_samples(&batch).unwrap(), samples);
        // Schema 1.4 had every column but the context's highland fraction; 1.3 nor the crater relief; 1.2 none of
        // the three crater ones; 1.1 neither the two context ones.
        let older = |prefixes: &[&str], dropped: usize| {
            let keep: Vec<usize> = (0..batch.num_columns())
                .filter(|&k| {
                    let name = batch.schema().field(k).name().clone();
                    !prefixes.iter().any(|p| name.starts_with(p))
                })
                .collect();
            assert_eq!(keep.len(), batch.num_columns() - dropped);
            batch_to_samples(&batch.project(&keep).unwrap()).unwrap()
        };
        let without_highland = |s: &Sample| Sample {
            context: s.context.clone().map(|c| ContextWindow {
                highland: None,
                ..c
            }),
            ..s.clone()
        };
        for (read, written) in older(&["context_highland"], 1).iter().zip(&samples) {
            assert_eq!(*read, without_highland(written));
        }
        for (read, written) in older(&["crater_relief", "context_highland"], 2)
            .iter()
            .zip(&samples)
        {
            let crater = written.crater.map(|c| CraterPosition {
                relief_to_diameter: None,
                ..c
            });
            assert_eq!(
                *read,
                Sample {
                    crater,
                    ..without_highland(written)
                }
            );
        }
        for (read, written) in older(&["crater_", "context_highland"], 4)
            .iter()
            .zip(&samples)
        {
            assert_eq!(
                *read,
                Sample {
                    crater: None,
                    ..without_highland(written)
                }
            );
        }
        for (read, written) in older(&["crater_", "context_"], 6).iter().zip(&samples) {
            assert_eq!(
                *read,
                Sample {
                    context: None,
                    crater: None,
                    ..written.clone()
                }
            );
        }
    }

    #[test]
    fn a_sample_without_a_crater_frame_is_written_as_nan_and_read_back_without_one() {
        let mut none = synthetic_sample(3);
        none.crater = None;
        let batch = samples_to_batch(&[synthetic_sample(1), none.clone()]).unwrap();
        let rho = batch
            .column_by_name("crater_rho")
            .unwrap()
            .as_any()
            .downcast_ref::<Float64Array>()
            .unwrap();
        assert_eq!((rho.value(0), rho.null_count()), (0.25, 0));
        assert!(rho.value(1).is_nan());
        assert_eq!(batch_to_samples(&batch).unwrap()[1], none);
    }

    #[test]
    fn writing_a_sample_without_context_or_with_a_wrong_size_window_is_refused() {
        let mut missing = synthetic_sample(3);
        missing.context = None;
        let err = samples_to_batch(&[synthetic_sample(1), missing]).unwrap_err();
        assert!(
            matches!(&err, SchemaError::MissingContext(id) if id == "ortho_3:103:203"),
            "{err}"
        );
        let mut short = synthetic_sample(4);
        short.context.as_mut().unwrap().heights_m.pop();
        assert!(matches!(
            samples_to_batch(&[short]).unwrap_err(),
            SchemaError::TensorLength {
                name: "context_dem",
                ..
            }
        ));
    }
}

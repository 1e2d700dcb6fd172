//! A row of the LROC cumulative index (`INDEX/CUMINDEX.TAB` with its PDS3 label `CUMINDEX.LBL`, or a CSV of the
//! same columns with a header row) → the acquisition geometry.
//!
//! The index gives one sub-spacecraft point and altitude (at the image's centre time), the sub-solar point and
//! distance, the image centre and its four corners on the reference sphere, and the start and stop times. What is
//! derived, and so approximated:
//! - **Spacecraft at the first and last line**: from the sub-spacecraft point, the spacecraft is moved along a
//!   great circle with the strip's heading (its azimuth at the image centre, from the first line's corners to the
//!   last line's) by the angles from the image centre to the first and last lines, at the index altitude: it
//!   flies parallel to the strip it images, as a slewed pushbroom does. Without this, one position for the
//!   whole strip would put the spacecraft up to half a strip length off along-track: on a 25 km NAC strip seen
//!   from 50 km, view vectors up to atan(12.5 / 50) = 14° wrong.
//! - **Attitude**: boresight from the spacecraft at mid-strip to the image centre on the reference sphere, camera
//!   +x along-track; no pitch or yaw.
//! - **Field of view**: the angle the first line's corners subtend at the spacecraft.
//!
//! Longitudes may be in any domain (LROC uses 0–360° east); latitudes are planetocentric; distances are km.

use std::collections::HashMap;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};

use dataset::contract::acquisition::j2000_seconds_from_iso_utc;
use dataset::science::crs::{
    body_fixed_from_lonlat, enu_axes, lonlat_from_body_fixed, MOON_RADIUS_M,
};
use dataset::science::geometry::angle_between;
use glam::{DMat3, DQuat, DVec3};

use super::{ImportError, ImportedGeometry};

/// Columns the importer reads, in the order the synthetic world writes them (after `PRODUCT_ID`).
pub const COLUMNS: [&str; 20] = [
    "PRODUCT_ID",
    "FRAME_ID",
    "START_TIME",
    "STOP_TIME",
    "CENTER_LATITUDE",
    "CENTER_LONGITUDE",
    "UPPER_LEFT_LATITUDE",
    "UPPER_LEFT_LONGITUDE",
    "UPPER_RIGHT_LATITUDE",
    "UPPER_RIGHT_LONGITUDE",
    "LOWER_LEFT_LATITUDE",
    "LOWER_LEFT_LONGITUDE",
    "LOWER_RIGHT_LATITUDE",
    "LOWER_RIGHT_LONGITUDE",
    "SUB_SOLAR_LATITUDE",
    "SUB_SOLAR_LONGITUDE",
    "SOLAR_DISTANCE",
    "SUB_SPACECRAFT_LATITUDE",
    "SUB_SPACECRAFT_LONGITUDE",
    "SPACECRAFT_ALTITUDE",
];

/// An index table opened for lookups: its columns (from the PDS3 label or the header row). Rows are streamed
/// from the file on each lookup and only the matching one is kept: a cumulative index lists every image of the mission.
#[derive(Debug)]
pub struct IndexTable {
    path: PathBuf,
    columns: HashMap<String, usize>,
    layout: Layout,
}

/// How a row's fields are cut.
#[derive(Debug)]
enum Layout {
    /// At the label's byte positions (a PDS3 fixed-width table).
    Fixed(Vec<LabelColumn>),
    /// On commas outside quotes, after a header row (a CSV of the same columns).
    Csv,
}

/// One column of a PDS3 table label.
#[derive(Debug, Clone, PartialEq)]
pub struct LabelColumn {
    pub name: String,
    /// 1-based, as in the label.
    pub start_byte: usize,
    pub bytes: usize,
}

impl IndexTable {
    /// Open `path`: with the PDS3 label `label` (or `path` with a `.LBL`/`.lbl` extension, when present) fields are
    /// cut at the label's byte positions; otherwise the first row must name the columns (CSV).
    pub fn open(path: &Path, label: Option<&Path>) -> Result<Self, ImportError> {
        let io = |p: &Path| {
            let p = p.to_path_buf();
            move |source| ImportError::Io { path: p, source }
        };
        let label = label.map(Path::to_path_buf).or_else(|| {
            ["LBL", "lbl"]
                .iter()
                .map(|ext| path.with_extension(ext))
                .find(|p| p.exists())
        });
        let (names, layout) = match &label {
            Some(label) => {
                let columns = parse_label(&std::fs::read_to_string(label).map_err(io(label))?)
                    .map_err(|problem| ImportError::Invalid {
                        path: label.clone(),
                        problem,
                    })?;
                let names = columns.iter().map(|c| c.name.clone()).collect();
                (names, Layout::Fixed(columns))
            }
            None => {
                let header: Vec<String> = csv_reader(path)?
                    .headers()
                    .map_err(|e| csv_error(path, e))?
                    .iter()
                    .map(clean)
                    .collect();
                if !header.iter().any(|h| h == "PRODUCT_ID") {
                    return Err(ImportError::Invalid {
                        path: path.to_path_buf(),
                        problem: "no PDS3 label next to it (CUMINDEX.LBL) and no header row naming PRODUCT_ID: pass --label".into(),
                    });
                }
                (header, Layout::Csv)
            }
        };
        let columns = names.into_iter().enumerate().map(|(i, n)| (n, i)).collect();
        Ok(Self {
            path: path.to_path_buf(),
            columns,
            layout,
        })
    }

    /// The fields of the row whose `PRODUCT_ID` is `product_id` (the first such row), read by streaming the file.
    pub fn row(&self, product_id: &str) -> Result<Vec<String>, ImportError> {
        let id_column = self.column("PRODUCT_ID")?;
        match &self.layout {
            Layout::Fixed(columns) => {
                let io = |source| ImportError::Io {
                    path: self.path.clone(),
                    source,
                };
                let file = std::fs::File::open(&self.path).map_err(io)?;
                for line in BufReader::new(file).lines() {
                    let fields = fixed_fields(columns, &line.map_err(io)?);
                    if fields.get(id_column).is_some_and(|v| v == product_id) {
                        return Ok(fields);
                    }
                }
            }
            Layout::Csv => {
                for record in csv_reader(&self.path)?.records() {
                    let fields: Vec<String> = record
                        .map_err(|e| csv_error(&self.path, e))?
                        .iter()
                        .map(clean)
                        .collect();
                    if fields.get(id_column).is_some_and(|v| v == product_id) {
                        return Ok(fields);
                    }
                }
            }
        }
        Err(ImportError::Invalid {
            path: self.path.clone(),
            problem: format!("no row with PRODUCT_ID {product_id}"),
        })
    }

    /// The geometry of the row whose `PRODUCT_ID` is `product_id`.
    pub fn geometry(&self, product_id: &str) -> Result<ImportedGeometry, ImportError> {
        let row = self.row(product_id)?;
        row_geometry(&Row {
            table: self,
            row: &row,
            product_id,
        })
    }

    fn column(&self, name: &str) -> Result<usize, ImportError> {
        self.columns
            .get(name)
            .copied()
            .ok_or_else(|| ImportError::field(&self.path, name, "no such column in the index"))
    }
}

struct Row<'a> {
    table: &'a IndexTable,
    row: &'a [String],
    product_id: &'a str,
}

impl Row<'_> {
    fn error(&self, key: &str, problem: impl Into<String>) -> ImportError {
        ImportError::field(
            &self.table.path,
            &format!("{key} (PRODUCT_ID {})", self.product_id),
            problem,
        )
    }

    fn text(&self, key: &str) -> Result<&str, ImportError> {
        let value = self
            .row
            .get(self.table.column(key)?)
            .map(String::as_str)
            .unwrap_or("");
        if value.is_empty() {
            return Err(self.error(key, "empty"));
        }
        Ok(value)
    }

    fn number(
        &self,
        key: &str,
        valid: std::ops::RangeInclusive<f64>,
        unit: &str,
    ) -> Result<f64, ImportError> {
        let text = self.text(key)?;
        let value: f64 = text
            .parse()
            .map_err(|_| self.error(key, format!("'{text}' is not a number")))?;
        if !valid.contains(&value) {
            return Err(self.error(
                key,
                format!("{value} outside {}–{} {unit}", valid.start(), valid.end()),
            ));
        }
        Ok(value)
    }

    fn time(&self, key: &str) -> Result<f64, ImportError> {
        let text = self.text(key)?;
        j2000_seconds_from_iso_utc(text).ok_or_else(|| {
            self.error(
                key,
                format!("'{text}' is not a UTC time (YYYY-MM-DDThh:mm:ss.sss)"),
            )
        })
    }

    /// A point on the reference sphere from `{prefix}_LATITUDE` / `{prefix}_LONGITUDE`, as a unit vector.
    fn direction(&self, prefix: &str) -> Result<DVec3, ImportError> {
        let lat = self.number(&format!("{prefix}_LATITUDE"), -90.0..=90.0, "degrees")?;
        let lon = self.number(&format!("{prefix}_LONGITUDE"), -360.0..=360.0, "degrees")?;
        Ok(body_fixed_from_lonlat(lon, lat, 0.0).normalize())
    }
}

fn row_geometry(row: &Row) -> Result<ImportedGeometry, ImportError> {
    let (start, stop) = (row.time("START_TIME")?, row.time("STOP_TIME")?);
    if stop <= start {
        return Err(row.error("STOP_TIME", "not after START_TIME"));
    }
    let camera_id = match row.text("FRAME_ID")? {
        "LEFT" => "NAC-L".to_string(),
        "RIGHT" => "NAC-R".to_string(),
        other => other.to_string(),
    };
    let solar_distance_km =
        row.number("SOLAR_DISTANCE", 1.0e7..=1.0e9, "km (an AU is 1.496e8 km)")?;
    let altitude_km = row.number("SPACECRAFT_ALTITUDE", 1.0..=1000.0, "km")?;
    let sun = row.direction("SUB_SOLAR")? * solar_distance_km * 1000.0;
    let orbit_radius_m = MOON_RADIUS_M + altitude_km * 1000.0;
    let spacecraft_mid = row.direction("SUB_SPACECRAFT")? * orbit_radius_m;
    let centre = row.direction("CENTER")?;
    let [ul, ur, ll, lr] =
        ["UPPER_LEFT", "UPPER_RIGHT", "LOWER_LEFT", "LOWER_RIGHT"].map(|c| row.direction(c));
    let (ul, ur, ll, lr) = (ul?, ur?, ll?, lr?);
    let first_line = (ul + ur).normalize();
    let last_line = (ll + lr).normalize();
    // Carry the mid-strip spacecraft along its track, heading as the strip heads (see the module docs).
    let heading = tangent_heading(centre, last_line - first_line);
    let up = spacecraft_mid.normalize();
    let (east, north) = east_north(up);
    let track = east * heading.0 + north * heading.1;
    let along_track = |arc: f64| (up * arc.cos() + track * arc.sin()) * orbit_radius_m;
    let spacecraft_start = along_track(-angle_between(centre, first_line));
    let spacecraft_stop = along_track(angle_between(centre, last_line));
    let boresight = (centre * MOON_RADIUS_M - spacecraft_mid).normalize();
    let along = (spacecraft_stop - spacecraft_start).normalize();
    let x_axis = (along - boresight * along.dot(boresight)).normalize();
    let camera_to_body = DQuat::from_mat3(&DMat3::from_cols(
        x_axis,
        boresight.cross(x_axis),
        boresight,
    ));
    let to_corner = |c: DVec3| (c * MOON_RADIUS_M - spacecraft_start).normalize();
    let fov_deg = to_corner(ul)
        .dot(to_corner(ur))
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees();
    Ok(ImportedGeometry {
        product_id: row.product_id.to_string(),
        camera_id,
        start_utc_s: start,
        stop_utc_s: stop,
        sun_body_m: sun,
        spacecraft_start_body_m: spacecraft_start,
        spacecraft_stop_body_m: spacecraft_stop,
        camera_to_body: camera_to_body.normalize(),
        fov_deg,
    })
}

/// Local east and north unit vectors at the point in direction `up` (body-fixed).
fn east_north(up: DVec3) -> (DVec3, DVec3) {
    let (lon, lat, _) = lonlat_from_body_fixed(up * MOON_RADIUS_M);
    let (east, north, _) = enu_axes(lon, lat);
    (east, north)
}

/// The (east, north) unit components of direction `d` in the tangent plane at unit vector `at`.
fn tangent_heading(at: DVec3, d: DVec3) -> (f64, f64) {
    let (east, north) = east_north(at);
    let (e, n) = (d.dot(east), d.dot(north));
    let norm = e.hypot(n);
    (e / norm, n / norm)
}

/// Columns of a PDS3 table label: each `OBJECT = COLUMN` with its `NAME`, `START_BYTE` and `BYTES`.
pub fn parse_label(text: &str) -> Result<Vec<LabelColumn>, String> {
    let mut columns = Vec::new();
    let mut current: Option<(Option<String>, Option<usize>, Option<usize>)> = None;
    for line in text.lines() {
        let Some((key, value)) = line.split_once('=') else {
            continue;
        };
        let (key, value) = (key.trim(), clean(value));
        match (key, &mut current) {
            ("OBJECT", None) if value == "COLUMN" => current = Some((None, None, None)),
            ("END_OBJECT", Some(_)) if value == "COLUMN" => {
                let (name, start, bytes) = current.take().unwrap_or_default();
                match (name, start, bytes) {
                    (Some(name), Some(start_byte), Some(bytes)) if start_byte >= 1 => {
                        columns.push(LabelColumn {
                            name,
                            start_byte,
                            bytes,
                        })
                    }
                    (name, ..) => {
                        return Err(format!(
                            "COLUMN {} lacks NAME, START_BYTE or BYTES",
                            name.unwrap_or_else(|| format!("#{}", columns.len() + 1))
                        ))
                    }
                }
            }
            ("NAME", Some(c)) => c.0 = Some(value),
            ("START_BYTE", Some(c)) => c.1 = value.parse().ok(),
            ("BYTES", Some(c)) => c.2 = value.parse().ok(),
            _ => {}
        }
    }
    if columns.is_empty() {
        return Err("no COLUMN objects: not a PDS3 table label".into());
    }
    Ok(columns)
}

/// A PDS3 label (`CUMINDEX.LBL`, describing `table_file`) of a comma-separated fixed-width table with these
/// columns (name, width in bytes, text?), and the rows formatted to match: what the synthetic world writes. Text
/// fields are quoted and left-aligned, numbers right-aligned; rows end in CR LF, as PDS3 tables do.
pub fn write_table(
    table_file: &str,
    columns: &[(&str, usize, bool)],
    rows: &[Vec<String>],
) -> (String, String) {
    let mut objects = String::new();
    let mut start = 1;
    for (name, width, text) in columns {
        let data_type = match (*text, name.ends_with("_TIME")) {
            (true, _) => "CHARACTER",
            (false, true) => "TIME",
            (false, false) => "ASCII_REAL",
        };
        // A text field's bytes start after its opening quote.
        let field_start = start + *text as usize;
        objects.push_str(&format!(
            "  OBJECT = COLUMN\r\n    NAME = {name}\r\n    DATA_TYPE = {data_type}\r\n    START_BYTE = {field_start}\r\n    BYTES = {width}\r\n  END_OBJECT = COLUMN\r\n"
        ));
        start += width + 2 * *text as usize + 1;
    }
    // `start` − 1 counts every field and one comma after each; a row has one comma fewer, plus CR LF.
    let row_bytes = start - 1 - 1 + 2;
    let label = format!(
        "PDS_VERSION_ID = PDS3\r\nRECORD_TYPE = FIXED_LENGTH\r\nRECORD_BYTES = {row_bytes}\r\nFILE_RECORDS = {rows}\r\n\
^INDEX_TABLE = \"{table_file}\"\r\nOBJECT = INDEX_TABLE\r\n  INTERCHANGE_FORMAT = ASCII\r\n  ROWS = {rows}\r\n\
  ROW_BYTES = {row_bytes}\r\n  COLUMNS = {columns}\r\n{objects}END_OBJECT = INDEX_TABLE\r\nEND\r\n",
        rows = rows.len(),
        columns = columns.len(),
    );
    let table = rows
        .iter()
        .map(|row| {
            let fields: Vec<String> = row
                .iter()
                .zip(columns)
                .map(|(v, &(_, w, text))| {
                    if text {
                        format!("\"{v:<w$}\"")
                    } else {
                        format!("{v:>w$}")
                    }
                })
                .collect();
            fields.join(",") + "\r\n"
        })
        .collect();
    (label, table)
}

/// A field without its quotes and padding.
fn clean(field: &str) -> String {
    field.trim().trim_matches('"').trim().to_string()
}

/// A PDS3 fixed-width line's fields, cut at the label's byte positions.
fn fixed_fields(columns: &[LabelColumn], line: &str) -> Vec<String> {
    let bytes = line.as_bytes();
    columns
        .iter()
        .map(|c| {
            let from = (c.start_byte - 1).min(bytes.len());
            let to = (from + c.bytes).min(bytes.len());
            clean(&String::from_utf8_lossy(&bytes[from..to]))
        })
        .collect()
}

/// A reader of an index exported as CSV: a header row, quoted fields, rows of any length (a short row is caught
/// where its missing field is asked for, with the field's name).
fn csv_reader(path: &Path) -> Result<csv::Reader<std::fs::File>, ImportError> {
    csv::ReaderBuilder::new()
        .flexible(true)
        .from_path(path)
        .map_err(|e| csv_error(path, e))
}

fn csv_error(path: &Path, error: csv::Error) -> ImportError {
    match error.into_kind() {
        csv::ErrorKind::Io(source) => ImportError::Io {
            path: path.to_path_buf(),
            source,
        },
        kind => ImportError::Invalid {
            path: path.to_path_buf(),
            problem: format!("not a readable CSV index: {kind:?}"),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn label_and_table_round_trip() {
        let columns = [
            ("PRODUCT_ID", 10, true),
            ("SOLAR_DISTANCE", 14, false),
            ("FRAME_ID", 5, true),
        ];
        let rows = vec![
            vec!["M1".to_string(), "1.5e8".to_string(), "LEFT".to_string()],
            vec!["M22, b".to_string(), "-3".to_string(), "RIGHT".to_string()],
        ];
        let (label, table) = write_table("CUMINDEX.TAB", &columns, &rows);
        assert!(table
            .lines()
            .all(|l| l.len() + 2 == 10 + 2 + 1 + 14 + 1 + 5 + 2 + 2));
        assert!(label.contains("ROW_BYTES = 37"), "{label}");
        let parsed = parse_label(&label).unwrap();
        assert_eq!(parsed.len(), 3);
        assert_eq!(
            parsed[0],
            LabelColumn {
                name: "PRODUCT_ID".into(),
                start_byte: 2,
                bytes: 10
            }
        );
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("CUMINDEX.TAB"), &table).unwrap();
        std::fs::write(dir.path().join("CUMINDEX.LBL"), &label).unwrap();
        let t = IndexTable::open(&dir.path().join("CUMINDEX.TAB"), None).unwrap();
        assert_eq!(t.row("M1").unwrap(), rows[0]);
        assert_eq!(t.row("M22, b").unwrap(), rows[1]);
        assert!(t
            .row("M3")
            .unwrap_err()
            .to_string()
            .contains("no row with PRODUCT_ID M3"));
        // The same rows as CSV with a header: the comma inside quotes stays in its field.
        let csv = format!(
            "PRODUCT_ID,SOLAR_DISTANCE,FRAME_ID\n{}",
            table.replace("\r\n", "\n")
        );
        std::fs::write(dir.path().join("index.csv"), csv).unwrap();
        let t = IndexTable::open(&dir.path().join("index.csv"), None).unwrap();
        assert_eq!(t.row("M1").unwrap(), rows[0]);
        assert_eq!(t.row("M22, b").unwrap(), rows[1]);
    }
}

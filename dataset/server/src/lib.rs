//! `g2r-dataset serve`: a read-only HTTP API over one published dataset, a directory or a prefix in object storage
//! (axum + tower-http; [`dataset::storage`]).
//!
//! Nothing outside the dataset can be served: shards are looked up by exact name in the manifest's list (never
//! joined from a request path), and every other endpoint answers from the in-memory [`index::DatasetIndex`].
//! File and bucket reads run on tokio's blocking pool so slow disks and slow links never stall the event loop.
//!
//! | endpoint | answer |
//! |---|---|
//! | `GET /` | HTML viewer |
//! | `GET /v1/info` | name, schema, counts, manifest blake3, dataset card |
//! | `GET /v1/splits` | per split: rows, shards, row groups |
//! | `GET /v1/rows?split=&offset=&length=[&tensors=base64]` | rows in the split's order (length ≤ 100) |
//! | `GET /v1/filter?[split=][&tile=][&bbox=lon0,lat0,lon1,lat1][&limit=]` | matching rows' metadata |
//! | `GET /v1/tiles` | split tiles with counts and bounds |
//! | `GET /v1/samples/{id}` and `/v1/samples/{id}/{dem,image,lit,context}.png` | one row, previews |
//! | `GET /v1/shards/{name}` | the shard's bytes, HTTP Range supported (pyarrow/polars/DuckDB remote reads) |
//! | `GET /v1/shards/{name}/row-groups/{i}` | one row group as an Arrow IPC stream |
//! | `GET /v1/row-groups?split=` | the split's row groups in order (what the trainer's planner shuffles) |
//! | `GET /v1/stream?split=&seed=&epoch=[&rank=&world=&window=]` | a training epoch as an Arrow IPC stream, rows in the planner's order |
//! | `GET /v1/manifest`, `/v1/croissant` | `manifest.json`, Croissant JSON-LD |

pub mod cache;
pub mod index;
pub mod loadtest;
pub mod preview;
pub mod tensors;

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::sync::Arc;

use axum::body::{Body, Bytes};
use axum::extract::{Path as UrlPath, Query, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::get;
use axum::{Json, Router};
use tower::ServiceExt;

use dataset::contract::planner::plan_epoch;
use dataset::contract::schema::Sample;
use dataset::storage::{DatasetLocation, RemoteDir};
use index::DatasetIndex;
use preview::Preview;

/// Most rows one `/v1/rows` request may ask for (tensors of 100 rows ≈ 21 MB as base64).
pub const MAX_ROWS_PER_REQUEST: usize = 100;
/// Most rows `/v1/filter` lists (it returns the total count too).
pub const MAX_FILTER_ROWS: usize = 1000;
// The media type of Arrow IPC streams: its one home is the client.
use dataset::client::ARROW_STREAM;
/// Most row groups one `/v1/stream` window may hold (≈ 55 MB decoded each).
pub const MAX_STREAM_WINDOW: usize = 8;
/// Epoch streams running at once; more wait their turn (each holds up to a window, a few hundred MB).
const CONCURRENT_STREAMS: usize = 2;

/// Tensor pages and previews built at once: as many as there are cores. Each is a burst of decoding and encoding;
/// more at once only time-slice the cores, and every other request's answer waits behind them.
fn raster_permits() -> &'static tokio::sync::Semaphore {
    static PERMITS: std::sync::OnceLock<tokio::sync::Semaphore> = std::sync::OnceLock::new();
    PERMITS.get_or_init(|| {
        tokio::sync::Semaphore::new(std::thread::available_parallelism().map_or(2, usize::from))
    })
}

/// Limits the epoch streams running at once, whatever clients ask for.
static STREAM_PERMITS: tokio::sync::Semaphore =
    tokio::sync::Semaphore::const_new(CONCURRENT_STREAMS);

const VIEWER_HTML: &str = include_str!("viewer.html");

/// An error answer: status and a one-line message, sent as `{"error": message}`.
#[derive(Debug)]
pub struct ApiError(StatusCode, String);

impl ApiError {
    fn bad_request(message: impl Into<String>) -> Self {
        Self(StatusCode::BAD_REQUEST, message.into())
    }
    fn not_found(message: impl Into<String>) -> Self {
        Self(StatusCode::NOT_FOUND, message.into())
    }
    fn internal(error: impl std::fmt::Display) -> Self {
        tracing::error!("{error}");
        Self(StatusCode::INTERNAL_SERVER_ERROR, error.to_string())
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        (self.0, Json(serde_json::json!({ "error": self.1 }))).into_response()
    }
}

type ApiResult<T> = Result<T, ApiError>;
type Params = Query<BTreeMap<String, String>>;
type Shared = State<Arc<DatasetIndex>>;

/// The router over a loaded index (tests and `serve` both use it).
pub fn router(index: Arc<DatasetIndex>) -> Router {
    Router::new()
        .route("/", get(viewer))
        .route("/v1/info", get(info))
        .route("/v1/splits", get(splits))
        .route("/v1/rows", get(rows))
        .route("/v1/filter", get(filter))
        .route("/v1/tiles", get(tiles))
        .route("/v1/samples/{id}", get(sample))
        .route("/v1/samples/{id}/{file}", get(sample_preview))
        .route("/v1/shards/{name}", get(shard_file))
        .route("/v1/shards/{name}/row-groups/{group}", get(row_group_ipc))
        .route("/v1/row-groups", get(row_groups))
        .route("/v1/stream", get(epoch_stream))
        .route("/v1/manifest", get(manifest))
        .route("/v1/croissant", get(croissant))
        .fallback(|| async {
            ApiError::not_found("no such endpoint; GET /v1/info lists the dataset, / is the viewer")
        })
        .with_state(index)
}

/// How `serve` treats the dataset.
#[derive(Debug, Clone, Copy)]
pub struct ServeOptions {
    /// Hash every shard against `manifest.json` before serving (sizes are always checked).
    pub verify_hashes: bool,
    /// Bytes of decoded rows and previews kept between requests ([`cache`]).
    pub cache_bytes: u64,
}

impl Default for ServeOptions {
    fn default() -> Self {
        Self {
            verify_hashes: false,
            cache_bytes: cache::DEFAULT_CACHE_MIB << 20,
        }
    }
}

/// Serve the dataset at `location` (a directory, or an object-storage URL such as `s3://bucket/prefix`) on `addr`
/// until Ctrl-C; `ready` is called with the bound address (port 0 picks a free one).
pub async fn serve(
    location: &str,
    addr: SocketAddr,
    options: ServeOptions,
    ready: impl FnOnce(SocketAddr),
) -> anyhow::Result<()> {
    let index = tokio::task::block_in_place(|| {
        DatasetIndex::load(
            DatasetLocation::open(location)?,
            options.verify_hashes,
            options.cache_bytes,
        )
    })?;
    tracing::info!(
        rows = index.rows.len(),
        shards = index.shards.len(),
        "loaded {}",
        index.location.describe()
    );
    let listener = tokio::net::TcpListener::bind(addr)
        .await
        .map_err(|e| anyhow::anyhow!("{addr}: cannot listen ({e}); pick another --addr port"))?;
    ready(listener.local_addr()?);
    axum::serve(listener, router(Arc::new(index)))
        .with_graceful_shutdown(async {
            let _ = tokio::signal::ctrl_c().await;
        })
        .await?;
    Ok(())
}

/// Run blocking file work off the event loop.
async fn blocking<T: Send + 'static>(
    work: impl FnOnce() -> anyhow::Result<T> + Send + 'static,
) -> ApiResult<T> {
    tokio::task::spawn_blocking(work)
        .await
        .map_err(ApiError::internal)?
        .map_err(ApiError::internal)
}

fn param<'a>(params: &'a BTreeMap<String, String>, name: &str) -> Option<&'a str> {
    params.get(name).map(String::as_str)
}

/// A non-negative integer query parameter, or `default` when absent.
fn integer(params: &BTreeMap<String, String>, name: &str, default: Option<u64>) -> ApiResult<u64> {
    match (param(params, name), default) {
        (Some(text), _) => text.parse::<u64>().map_err(|_| {
            ApiError::bad_request(format!(
                "'{name}' must be a non-negative integer, got '{text}'"
            ))
        }),
        (None, Some(d)) => Ok(d),
        (None, None) => Err(ApiError::bad_request(format!(
            "missing query parameter '{name}'"
        ))),
    }
}

/// The rows of a split, or 404 naming the splits there are.
fn split_rows<'a>(index: &'a DatasetIndex, split: &str) -> ApiResult<&'a [usize]> {
    index.splits.get(split).map(Vec::as_slice).ok_or_else(|| {
        ApiError::not_found(format!(
            "unknown split '{split}'; this dataset has {:?}",
            index.splits.keys().collect::<Vec<_>>()
        ))
    })
}

fn required_split<'a>(
    index: &'a DatasetIndex,
    params: &BTreeMap<String, String>,
) -> ApiResult<(&'a str, &'a [usize])> {
    let split = param(params, "split")
        .ok_or_else(|| ApiError::bad_request("missing query parameter 'split'"))?;
    let (name, _) = index
        .splits
        .get_key_value(split)
        .ok_or_else(|| split_rows(index, split).unwrap_err())?;
    Ok((name.as_str(), split_rows(index, split)?))
}

/// A sample's metadata as JSON (column names as in the schema) plus where it lives, serialised straight from the
/// index (fields in alphabetical order, as a JSON map would list them): the metadata pages are the load's most
/// frequent request, and building a `serde_json::Value` map per row cost more than writing the row.
#[derive(serde::Serialize)]
struct SampleJson<'a> {
    acq_time: &'a str,
    camera_att: [f64; 4],
    camera_pos_enu: [f64; 3],
    center_lat: f64,
    center_lon: f64,
    center_x: f64,
    center_y: f64,
    emission_deg: f64,
    enu_origin_height_m: f64,
    footprint_lonlat: [f64; 8],
    fov_deg: f64,
    gsd_m: f64,
    incidence_deg: f64,
    location: LocationJson<'a>,
    map_to_en: [f64; 4],
    ortho_id: &'a str,
    phase_deg: f64,
    provenance: &'a str,
    sample_id: &'a str,
    split: dataset::contract::schema::Split,
    sun_dir_enu: [f64; 3],
    tile_id: &'a str,
    /// Rasters, in `/v1/rows?tensors=base64` pages only.
    #[serde(skip_serializing_if = "Option::is_none")]
    tensors: Option<tensors::TensorsJson>,
}

#[derive(serde::Serialize)]
struct LocationJson<'a> {
    row: usize,
    row_group: usize,
    shard: &'a str,
}

fn sample_json(index: &DatasetIndex, row: usize) -> SampleJson<'_> {
    let r = &index.rows[row];
    let s = &r.meta;
    SampleJson {
        acq_time: &s.acq_time,
        camera_att: s.camera_att,
        camera_pos_enu: s.camera_pos_enu_m,
        center_lat: s.center_lat_deg,
        center_lon: s.center_lon_deg,
        center_x: s.center_x_m,
        center_y: s.center_y_m,
        emission_deg: s.emission_deg,
        enu_origin_height_m: s.enu_origin_height_m,
        footprint_lonlat: s.footprint_lonlat_deg,
        fov_deg: s.fov_deg,
        gsd_m: s.gsd_m,
        incidence_deg: s.incidence_deg,
        location: LocationJson {
            row: r.row,
            row_group: r.row_group,
            shard: &index.shard_names[r.shard],
        },
        map_to_en: s.map_to_en,
        ortho_id: &s.ortho_id,
        phase_deg: s.phase_deg,
        provenance: &s.provenance,
        sample_id: &s.sample_id,
        split: s.split,
        sun_dir_enu: s.sun_dir_enu,
        tile_id: &s.tile_id,
        tensors: None,
    }
}

async fn viewer() -> Html<&'static str> {
    Html(VIEWER_HTML)
}

async fn info(State(index): Shared) -> Json<serde_json::Value> {
    // The dataset's own schema (an older minor version lacks columns this build writes); this build's for a
    // dataset without shards.
    let dataset_schema = index
        .shards
        .first()
        .map_or_else(dataset::contract::schema::sample_schema, |s| s.schema());
    let schema: Vec<serde_json::Value> = dataset_schema
        .fields()
        .iter()
        .map(|f| {
            serde_json::json!({
                "name": f.name(), "type": f.data_type().to_string(),
                "unit": f.metadata().get("unit"), "description": f.metadata().get("description"),
            })
        })
        .collect();
    let m = &index.manifest;
    Json(serde_json::json!({
        "name": m.name, "license": m.license, "seed": m.seed, "crs": m.crs,
        "schema_version": m.schema_version, "schema": schema,
        "split_counts": m.split_counts, "rows": index.rows.len(), "shards": index.shards.len(),
        "dem_std_m": m.dem_std_m, "manifest_blake3": index.manifest_blake3, "card": index.card,
    }))
}

async fn splits(State(index): Shared) -> Json<serde_json::Value> {
    let splits: Vec<serde_json::Value> = index
        .splits
        .iter()
        .map(|(name, rows)| {
            serde_json::json!({
                "name": name, "rows": rows.len(),
                "shards": index.manifest.split_shards(name),
                "row_groups": index.row_groups.get(name).map_or(0, Vec::len),
            })
        })
        .collect();
    Json(serde_json::json!({ "splits": splits }))
}

async fn rows(State(index): Shared, Query(params): Params) -> ApiResult<Response> {
    let (split, rows) = required_split(&index, &params)?;
    let offset = integer(&params, "offset", Some(0))? as usize;
    let length = integer(&params, "length", Some(20))? as usize;
    if length == 0 || length > MAX_ROWS_PER_REQUEST {
        return Err(ApiError::bad_request(format!(
            "'length' must be 1..={MAX_ROWS_PER_REQUEST}, got {length}; page with 'offset'"
        )));
    }
    let tensors = match param(&params, "tensors") {
        None | Some("none") => false,
        Some("base64") => true,
        Some(other) => {
            return Err(ApiError::bad_request(format!(
                "'tensors' must be 'none' or 'base64', got '{other}'"
            )))
        }
    };
    let selected: Vec<usize> = rows.iter().skip(offset).take(length).copied().collect();
    let page = RowsPage {
        split: split.to_string(),
        offset,
        total: rows.len(),
        selected,
    };
    if !tensors || page.selected.is_empty() {
        return Ok(Json(page.json(&index, &[])).into_response());
    }
    // Rasters as base64 are ~0.35 MB of JSON a row: read, encoded and serialised on the blocking pool, so the
    // event loop's few threads keep answering other requests meanwhile.
    let _permit = raster_permits()
        .acquire()
        .await
        .map_err(ApiError::internal)?;
    let body = blocking(move || {
        let full = index.read_full(&page.selected)?;
        Ok(serde_json::to_vec(&page.json(&index, &full))?)
    })
    .await?;
    Ok(([(header::CONTENT_TYPE, "application/json")], body).into_response())
}

#[derive(serde::Serialize)]
struct PageJson<'a> {
    offset: usize,
    rows: Vec<SampleJson<'a>>,
    split: &'a str,
    total: usize,
}

/// One `/v1/rows` answer: rows `selected` (indices into the index's rows) of a split, from `offset` of `total`.
struct RowsPage {
    split: String,
    offset: usize,
    total: usize,
    selected: Vec<usize>,
}

impl RowsPage {
    /// The page as JSON, each row with its rasters when `full` holds its samples (in `selected`'s order).
    fn json<'a>(&'a self, index: &'a DatasetIndex, full: &[Arc<Sample>]) -> PageJson<'a> {
        let mut rows: Vec<SampleJson> = self
            .selected
            .iter()
            .map(|&r| sample_json(index, r))
            .collect();
        for (row, sample) in rows.iter_mut().zip(full) {
            row.tensors = Some(tensors::TensorsJson::of(sample));
        }
        PageJson {
            offset: self.offset,
            rows,
            split: &self.split,
            total: self.total,
        }
    }
}

/// `lon0,lat0,lon1,lat1` in degrees.
fn parse_bbox(text: &str) -> ApiResult<[f64; 4]> {
    let values: Vec<f64> = text
        .split(',')
        .map(|v| v.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| {
            ApiError::bad_request(format!(
                "'bbox' must be lon0,lat0,lon1,lat1 in degrees, got '{text}'"
            ))
        })?;
    match values[..] {
        [a, b, c, d] if a <= c && b <= d && values.iter().all(|v| v.is_finite()) => Ok([a, b, c, d]),
        _ => Err(ApiError::bad_request(format!(
            "'bbox' must be four finite numbers lon0,lat0,lon1,lat1 with lon0 <= lon1 and lat0 <= lat1, got '{text}'"
        ))),
    }
}

async fn filter(State(index): Shared, Query(params): Params) -> ApiResult<Json<serde_json::Value>> {
    if let Some(split) = param(&params, "split") {
        split_rows(&index, split)?;
    }
    let bbox = param(&params, "bbox").map(parse_bbox).transpose()?;
    let limit = integer(&params, "limit", Some(100))? as usize;
    if limit > MAX_FILTER_ROWS {
        return Err(ApiError::bad_request(format!(
            "'limit' must be at most {MAX_FILTER_ROWS}, got {limit}"
        )));
    }
    let (split, tile) = (param(&params, "split"), param(&params, "tile"));
    let matches: Vec<usize> = (0..index.rows.len())
        .filter(|&i| {
            let s = &index.rows[i].meta;
            split.is_none_or(|v| s.split.name() == v)
                && tile.is_none_or(|v| s.tile_id == v)
                && bbox.is_none_or(|b| {
                    (b[0]..=b[2]).contains(&s.center_lon_deg)
                        && (b[1]..=b[3]).contains(&s.center_lat_deg)
                })
        })
        .collect();
    let listed: Vec<SampleJson> = matches
        .iter()
        .take(limit)
        .map(|&r| sample_json(&index, r))
        .collect();
    Ok(Json(
        serde_json::json!({ "count": matches.len(), "rows": listed }),
    ))
}

async fn tiles(State(index): Shared) -> Json<serde_json::Value> {
    Json(serde_json::json!({ "tiles": index.tiles }))
}

fn row_of(index: &DatasetIndex, id: &str) -> ApiResult<usize> {
    index
        .row_index(id)
        .ok_or_else(|| ApiError::not_found(format!("no sample '{id}' in this dataset")))
}

async fn sample(State(index): Shared, UrlPath(id): UrlPath<String>) -> ApiResult<Response> {
    Ok(Json(sample_json(&index, row_of(&index, &id)?)).into_response())
}

async fn sample_preview(
    State(index): Shared,
    UrlPath((id, file)): UrlPath<(String, String)>,
) -> ApiResult<Response> {
    let preview = Preview::from_file_name(&file).ok_or_else(|| {
        ApiError::not_found(format!(
            "no preview '{file}'; use dem.png, image.png, lit.png or context.png"
        ))
    })?;
    let row = row_of(&index, &id)?;
    let png = match index.cache.preview(row, preview) {
        Some(png) => Some(png),
        None => {
            let _permit = raster_permits()
                .acquire()
                .await
                .map_err(ApiError::internal)?;
            blocking(move || {
                let sample = index.read_full(&[row])?.pop().expect("one row");
                let png = preview::preview_png(&sample, preview).map(Bytes::from);
                if let Some(png) = &png {
                    index.cache.keep_preview(row, preview, png.clone());
                }
                Ok(png)
            })
            .await?
        }
    }
    .ok_or_else(|| {
        ApiError::not_found(format!(
            "sample '{id}' has no context window: the dataset predates schema 1.2; re-publish it for context"
        ))
    })?;
    Ok((
        [
            (header::CONTENT_TYPE, "image/png"),
            (header::CACHE_CONTROL, "max-age=3600"),
        ],
        png,
    )
        .into_response())
}

fn listed_shard(index: &DatasetIndex, name: &str) -> ApiResult<usize> {
    index.shard_by_name(name).ok_or_else(|| {
        ApiError::not_found(format!(
            "no shard '{name}' in manifest.json; GET /v1/splits lists them"
        ))
    })
}

/// The shard's bytes, whole or one byte range (206), as tower-http's `ServeFile` answers for a file: a malformed or
/// unsatisfiable range, or several ranges, get 416.
async fn shard_file(
    State(index): Shared,
    UrlPath(name): UrlPath<String>,
    request: Request,
) -> ApiResult<Response> {
    let shard = listed_shard(&index, &name)?;
    let remote = match &index.location {
        DatasetLocation::Local(_) => {
            let path = index.shards[shard].path().to_path_buf();
            let mime = PARQUET_MIME.parse().expect("a valid media type");
            let response = tower_http::services::ServeFile::new_with_mime(&path, &mime)
                .oneshot(request)
                .await
                .map_err(ApiError::internal)?;
            return Ok(response.map(Body::new));
        }
        DatasetLocation::Remote(remote) => remote.clone(),
    };
    let size = index
        .manifest
        .shards
        .iter()
        .find(|entry| entry.path == name)
        .expect("listed_shard found it in the manifest")
        .bytes;
    let content = [
        (header::CONTENT_TYPE, parquet_mime()),
        (header::ACCEPT_RANGES, HeaderValue::from_static("bytes")),
    ];
    // An empty object has no byte to serve: every range is unsatisfiable (http-range-header would accept 0-0).
    let range = request.headers().get(header::RANGE);
    if size == 0 && range.is_some() {
        return Ok(unsatisfiable(size));
    }
    let Some(range) = range else {
        let body = remote_bytes(remote, name, 0..size);
        return Ok((
            content,
            [(header::CONTENT_LENGTH, HeaderValue::from(size))],
            body,
        )
            .into_response());
    };
    let ranges = range
        .to_str()
        .ok()
        .and_then(|text| http_range_header::parse_range_header(text).ok())
        .and_then(|parsed| parsed.validate(size).ok());
    let Some([range]) = ranges.as_deref() else {
        return Ok(unsatisfiable(size));
    };
    let (first, last) = (*range.start(), *range.end());
    let body = remote_bytes(remote, name, first..last + 1);
    Ok((
        StatusCode::PARTIAL_CONTENT,
        content,
        [
            (header::CONTENT_LENGTH, HeaderValue::from(last + 1 - first)),
            (
                header::CONTENT_RANGE,
                HeaderValue::from_str(&format!("bytes {first}-{last}/{size}"))
                    .expect("digits are a valid header"),
            ),
        ],
        body,
    )
        .into_response())
}

/// 416 for a shard of `size` bytes.
fn unsatisfiable(size: u64) -> Response {
    (
        StatusCode::RANGE_NOT_SATISFIABLE,
        [(header::CONTENT_RANGE, format!("bytes */{size}"))],
        "the range is malformed, lies outside the shard, or asks for several ranges (one is served at a time)",
    )
        .into_response()
}

const PARQUET_MIME: &str = "application/vnd.apache.parquet";

fn parquet_mime() -> HeaderValue {
    HeaderValue::from_static(PARQUET_MIME)
}

/// Bytes `range` of object `name`, streamed in ranged GETs of at most 8 MiB each, so a whole-shard download holds
/// one piece in memory, not the shard.
fn remote_bytes(
    remote: std::sync::Arc<RemoteDir>,
    name: String,
    range: std::ops::Range<u64>,
) -> Body {
    const PIECE: u64 = 8 << 20;
    let end = range.end;
    let pieces = futures_util::stream::try_unfold(range.start, move |at| {
        let (remote, name) = (remote.clone(), name.clone());
        async move {
            if at >= end {
                return Ok(None);
            }
            let to = (at + PIECE).min(end);
            let bytes = tokio::task::spawn_blocking(move || remote.get_range(&name, at..to))
                .await
                .map_err(anyhow::Error::from)??;
            Ok::<_, anyhow::Error>(Some((bytes, to)))
        }
    });
    Body::from_stream(pieces)
}

fn arrow_response(bytes: Vec<u8>) -> Response {
    (
        [(header::CONTENT_TYPE, HeaderValue::from_static(ARROW_STREAM))],
        bytes,
    )
        .into_response()
}

async fn row_group_ipc(
    State(index): Shared,
    UrlPath((name, group)): UrlPath<(String, String)>,
) -> ApiResult<Response> {
    let shard = listed_shard(&index, &name)?;
    let group: usize = group.parse().map_err(|_| {
        ApiError::bad_request(format!(
            "row group must be a non-negative integer, got '{group}'"
        ))
    })?;
    let count = index.shards[shard].row_group_sizes().len();
    if group >= count {
        return Err(ApiError::not_found(format!(
            "{name} has {count} row groups, no row group {group}"
        )));
    }
    let bytes = blocking(move || {
        let batches = index.shards[shard].read_batches(group, None, true)?;
        Ok(dataset::contract::wire::ipc_stream_bytes(&batches)?)
    })
    .await?;
    Ok(arrow_response(bytes))
}

async fn row_groups(
    State(index): Shared,
    Query(params): Params,
) -> ApiResult<Json<serde_json::Value>> {
    let (split, _) = required_split(&index, &params)?;
    let groups: Vec<serde_json::Value> = index
        .row_groups
        .get(split)
        .map_or(&[][..], Vec::as_slice)
        .iter()
        .map(|g| serde_json::json!({ "shard": g.shard, "row_group": g.row_group, "rows": g.rows }))
        .collect();
    Ok(Json(
        serde_json::json!({ "split": split, "row_groups": groups }),
    ))
}

/// One epoch in the trainer's order (`dataset::contract::planner::plan_epoch`), one IPC record batch per shuffle window,
/// streamed as windows are read: memory is one window, whatever the split's size.
async fn epoch_stream(
    State(index): Shared,
    Query(params): Params,
    headers: HeaderMap,
) -> ApiResult<Response> {
    let accept = headers
        .get(header::ACCEPT)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("");
    if !accept.contains(ARROW_STREAM) {
        return Err(ApiError(
            StatusCode::NOT_ACCEPTABLE,
            format!("/v1/stream answers only 'Accept: {ARROW_STREAM}'"),
        ));
    }
    let (split, _) = required_split(&index, &params)?;
    let split = split.to_string();
    let seed = integer(&params, "seed", None)?;
    let epoch = integer(&params, "epoch", None)?;
    let rank = integer(&params, "rank", Some(0))? as usize;
    let world = integer(&params, "world", Some(1))? as usize;
    let window = integer(&params, "window", Some(4))? as usize;
    if world == 0 || rank >= world || world > 1024 {
        return Err(ApiError::bad_request(format!(
            "need 0 <= rank < world <= 1024, got rank {rank} world {world}"
        )));
    }
    if window == 0 || window > MAX_STREAM_WINDOW {
        return Err(ApiError::bad_request(format!(
            "'window' must be 1..={MAX_STREAM_WINDOW} row groups, got {window}"
        )));
    }
    let (sender, mut receiver) = tokio::sync::mpsc::channel::<Result<Vec<u8>, std::io::Error>>(2);
    let permit = STREAM_PERMITS.acquire().await.map_err(ApiError::internal)?;
    tokio::task::spawn_blocking(move || {
        let _permit = permit; // held until this stream is done or its client went away
        let groups = index.row_groups.get(&split).map_or(&[][..], Vec::as_slice);
        let plan = plan_epoch(groups, seed, epoch, window, rank, world);
        let send = |item| sender.blocking_send(item).is_ok();
        let result = (|| -> anyhow::Result<()> {
            // The dataset's own schema (a 1.1 dataset has no context columns), not this build's.
            let schema = index
                .shards
                .first()
                .map_or_else(dataset::contract::schema::sample_schema, |shard| {
                    shard.schema()
                });
            let mut writer = arrow::ipc::writer::StreamWriter::try_new(Vec::new(), &schema)?;
            let mut start = 0;
            for (w, window_groups) in plan.windows.iter().enumerate() {
                let end = start
                    + plan.window_of[start..]
                        .iter()
                        .take_while(|&&x| x == w)
                        .count();
                let mut batches = Vec::new();
                let mut offsets = BTreeMap::new();
                let mut rows_so_far = 0;
                for &g in window_groups {
                    let group = &groups[g];
                    let shard = index
                        .shard_by_name(&group.shard)
                        .expect("row groups come from the index");
                    offsets.insert(g, rows_so_far);
                    for batch in index.shards[shard].read_batches(group.row_group, None, true)? {
                        rows_so_far += batch.num_rows();
                        batches.push(batch);
                    }
                }
                let all = arrow::compute::concat_batches(&schema, &batches)?;
                let take: Vec<u32> = plan.rows[start..end]
                    .iter()
                    .map(|r| (offsets[&r.group] + r.row) as u32)
                    .collect();
                let ordered = arrow::compute::take_record_batch(
                    &all,
                    &arrow::array::UInt32Array::from(take),
                )?;
                writer.write(&ordered)?;
                if !send(Ok(std::mem::take(writer.get_mut()))) {
                    return Ok(()); // client went away
                }
                start = end;
            }
            writer.finish()?;
            send(Ok(std::mem::take(writer.get_mut())));
            Ok(())
        })();
        if let Err(e) = result {
            tracing::error!("stream {split} epoch {epoch}: {e:#}");
            send(Err(std::io::Error::other(e.to_string())));
        }
    });
    let stream = futures_util::stream::poll_fn(move |cx| receiver.poll_recv(cx));
    Ok((
        [(header::CONTENT_TYPE, HeaderValue::from_static(ARROW_STREAM))],
        Body::from_stream(stream),
    )
        .into_response())
}

async fn manifest(State(index): Shared) -> Response {
    (
        [(header::CONTENT_TYPE, "application/json")],
        index.manifest_bytes.clone(),
    )
        .into_response()
}

async fn croissant(State(index): Shared) -> Response {
    (
        [(header::CONTENT_TYPE, "application/ld+json")],
        serde_json::to_vec_pretty(&index.croissant).expect("JSON value serialises"),
    )
        .into_response()
}

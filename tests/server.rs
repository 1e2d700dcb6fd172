//! `g2r-dataset serve` end to end over loopback: every endpoint's shape, rows equal to what pyarrow reads, exact
//! Range bytes, hostile requests refused, 32 concurrent clients without errors, the trainer streaming the same
//! batches over HTTP as from local files, and the viewer rendered by a real headless Chromium. Faults are in
//! `server_faults.rs`.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::PathBuf;
use std::process::Command;
use std::sync::Arc;

use dataset::client::HttpClient;
use dataset::contract::planner::plan_epoch;
use dataset::contract::schema::{Sample, Split, CROP_PX, SCHEMA_VERSION};
use dataset::contract::shard::read_shard;
use train::data::{
    ContextNormalisation, ElevationNormalisation, EpochStream, HttpSource, InputNormalisation,
    LocalSource, SampleSource, StreamConfig,
};
use train::data_parallel::Replica;

#[path = "server_fixture.rs"]
mod server_fixture;

use server_fixture::{fixture, sample, serve_in_background, TILE_M};

/// Send raw request bytes (no client-side path normalisation) and return (status, body).
fn raw_get(addr: SocketAddr, target: &str) -> (u16, String) {
    let mut stream = TcpStream::connect(addr).unwrap();
    write!(
        stream,
        "GET {target} HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut response = String::new();
    stream.read_to_string(&mut response).unwrap();
    let status = response.split_whitespace().nth(1).unwrap().parse().unwrap();
    (status, response)
}

#[test]
fn every_endpoint_answers_with_its_documented_shape() {
    let (f, _serial) = fixture();
    let c = f.client();
    let info: serde_json::Value = c.get_json("/v1/info").unwrap();
    assert_eq!(info["name"], "server-fixture");
    assert_eq!(info["rows"], 390);
    assert_eq!(info["split_counts"]["train"], 340);
    assert_eq!(info["schema_version"], SCHEMA_VERSION);
    assert_eq!(
        info["schema"].as_array().unwrap().len(),
        dataset::contract::schema::sample_schema().fields().len()
    );
    assert_eq!(
        info["manifest_blake3"].as_str().unwrap(),
        dataset::files::hash_file(&f.dir.join("manifest.json")).unwrap()
    );
    assert!(info["card"]
        .as_str()
        .unwrap()
        .starts_with("# server-fixture"));

    let splits: serde_json::Value = c.get_json("/v1/splits").unwrap();
    let train = &splits["splits"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["name"] == "train")
        .unwrap();
    assert_eq!(
        (train["rows"].as_u64(), train["row_groups"].as_u64()),
        (Some(340), Some(3))
    );
    assert_eq!(train["shards"][1], "train-00001-of-00002.parquet");

    // Rows in the split's order, across the shard boundary (300 | 40).
    let page: serde_json::Value = c
        .get_json("/v1/rows?split=train&offset=295&length=10")
        .unwrap();
    assert_eq!(
        (page["total"].as_u64(), page["offset"].as_u64()),
        (Some(340), Some(295))
    );
    let ids: Vec<&str> = page["rows"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["sample_id"].as_str().unwrap())
        .collect();
    let expected: Vec<&str> = f.samples["train"][295..305]
        .iter()
        .map(|s| s.sample_id.as_str())
        .collect();
    assert_eq!(ids, expected);
    assert!(
        page["rows"][0].get("tensors").is_none(),
        "tensors only when asked"
    );
    assert_eq!(
        page["rows"][6]["location"]["shard"],
        "train-00001-of-00002.parquet"
    );
    assert_eq!(page["rows"][6]["location"]["row"], 1);
    let tail: serde_json::Value = c
        .get_json("/v1/rows?split=test&offset=18&length=100")
        .unwrap();
    assert_eq!(tail["rows"].as_array().unwrap().len(), 2);

    // Filters against an independent count over the fixture.
    let by_tile: serde_json::Value = c.get_json("/v1/filter?tile=t_3_-511&limit=3").unwrap();
    let want = f
        .samples
        .values()
        .flatten()
        .filter(|s| s.tile_id == "t_3_-511")
        .count();
    assert_eq!(by_tile["count"].as_u64(), Some(want as u64));
    assert_eq!(by_tile["rows"].as_array().unwrap().len(), 3.min(want));
    let bbox = [-11.5, -43.35, -10.0, -43.3];
    let by_box: serde_json::Value = c
        .get_json(&format!(
            "/v1/filter?split=train&bbox={},{},{},{}&limit=1000",
            bbox[0], bbox[1], bbox[2], bbox[3]
        ))
        .unwrap();
    let want = f.samples["train"]
        .iter()
        .filter(|s| {
            (bbox[0]..=bbox[2]).contains(&s.center_lon_deg)
                && (bbox[1]..=bbox[3]).contains(&s.center_lat_deg)
        })
        .count();
    assert!(want > 0 && want < 340, "the box must cut the split: {want}");
    assert_eq!(by_box["count"].as_u64(), Some(want as u64));

    // Tiles: one split each, exact squares from summary.json's tile size.
    let tiles: serde_json::Value = c.get_json("/v1/tiles").unwrap();
    let tiles = tiles["tiles"].as_array().unwrap();
    assert_eq!(tiles.len(), 12);
    let t = tiles.iter().find(|t| t["tile_id"] == "t_5_-512").unwrap();
    assert_eq!(t["split"], "test");
    assert_eq!(
        t["rect_m"],
        serde_json::json!([5.0 * TILE_M, -512.0 * TILE_M, 6.0 * TILE_M, -511.0 * TILE_M])
    );

    // One sample and its previews (PNG, 128 × 128).
    let s = &f.samples["val"][7];
    let one: serde_json::Value = c.get_json(&format!("/v1/samples/{}", s.sample_id)).unwrap();
    assert_eq!(one["incidence_deg"].as_f64(), Some(s.incidence_deg));
    for file in ["dem.png", "image.png", "lit.png", "context.png"] {
        let png = c
            .get_ok(&format!("/v1/samples/{}/{file}", s.sample_id), &[])
            .unwrap();
        assert_eq!(png.header("content-type"), Some("image/png"));
        let decoded = image::load_from_memory(&png.body).unwrap();
        assert_eq!(
            (decoded.width(), decoded.height()),
            (CROP_PX as u32, CROP_PX as u32)
        );
    }

    // Manifest bytes as published; Croissant lists every shard.
    assert_eq!(
        c.get_ok("/v1/manifest", &[]).unwrap().body,
        std::fs::read(f.dir.join("manifest.json")).unwrap()
    );
    let croissant: serde_json::Value = c.get_json("/v1/croissant").unwrap();
    assert_eq!(croissant["distribution"].as_array().unwrap().len(), 4);

    // A row group as Arrow IPC equals the shard's rows.
    let ipc = c
        .get_ok("/v1/shards/train-00000-of-00002.parquet/row-groups/1", &[])
        .unwrap();
    assert_eq!(
        ipc.header("content-type"),
        Some(dataset::client::ARROW_STREAM)
    );
    assert_eq!(
        dataset::contract::wire::samples_from_ipc_stream(&ipc.body).unwrap(),
        f.samples["train"][256..300]
    );

    // The viewer page.
    let page = c.get_ok("/", &[]).unwrap();
    assert!(page.text().contains("<canvas id=\"map\""));
}

#[test]
fn epoch_stream_serves_rows_in_the_planners_order() {
    let (f, _serial) = fixture();
    let local = LocalSource::open(&f.dir).unwrap();
    let groups = local.row_groups(Split::Train).unwrap();
    let by_group: Vec<Vec<Sample>> = groups
        .iter()
        .map(|g| local.read_row_group(g).unwrap())
        .collect();
    for (rank, world, window) in [(0, 1, 2), (1, 2, 1)] {
        let plan = plan_epoch(&groups, 5, 3, window, rank, world);
        let expected: Vec<&Sample> = plan
            .rows
            .iter()
            .map(|r| &by_group[r.group][r.row])
            .collect();
        let body = f
            .client()
            .get_ok(
                &format!("/v1/stream?split=train&seed=5&epoch=3&rank={rank}&world={world}&window={window}"),
                &[("Accept", dataset::client::ARROW_STREAM)],
            )
            .unwrap()
            .body;
        let streamed = dataset::contract::wire::samples_from_ipc_stream(&body).unwrap();
        assert_eq!(streamed.len(), expected.len());
        assert!(
            streamed.iter().zip(&expected).all(|(a, b)| a == *b),
            "rank {rank}/{world}"
        );
    }
    let refused = f
        .client()
        .get("/v1/stream?split=train&seed=5&epoch=3", &[])
        .unwrap();
    assert_eq!(refused.status, 406);
}

#[test]
fn rows_and_remote_shard_reads_equal_what_pyarrow_and_polars_read() {
    let (f, _serial) = fixture();
    let script = r#"
import sys, json, base64, urllib.request
import numpy as np, pyarrow.parquet as pq, polars as pl
url, shard_dir = sys.argv[1], sys.argv[2]
name = "train-00000-of-00002.parquet"
table = pq.read_table(f"{shard_dir}/{name}")
body = json.load(urllib.request.urlopen(f"{url}/v1/rows?split=train&offset=250&length=20&tensors=base64"))
assert len(body["rows"]) == 20
scalars = ["sample_id", "split", "tile_id", "ortho_id", "center_x", "center_y", "center_lon", "center_lat",
           "enu_origin_height_m", "fov_deg", "gsd_m", "incidence_deg", "emission_deg", "phase_deg", "acq_time",
           "provenance", "footprint_lonlat", "sun_dir_enu", "camera_pos_enu", "map_to_en", "camera_att"]
for k, row in enumerate(body["rows"]):
    i = 250 + k
    for col in scalars:
        assert table.column(col)[i].as_py() == row[col], (col, i, row[col])
    for col, dtype in [("dem", np.float32), ("image", np.float32), ("valid", np.uint8), ("sun_lit", np.float32)]:
        t = row["tensors"][col]
        got = np.frombuffer(base64.b64decode(t["base64"]), dtype=dtype).reshape(t["shape"])
        want = np.asarray(table.column(col)[i].values.to_numpy(zero_copy_only=False), dtype=dtype).reshape(t["shape"])
        assert t["dtype"] == np.dtype(dtype).name and np.array_equal(got, want), col
    ctx = row["tensors"]["context_dem"]
    got = np.frombuffer(base64.b64decode(ctx["base64"]), dtype=np.float32).reshape(ctx["shape"])
    want = np.asarray(table.column("context_dem")[i].values.to_numpy(zero_copy_only=False), dtype=np.float32)
    assert ctx["shape"] == [32, 32] and np.array_equal(got, want.reshape(32, 32), equal_nan=True), "context_dem"
    assert ctx["gsd_m"] == table.column("context_gsd_m")[i].as_py()
    units = row["tensors"]["context_highland"]
    got = np.frombuffer(base64.b64decode(units["base64"]), dtype=np.float32).reshape(units["shape"])
    want = np.asarray(table.column("context_highland")[i].values.to_numpy(zero_copy_only=False), dtype=np.float32)
    assert np.array_equal(got, want.reshape(32, 32), equal_nan=True), "context_highland"
# Remote reads through HTTP Range requests, with no custom code.
remote = pl.read_parquet(f"{url}/v1/shards/{name}", columns=["sample_id", "incidence_deg", "dem"])
local = pl.read_parquet(f"{shard_dir}/{name}", columns=["sample_id", "incidence_deg", "dem"])
assert remote.equals(local), "polars over HTTP differs from the file"
print("ok", len(body["rows"]), remote.shape)
"#;
    let out = Command::new(g2r_tests::python())
        .args(["-c", script, &f.url(), f.dir.to_str().unwrap()])
        .output()
        .expect("python with pyarrow/polars/numpy (bash .ci/setup makes .venv)");
    assert!(
        out.status.success(),
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn range_reads_return_exactly_the_files_bytes() {
    let (f, _serial) = fixture();
    let c = f.client();
    let name = "val-00000-of-00001.parquet";
    let bytes = std::fs::read(f.dir.join(name)).unwrap();
    let n = bytes.len();
    let whole = c.get_ok(&format!("/v1/shards/{name}"), &[]).unwrap();
    assert_eq!(whole.status, 200);
    assert_eq!(whole.body, bytes);
    assert_eq!(whole.header("accept-ranges"), Some("bytes"));
    for (range, expected) in [
        ("bytes=0-99".to_string(), &bytes[..100]),
        (
            format!("bytes={}-{}", n / 2, n / 2 + 4095),
            &bytes[n / 2..n / 2 + 4096],
        ),
        ("bytes=-8".to_string(), &bytes[n - 8..]), // the Parquet footer length + magic, as readers ask for it
        (format!("bytes={}-", n - 1000), &bytes[n - 1000..]),
        (format!("bytes={}-{}", n - 10, n + 500), &bytes[n - 10..]), // clamped to the file's end
    ] {
        let part = c
            .get(&format!("/v1/shards/{name}"), &[("Range", &range)])
            .unwrap();
        assert_eq!(part.status, 206, "{range}");
        assert_eq!(part.body, expected, "{range}");
        let content_range = part.header("content-range").unwrap();
        assert!(
            content_range.ends_with(&format!("/{n}")),
            "{range}: {content_range}"
        );
    }
    for bad in [
        "bytes=abc",
        "bytes=10-5",
        "pages=0-1",
        &format!("bytes={}-{}", n + 10, n + 20),
    ] {
        let r = c
            .get(&format!("/v1/shards/{name}"), &[("Range", bad)])
            .unwrap();
        assert_eq!(r.status, 416, "{bad}");
    }
}

#[test]
fn hostile_and_malformed_requests_get_4xx_and_nothing_outside_the_directory() {
    let (f, _serial) = fixture();
    let secret = "TOP-SECRET-OUTSIDE-DIR";
    for target in [
        "/v1/shards/../secret.txt",
        "/v1/shards/..%2Fsecret.txt",
        "/v1/shards/%2e%2e%2fsecret.txt",
        "/v1/shards/%2E%2E/secret.txt",
        "/v1/shards/..%5Csecret.txt",
        "/v1/shards/%2Fetc%2Fpasswd",
        "/v1/shards//etc/passwd",
        "/v1/shards/summary.json", // inside the directory, but not a listed shard
        "/../secret.txt",
        "/%2e%2e/secret.txt",
        "//etc/passwd",
        "/v1/samples/..%2F..%2Fsecret.txt/dem.png",
        "/v1/samples/M0:1:7/..%2F..%2Fsecret.txt",
        "/v1/shards/train-00000-of-00002.parquet/row-groups/..%2F..%2Fsecret.txt",
        "/v1/shards/train-00000-of-00002.parquet/row-groups/99",
    ] {
        let (status, body) = raw_get(f.addr, target);
        assert!((400..500).contains(&status), "{target}: {status}");
        assert!(
            !body.contains(secret) && !body.contains("root:x:0"),
            "{target} leaked a file"
        );
    }
    let c = f.client();
    for (query, status, message) in [
        (
            "/v1/rows?split=train&length=101",
            400,
            "'length' must be 1..=100",
        ),
        (
            "/v1/rows?split=train&length=0",
            400,
            "'length' must be 1..=100",
        ),
        (
            "/v1/rows?split=train&length=-5",
            400,
            "non-negative integer, got '-5'",
        ),
        (
            "/v1/rows?split=train&length=ten",
            400,
            "non-negative integer, got 'ten'",
        ),
        (
            "/v1/rows?split=train&offset=-1",
            400,
            "'offset' must be a non-negative integer",
        ),
        ("/v1/rows?split=train&tensors=raw", 400, "'tensors' must be"),
        ("/v1/rows?length=5", 400, "missing query parameter 'split'"),
        ("/v1/rows?split=holdout", 404, "unknown split 'holdout'"),
        ("/v1/filter?split=holdout", 404, "unknown split"),
        ("/v1/filter?bbox=1,2,3", 400, "'bbox' must be"),
        ("/v1/filter?bbox=5,0,1,1", 400, "lon0 <= lon1"),
        ("/v1/filter?limit=100000", 400, "'limit' must be at most"),
        ("/v1/samples/nope:1:2", 404, "no sample 'nope:1:2'"),
        ("/v1/samples/M0:1:7/dem.jpg", 404, "no preview 'dem.jpg'"),
        (
            "/v1/stream?split=train&epoch=1",
            400,
            "missing query parameter 'seed'",
        ),
        ("/v1/nothing", 404, "no such endpoint"),
    ] {
        let headers = [("Accept", dataset::client::ARROW_STREAM)];
        let r = c.get(query, &headers).unwrap();
        assert_eq!(r.status, status, "{query}: {}", r.text());
        let body: serde_json::Value = serde_json::from_slice(&r.body).unwrap();
        assert!(
            body["error"].as_str().unwrap().contains(message),
            "{query}: {}",
            r.text()
        );
    }
}

/// Resident memory of this process, bytes (Linux).
fn rss_bytes() -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap();
    let line = status.lines().find(|l| l.starts_with("VmRSS:")).unwrap();
    line.split_whitespace()
        .nth(1)
        .unwrap()
        .parse::<u64>()
        .unwrap()
        * 1024
}

#[test]
fn thirty_two_concurrent_clients_get_no_errors_in_bounded_memory() {
    let (f, _serial) = fixture();
    // Warm-up round so one-time allocations (runtime threads, footers) are not counted as growth.
    dataset_server::loadtest::run(&f.url(), 32, 320, 1).unwrap();
    let before = rss_bytes();
    let report = dataset_server::loadtest::run(&f.url(), 32, 3200, 2).unwrap();
    let grown = rss_bytes().saturating_sub(before);
    eprintln!(
        "load: {} requests from {} clients in {:.2} s: {:.0} req/s, {:.0} rows/s, {:.1} MB/s, p50 {:.1} ms, p99 {:.1} ms; RSS +{} MiB",
        report.requests,
        report.clients,
        report.wall_s,
        report.requests_per_s,
        report.rows_per_s,
        report.mb_per_s,
        report.p50_ms,
        report.p99_ms,
        grown >> 20
    );
    assert_eq!(report.errors, 0, "{:?}", report.error_samples);
    assert_eq!(report.requests, 3200);
    assert!(
        grown < 512 << 20,
        "RSS grew by {} MiB under load",
        grown >> 20
    );
}

#[test]
fn trainer_over_http_gets_the_same_first_epoch_batches_as_from_local_files() {
    let (f, _serial) = fixture();
    let config = StreamConfig {
        seed: 11,
        batch_size: 8,
        window_groups: 2,
        augment: true,
        max_samples: None,
    };
    let local: Arc<dyn SampleSource> = Arc::new(LocalSource::open(&f.dir).unwrap());
    let remote: Arc<dyn SampleSource> = Arc::new(HttpSource::open(&f.url()).unwrap());
    assert_eq!(local.manifest(), remote.manifest());
    assert_eq!(
        local.row_groups(Split::Train).unwrap(),
        remote.row_groups(Split::Train).unwrap()
    );
    // Every input: the elevation plane and the context window are carried over HTTP too.
    let input = InputNormalisation {
        dem_std_m: local.manifest().dem_std_m,
        elevation: Some(ElevationNormalisation {
            mean_m: -1000.0,
            std_m: 100.0,
        }),
        context: Some(ContextNormalisation {
            gsd_m: 512.0,
            std_m: 150.0,
            absolute: false,
            crater_rms_m: None,
            crater_frame: false,
            crater_relief: None,
            units: false,
        }),
    };
    let from_local: Vec<_> = EpochStream::start(
        local,
        Split::Train,
        config,
        input,
        None,
        0,
        0,
        Replica::SOLE,
        std::convert::identity,
    )
    .unwrap()
    .map(Result::unwrap)
    .collect();
    let from_http: Vec<_> = EpochStream::start(
        remote,
        Split::Train,
        config,
        input,
        None,
        0,
        0,
        Replica::SOLE,
        std::convert::identity,
    )
    .unwrap()
    .map(Result::unwrap)
    .collect();
    assert_eq!(from_local.len(), 340usize.div_ceil(8));
    assert!(from_local
        .iter()
        .all(|b| b.context_input.len() == b.len() * 2 * 32 * 32));
    assert!(
        from_local == from_http,
        "HTTP batches differ from local batches"
    );
    // And the shuffle really shuffles: the first batch is not the file's first rows.
    let file_order: Vec<String> = read_shard(&f.dir.join("train-00000-of-00002.parquet")).unwrap()
        [..8]
        .iter()
        .map(|s| s.sample_id.clone())
        .collect();
    assert_ne!(from_http[0].sample_ids, file_order);
}

/// A Chromium/Chrome binary: $G2R_CHROMIUM, else the first on PATH.
fn chromium() -> PathBuf {
    if let Some(path) = std::env::var_os("G2R_CHROMIUM") {
        return path.into();
    }
    for name in ["chromium", "chromium-browser", "google-chrome"] {
        if let Ok(out) = Command::new("which").arg(name).output() {
            if out.status.success() {
                return String::from_utf8_lossy(&out.stdout).trim().into();
            }
        }
    }
    panic!("no chromium on PATH: install it (bash .ci/setup does: apt-get install chromium) or set G2R_CHROMIUM");
}

#[test]
fn viewer_renders_samples_and_the_tile_map_in_headless_chromium() {
    let (f, _serial) = fixture();
    let shots = tempfile::tempdir().unwrap();
    let screenshot = shots.path().join("viewer.png");
    let common = [
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--hide-scrollbars",
        "--window-size=1280,900",
        "--virtual-time-budget=15000",
    ];
    let profile = format!("--user-data-dir={}", shots.path().join("profile").display());
    let dom = Command::new(chromium())
        .args(common)
        .arg(&profile)
        .arg("--dump-dom")
        .arg(f.url())
        .output()
        .unwrap();
    let dom = String::from_utf8_lossy(&dom.stdout);
    assert!(
        dom.contains("data-ready=\"1\""),
        "viewer never finished loading:\n{dom}"
    );
    assert_eq!(
        dom.matches("class=\"sample\"").count(),
        12,
        "one page of samples"
    );
    assert!(dom.contains("<h1 id=\"title\">server-fixture</h1>"));
    assert!(dom.contains(&format!(
        "data-sample-id=\"{}\"",
        f.samples["train"][0].sample_id
    )));
    assert!(dom.contains("train: 1–12 of 340"));
    let status = Command::new(chromium())
        .args(common)
        .arg(&profile)
        .arg(format!("--screenshot={}", screenshot.display()))
        .arg(f.url())
        .output()
        .unwrap();
    assert!(
        screenshot.exists(),
        "no screenshot: {}",
        String::from_utf8_lossy(&status.stderr)
    );
    let shot = image::open(&screenshot).unwrap().to_rgb8();
    assert_eq!((shot.width(), shot.height()), (1280, 900));
    let count = |rgb: [u8; 3]| shot.pixels().filter(|p| p.0 == rgb).count();
    // The canvas map paints val tiles #6ea0e6 and test tiles #f0a050 (legend chips are far smaller).
    assert!(
        count([0x6e, 0xa0, 0xe6]) > 2000 && count([0xf0, 0xa0, 0x50]) > 2000,
        "tile map not drawn"
    );
    // Previews loaded: many distinct grey levels in the sample grid (text alone has few).
    let greys: std::collections::BTreeSet<u8> = shot
        .enumerate_pixels()
        .filter(|(x, _, p)| *x > 450 && p.0[0] == p.0[1] && p.0[1] == p.0[2])
        .map(|(_, _, p)| p.0[0])
        .collect();
    assert!(
        greys.len() > 150,
        "previews not rendered ({} grey levels)",
        greys.len()
    );
}

#[test]
fn a_split_without_rows_answers_empty_not_an_error() {
    // Publish lists every split, with count 0 when the tiles gave it none: the server must answer, not panic.
    let root = tempfile::tempdir().unwrap();
    let dir = root.path().join("dataset");
    let rows: Vec<Sample> = (0..3).map(|i| sample(0, "train", i)).collect();
    let split_summary = serde_json::json!({ "tile_size_m": TILE_M });
    dataset::testing::write_dataset(
        &dir,
        "one-split",
        &[("train", vec![rows]), ("test", vec![])],
        split_summary,
    )
    .unwrap();
    let c = HttpClient::new(&format!("http://{}", serve_in_background(&dir))).unwrap();
    let groups: serde_json::Value = c.get_json("/v1/row-groups?split=test").unwrap();
    assert_eq!(groups["row_groups"].as_array().unwrap().len(), 0);
    let page: serde_json::Value = c.get_json("/v1/rows?split=test").unwrap();
    assert_eq!(page["total"], 0);
    let stream = c
        .get_ok(
            "/v1/stream?split=test&seed=1&epoch=0",
            &[("Accept", dataset::client::ARROW_STREAM)],
        )
        .unwrap();
    assert!(
        dataset::contract::wire::samples_from_ipc_stream(&stream.body)
            .unwrap()
            .is_empty()
    );
    let too_wide = c
        .get(
            "/v1/stream?split=train&seed=1&epoch=0&window=9",
            &[("Accept", dataset::client::ARROW_STREAM)],
        )
        .unwrap();
    assert_eq!(too_wide.status, 400);
}

/// A dataset published before schema 1.2 (no context columns) still loads, streams and reads: its samples come
/// back whole, without context.
#[test]
fn a_schema_1_1_dataset_serves_and_streams_its_rows_without_context() {
    let root = tempfile::tempdir().unwrap();
    let dir = root.path().join("dataset");
    let rows: Vec<Sample> = (0..5).map(|i| sample(0, "train", i)).collect();
    let split_summary = serde_json::json!({ "tile_size_m": TILE_M });
    dataset::testing::write_dataset(&dir, "old", &[("train", vec![rows.clone()])], split_summary)
        .unwrap();
    dataset::testing::downgrade_to_schema_1_1(&dir).unwrap();
    let without_context: Vec<Sample> = rows
        .iter()
        .map(|s| Sample {
            context: None,
            crater: None,
            ..s.clone()
        })
        .collect();
    let local = LocalSource::open(&dir).unwrap();
    assert_eq!(local.manifest().schema_version, "1.1.0");
    let groups = local.row_groups(Split::Train).unwrap();
    assert_eq!(local.read_row_group(&groups[0]).unwrap(), without_context);

    let url = format!("http://{}", serve_in_background(&dir));
    let remote = HttpSource::open(&url).unwrap();
    assert_eq!(remote.read_row_group(&groups[0]).unwrap(), without_context);
    let stream = HttpClient::new(&url)
        .unwrap()
        .get_ok(
            "/v1/stream?split=train&seed=1&epoch=0",
            &[("Accept", dataset::client::ARROW_STREAM)],
        )
        .unwrap();
    let mut streamed = dataset::contract::wire::samples_from_ipc_stream(&stream.body).unwrap();
    streamed.sort_by(|a, b| a.sample_id.cmp(&b.sample_id));
    let mut expected = without_context;
    expected.sort_by(|a, b| a.sample_id.cmp(&b.sample_id));
    assert_eq!(streamed, expected);

    // The JSON views describe the dataset as it is: its own schema (neither the two context columns of schema 1.2
    // nor the three crater columns of 1.3 and 1.4 nor the unit column of 1.6), no context tensor, no context
    // preview.
    let client = HttpClient::new(&url).unwrap();
    let info: serde_json::Value = client.get_json("/v1/info").unwrap();
    let columns: Vec<&str> = info["schema"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f["name"].as_str().unwrap())
        .collect();
    assert_eq!(
        columns.len(),
        dataset::contract::schema::sample_schema().fields().len() - 6
    );
    assert!(
        columns.contains(&"dem")
            && !columns
                .iter()
                .any(|c| dataset::testing::is_newer_than_1_1(c))
    );
    let page: serde_json::Value = client
        .get_json("/v1/rows?split=train&length=1&tensors=base64")
        .unwrap();
    assert!(page["rows"][0]["tensors"]["dem"].is_object());
    assert!(page["rows"][0]["tensors"]["context_dem"].is_null());
    let id = &expected[0].sample_id;
    let png = client
        .get(&format!("/v1/samples/{id}/context.png"), &[])
        .unwrap();
    assert_eq!(png.status, 404);
    assert!(String::from_utf8_lossy(&png.body).contains("predates schema 1.2"));
    assert_eq!(
        client
            .get(&format!("/v1/samples/{id}/dem.png"), &[])
            .unwrap()
            .status,
        200
    );
}

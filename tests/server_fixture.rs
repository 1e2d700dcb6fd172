//! The dataset the server tests publish and the server they share, for `server.rs` and `server_faults.rs` (each
//! test binary uses part of it).
#![allow(dead_code)]

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use dataset::client::HttpClient;
use dataset::contract::schema::{Sample, CROP_PX};

pub const TILE_M: f64 = 2560.0;
/// (split, rows per shard): train spans two shards and three row groups.
pub const LAYOUT: [(&str, &[usize]); 3] = [("train", &[300, 40]), ("val", &[30]), ("test", &[20])];

/// A varied sample: each split owns its own 2 × 2 tiles (a 6 × 2 tile map), centres and lon/lat spread so filters have something to find.
pub fn sample(split_index: usize, split: &str, i: usize) -> Sample {
    let n = CROP_PX * CROP_PX;
    let tile = (
        split_index as i64 * 2 + (i % 2) as i64,
        -512 + ((i / 2) % 2) as i64,
    );
    let x = tile.0 as f64 * TILE_M + 200.0 + (i % 9) as f64 * 100.0;
    let y = tile.1 as f64 * TILE_M + 300.0 + (i % 5) as f64 * 150.0;
    Sample {
        sample_id: format!("M{split_index}:{i}:{}", i * 7 % 1000),
        split: split.parse().expect("a split name"),
        tile_id: format!("t_{}_{}", tile.0, tile.1),
        ortho_id: format!("M{split_index}"),
        center_x_m: x,
        center_y_m: y,
        center_lon_deg: -11.5 + x / 30_000.0,
        center_lat_deg: -43.3 + (y + 1_310_000.0) / 30_000.0,
        footprint_lonlat_deg: [i as f64, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.5],
        image: (0..n)
            .map(|k| ((k * 31 + i * 17) % 1000) as f32 / 20_000.0)
            .collect(),
        valid: (0..n)
            .map(|k| u8::from(!(k + i).is_multiple_of(11)))
            .collect(),
        sun_lit: (0..n).map(|k| ((k + i) % 5) as f32 / 4.0).collect(),
        camera_pos_enu_m: [i as f64, -20.0, 50_000.0],
        enu_origin_height_m: -1200.0 + i as f64 * 0.5,
        incidence_deg: 40.0 + (i % 30) as f64,
        phase_deg: 41.0 + (i % 30) as f64,
        ..dataset::testing::synthetic_sample(i)
    }
}

pub struct Fixture {
    pub dir: PathBuf,
    pub addr: SocketAddr,
    pub samples: BTreeMap<String, Vec<Sample>>,
    _root: tempfile::TempDir,
}

impl Fixture {
    pub fn url(&self) -> String {
        format!("http://{}", self.addr)
    }
    pub fn client(&self) -> HttpClient {
        HttpClient::new(&self.url()).unwrap()
    }
}

/// Publish the fixture dataset under `root/dataset` (plus a secret file next to it, outside the served dir).
pub fn publish(root: &Path) -> (PathBuf, BTreeMap<String, Vec<Sample>>) {
    let dir = root.join("dataset");
    std::fs::write(root.join("secret.txt"), "TOP-SECRET-OUTSIDE-DIR").unwrap();
    let mut layout = Vec::new();
    let mut all = BTreeMap::new();
    for (s, (split, sizes)) in LAYOUT.iter().enumerate() {
        let mut next = 0;
        let shards: Vec<Vec<Sample>> = sizes
            .iter()
            .map(|&size| {
                next += size;
                (next - size..next).map(|i| sample(s, split, i)).collect()
            })
            .collect();
        all.insert(split.to_string(), shards.concat());
        layout.push((*split, shards));
    }
    let split_summary = serde_json::json!({ "dropped_straddling_splits": 0, "tile_size_m": TILE_M, "guard_band_m": 0.0 });
    dataset::testing::write_dataset(&dir, "server-fixture", &layout, split_summary).unwrap();
    (dir, all)
}

/// Tests of one binary run one at a time: the load test measures this process's memory, and the others would
/// add theirs (the trainer test holds f64 batches).
static SERIAL: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// One server for the whole test binary, on a free loopback port, in its own runtime thread.
pub fn fixture() -> (&'static Fixture, std::sync::MutexGuard<'static, ()>) {
    let guard = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    (fixture_once(), guard)
}

/// Serve `dir` on a free loopback port from a runtime thread of its own (it ends with the test process).
pub fn serve_in_background(dir: &Path) -> SocketAddr {
    let (send, receive) = std::sync::mpsc::channel();
    let serve_dir = dir.to_path_buf();
    std::thread::spawn(move || {
        let runtime = tokio::runtime::Runtime::new().unwrap();
        runtime
            .block_on(dataset_server::serve(
                serve_dir.to_str().unwrap(),
                "127.0.0.1:0".parse().unwrap(),
                dataset_server::ServeOptions {
                    verify_hashes: true,
                    ..Default::default()
                },
                |addr| {
                    send.send(addr).unwrap();
                },
            ))
            .unwrap();
    });
    receive.recv().expect("server started")
}

fn fixture_once() -> &'static Fixture {
    static FIXTURE: OnceLock<Fixture> = OnceLock::new();
    FIXTURE.get_or_init(|| {
        let root = tempfile::tempdir().unwrap();
        let (dir, samples) = publish(root.path());
        let addr = serve_in_background(&dir);
        Fixture {
            dir,
            addr,
            samples,
            _root: root,
        }
    })
}

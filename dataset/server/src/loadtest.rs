//! `g2r-dataset load-test`: many concurrent clients against a running server, mixed the way a viewer and remote
//! readers use it (metadata pages, tensor rows, previews, shard range reads). Reports throughput and latency.

use std::time::{Duration, Instant};

use anyhow::{bail, Result};
use rand::Rng;

use dataset::client::HttpClient;
use dataset::contract::rng::keyed_rng;

#[derive(Debug, Clone, serde::Serialize)]
pub struct LoadReport {
    pub clients: usize,
    pub requests: usize,
    pub errors: usize,
    /// First few error lines, for the report.
    pub error_samples: Vec<String>,
    pub wall_s: f64,
    pub requests_per_s: f64,
    /// Rows returned by `/v1/rows`, per second.
    pub rows_per_s: f64,
    /// Response body megabytes (10⁶ B) per second.
    pub mb_per_s: f64,
    pub p50_ms: f64,
    pub p99_ms: f64,
    pub max_ms: f64,
    /// The same percentiles for each kind of request, so a tail can be traced to what makes it.
    pub by_kind: Vec<KindLatency>,
}

/// Latency of one kind of request in the mix.
#[derive(Debug, Clone, serde::Serialize)]
pub struct KindLatency {
    pub kind: &'static str,
    pub requests: usize,
    pub p50_ms: f64,
    pub p99_ms: f64,
    pub max_ms: f64,
}

/// The kinds of request in the mix, in the order they are drawn.
const KINDS: [&str; 4] = ["metadata page", "tensor page", "preview", "shard range"];

/// The `q` quantile of ascending `sorted` latencies (nearest rank).
fn quantile(sorted: &[f64], q: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

/// Latencies in ms, ascending.
fn sorted_ms<'a>(outcomes: impl Iterator<Item = &'a Outcome>) -> Vec<f64> {
    let mut ms: Vec<f64> = outcomes.map(|r| r.latency.as_secs_f64() * 1e3).collect();
    ms.sort_by(f64::total_cmp);
    ms
}

/// A `/v1/rows` answer, read only as far as its row count.
#[derive(serde::Deserialize)]
struct RowCount {
    rows: Vec<serde::de::IgnoredAny>,
}

/// One request's result.
struct Outcome {
    /// Index into [`KINDS`].
    kind: usize,
    latency: Duration,
    bytes: usize,
    rows: usize,
    error: Option<String>,
}

impl Outcome {
    fn failed(kind: usize, latency: Duration, error: String) -> Self {
        Self {
            kind,
            latency,
            bytes: 0,
            rows: 0,
            error: Some(error),
        }
    }
}

/// `clients` threads share `requests` requests; request kinds are drawn from a ChaCha stream keyed by
/// (seed, client), so the same arguments replay the same request sequence.
pub fn run(base_url: &str, clients: usize, requests: usize, seed: u64) -> Result<LoadReport> {
    if clients == 0 || requests == 0 {
        bail!("--clients and --requests must be positive");
    }
    let client = HttpClient::new(base_url)?;
    let splits: serde_json::Value = client.get_json("/v1/splits")?;
    let splits: Vec<(String, u64, Vec<String>)> = splits["splits"]
        .as_array()
        .into_iter()
        .flatten()
        .map(|s| {
            (
                s["name"].as_str().unwrap_or_default().to_string(),
                s["rows"].as_u64().unwrap_or(0),
                s["shards"]
                    .as_array()
                    .into_iter()
                    .flatten()
                    .filter_map(|n| n.as_str().map(str::to_string))
                    .collect(),
            )
        })
        .filter(|s| s.1 > 0)
        .collect();
    if splits.is_empty() {
        bail!("{base_url}: the dataset has no rows to load-test with");
    }
    let manifest: dataset::contract::manifest::DatasetManifest = client.get_json("/v1/manifest")?;
    let ids: serde_json::Value =
        client.get_json(&format!("/v1/rows?split={}&length=100", splits[0].0))?;
    let ids: Vec<String> = ids["rows"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(|r| r["sample_id"].as_str().map(str::to_string))
        .collect();
    let start = Instant::now();
    let results: Vec<Vec<Outcome>> = std::thread::scope(|scope| {
        let handles: Vec<_> = (0..clients)
            .map(|c| {
                let (client, splits, manifest, ids) = (client.clone(), &splits, &manifest, &ids);
                let count = requests / clients + usize::from(c < requests % clients);
                scope.spawn(move || {
                    let mut rng = keyed_rng(seed, "load-test", c as u64);
                    (0..count)
                        .map(|_| {
                            let (split, rows, _) = &splits[rng.random_range(0..splits.len())];
                            // 40 % metadata pages, 20 % each of the others (KINDS' order).
                            let kind = match rng.random_range(0..10) {
                                0..=3 => 0,
                                4 | 5 => 1,
                                6 | 7 => 2,
                                _ => 3,
                            };
                            let (path, range) = match kind {
                                0 => (
                                    format!(
                                        "/v1/rows?split={split}&offset={}&length=20",
                                        rng.random_range(0..*rows)
                                    ),
                                    None,
                                ),
                                1 => (
                                    format!(
                                        "/v1/rows?split={split}&offset={}&length=2&tensors=base64",
                                        rng.random_range(0..*rows)
                                    ),
                                    None,
                                ),
                                2 => {
                                    let id = &ids[rng.random_range(0..ids.len())];
                                    let file =
                                        ["dem.png", "image.png", "lit.png"][rng.random_range(0..3)];
                                    (format!("/v1/samples/{id}/{file}"), None)
                                }
                                _ => {
                                    let shard = &manifest.shards
                                        [rng.random_range(0..manifest.shards.len())];
                                    let len = 65_536.min(shard.bytes);
                                    let from = rng.random_range(0..=shard.bytes - len);
                                    (
                                        format!("/v1/shards/{}", shard.path),
                                        Some(format!("bytes={from}-{}", from + len - 1)),
                                    )
                                }
                            };
                            let headers: Vec<(&str, &str)> =
                                range.as_deref().map(|r| ("Range", r)).into_iter().collect();
                            let t0 = Instant::now();
                            let outcome = client.get(&path, &headers);
                            let latency = t0.elapsed();
                            match outcome {
                                Ok(r) if (200..300).contains(&r.status) => {
                                    let rows_returned = if path.starts_with("/v1/rows") {
                                        // Counted without building the rows: the clients share the server's
                                        // cores, and a tensor page is ~0.7 MB of base64.
                                        serde_json::from_slice::<RowCount>(&r.body)
                                            .map_or(0, |page| page.rows.len())
                                    } else {
                                        0
                                    };
                                    Outcome {
                                        kind,
                                        latency,
                                        bytes: r.body.len(),
                                        rows: rows_returned,
                                        error: None,
                                    }
                                }
                                Ok(r) => Outcome::failed(
                                    kind,
                                    latency,
                                    format!("{path}: HTTP {} {}", r.status, r.text().trim()),
                                ),
                                Err(e) => Outcome::failed(kind, latency, format!("{e:#}")),
                            }
                        })
                        .collect()
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| h.join().expect("load-test client panicked"))
            .collect()
    });
    let wall_s = start.elapsed().as_secs_f64();
    let all: Vec<_> = results.into_iter().flatten().collect();
    let latencies = sorted_ms(all.iter());
    let by_kind = KINDS
        .iter()
        .enumerate()
        .filter_map(|(k, &kind)| {
            let ms = sorted_ms(all.iter().filter(|r| r.kind == k));
            (!ms.is_empty()).then(|| KindLatency {
                kind,
                requests: ms.len(),
                p50_ms: quantile(&ms, 0.5),
                p99_ms: quantile(&ms, 0.99),
                max_ms: quantile(&ms, 1.0),
            })
        })
        .collect();
    let errors: Vec<String> = all.iter().filter_map(|r| r.error.clone()).collect();
    Ok(LoadReport {
        clients,
        requests: all.len(),
        errors: errors.len(),
        error_samples: errors.into_iter().take(5).collect(),
        wall_s,
        requests_per_s: all.len() as f64 / wall_s,
        rows_per_s: all.iter().map(|r| r.rows).sum::<usize>() as f64 / wall_s,
        mb_per_s: all.iter().map(|r| r.bytes).sum::<usize>() as f64 / 1e6 / wall_s,
        p50_ms: quantile(&latencies, 0.5),
        p99_ms: quantile(&latencies, 0.99),
        max_ms: quantile(&latencies, 1.0),
        by_kind,
    })
}

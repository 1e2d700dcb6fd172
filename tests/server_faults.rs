//! `g2r-dataset serve` under faults: more clients than it serves at once, clients that disconnect mid-stream,
//! readers that stop reading, and shards that vanish or are cut short while it runs. Loopback only.

use std::io::{Read, Write};
use std::net::TcpStream;

use dataset::client::HttpClient;

#[path = "server_fixture.rs"]
mod server_fixture;

use server_fixture::{fixture, publish, serve_in_background};

/// More clients than the server answers at once (tokio's workers, one raster request a core) queue; none fails.
#[test]
fn two_hundred_fifty_six_clients_queue_and_get_no_errors() {
    let (f, _serial) = fixture();
    let report = dataset_server::loadtest::run(&f.url(), 256, 768, 4).unwrap();
    assert_eq!(report.errors, 0, "{:?}", report.error_samples);
    assert_eq!(report.requests, 768);
}

/// The epoch request the disconnect and slow-reader tests start (Arrow IPC, one row group a window).
fn stream_request(seed: u32) -> String {
    format!(
        "GET /v1/stream?split=train&seed={seed}&epoch=0&window=1 HTTP/1.1\r\nHost: localhost\r\nAccept: {}\r\n\r\n",
        dataset::client::ARROW_STREAM
    )
}

/// Clients that go away mid-stream give their stream's place back: with more of them than the streams allowed at
/// once, a later stream still runs to its end, and other requests are answered meanwhile.
#[test]
fn clients_that_disconnect_mid_stream_leave_the_server_streaming() {
    let (f, _serial) = fixture();
    for seed in 0..3 {
        let mut stream = TcpStream::connect(f.addr).unwrap();
        stream
            .set_read_timeout(Some(std::time::Duration::from_secs(60)))
            .unwrap();
        stream.write_all(stream_request(seed).as_bytes()).unwrap();
        let mut first = [0u8; 4096];
        stream.read_exact(&mut first).unwrap();
        assert!(
            first.starts_with(b"HTTP/1.1 200"),
            "{}",
            String::from_utf8_lossy(&first[..64])
        );
        drop(stream); // mid-stream: the first window alone is larger than what was read
    }
    let url = f.url();
    let (send, receive) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let client = HttpClient::new(&url).unwrap();
        let path = "/v1/stream?split=train&seed=9&epoch=0&window=1";
        send.send(client.get(path, &[("Accept", dataset::client::ARROW_STREAM)]))
            .unwrap();
    });
    let whole = receive
        .recv_timeout(std::time::Duration::from_secs(120))
        .expect("a stream after the disconnects did not finish: a gone client kept its place")
        .unwrap();
    assert_eq!(whole.status, 200);
    let streamed = dataset::contract::wire::samples_from_ipc_stream(&whole.body).unwrap();
    assert_eq!(streamed.len(), f.samples["train"].len());
    assert_eq!(f.client().get("/v1/info", &[]).unwrap().status, 200);
}

/// Readers that take nothing off their sockets (a whole shard each, and epoch streams) hold only their own
/// requests: meanwhile 32 clients get every answer.
#[test]
fn slow_readers_do_not_hold_up_other_clients() {
    let (f, _serial) = fixture();
    let mut slow = Vec::new();
    for k in 0..8 {
        let mut stream = TcpStream::connect(f.addr).unwrap();
        let request = if k % 2 == 0 {
            "GET /v1/shards/train-00000-of-00002.parquet HTTP/1.1\r\nHost: localhost\r\n\r\n"
                .to_string()
        } else {
            stream_request(100 + k)
        };
        stream.write_all(request.as_bytes()).unwrap();
        slow.push(stream); // never read
    }
    let report = dataset_server::loadtest::run(&f.url(), 32, 320, 5).unwrap();
    assert_eq!(report.errors, 0, "{:?}", report.error_samples);
    drop(slow);
}

/// A shard removed or cut short while the server runs: requests that need its bytes get a 4xx/5xx naming it, the
/// server stays up, and requests for the other shards are answered as before.
#[test]
fn a_shard_that_vanishes_or_is_truncated_fails_only_its_own_requests() {
    let root = tempfile::tempdir().unwrap();
    let (dir, _) = publish(root.path());
    let addr = serve_in_background(&dir);
    let client = HttpClient::new(&format!("http://{addr}")).unwrap();
    let tensors = |split: &str, offset: usize| {
        client
            .get(
                &format!("/v1/rows?split={split}&offset={offset}&length=2&tensors=base64"),
                &[],
            )
            .unwrap()
    };
    let failed_naming = |response: dataset::client::HttpResponse, shard: &str| {
        assert!(
            (400..600).contains(&response.status) && response.text().contains(shard),
            "{shard}: HTTP {} {}",
            response.status,
            response.text()
        );
    };
    let kept = tensors("val", 20);
    assert_eq!(kept.status, 200);

    // The second train shard holds the split's rows 300..340; the first, rows 0..300.
    let gone = "train-00001-of-00002.parquet";
    std::fs::remove_file(dir.join(gone)).unwrap();
    failed_naming(tensors("train", 310), gone);
    let whole = client.get(&format!("/v1/shards/{gone}"), &[]).unwrap();
    assert!((400..600).contains(&whole.status), "HTTP {}", whole.status);
    assert_eq!(tensors("train", 10).status, 200);

    // Cut to its first 4 KiB: no tensor page of any row is whole.
    let cut = "val-00000-of-00001.parquet";
    let bytes = std::fs::read(dir.join(cut)).unwrap();
    std::fs::write(dir.join(cut), &bytes[..4096]).unwrap();
    failed_naming(tensors("val", 0), cut);
    let id = client
        .get_json::<serde_json::Value>("/v1/rows?split=val&offset=1&length=1")
        .unwrap()["rows"][0]["sample_id"]
        .as_str()
        .unwrap()
        .to_string();
    failed_naming(
        client
            .get(&format!("/v1/samples/{id}/dem.png"), &[])
            .unwrap(),
        cut,
    );
    // Rows read before the cut are kept in memory (the cache): served as they were, byte for byte.
    let again = tensors("val", 20);
    assert_eq!((again.status, &again.body), (200, &kept.body));

    assert_eq!(tensors("train", 100).status, 200);
    assert_eq!(client.get("/v1/info", &[]).unwrap().status, 200);
    assert_eq!(
        client
            .get("/v1/shards/test-00000-of-00001.parquet", &[])
            .unwrap()
            .status,
        200
    );
}

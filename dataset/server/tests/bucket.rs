//! `g2r-dataset serve s3://…`: a published dataset served from a bucket answers every endpoint with the same bytes
//! as the same dataset served from its folder, and a prefix that holds no dataset, or one with a shard missing, is
//! refused in one line. Against an S3 server on 127.0.0.1 (moto, started on a free loopback port and stopped by
//! PID; `.ci/setup` installs `moto[server]` into .venv); the servers run as child processes, stopped when dropped.

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};

use dataset::client::HttpClient;
use dataset::contract::schema::{Sample, Split};
use dataset::testing::s3::Moto;
use dataset::testing::{synthetic_sample, write_dataset};

fn dataset_cli() -> Command {
    Command::new(env!("CARGO_BIN_EXE_g2r-dataset"))
}

/// Samples `ids` of one split, spread over three tiles.
fn samples(split: Split, ids: std::ops::Range<usize>) -> Vec<Sample> {
    ids.map(|i| Sample {
        split,
        tile_id: format!("t_{}_4", i % 3),
        ..synthetic_sample(i)
    })
    .collect()
}

/// A published dataset in `root/dataset`: train in two shards, the first of two row groups; val in one.
fn published(root: &Path) -> std::path::PathBuf {
    let dir = root.join("dataset");
    write_dataset(
        &dir,
        "bucket-fixture",
        &[
            (
                "train",
                vec![
                    samples(Split::Train, 0..270),
                    samples(Split::Train, 270..290),
                ],
            ),
            ("val", vec![samples(Split::Val, 290..310)]),
        ],
        serde_json::json!({ "tile_size_m": 2560.0 }),
    )
    .expect("writing the fixture dataset");
    dir
}

/// Copy `dir` to `url` with `g2r-dataset upload`.
fn upload(dir: &Path, url: &str, moto: &Moto) {
    let out = dataset_cli()
        .arg("upload")
        .arg(dir)
        .arg(url)
        .envs(moto.env())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "upload: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// A `g2r-dataset serve` process, killed (by its PID) when dropped.
struct Served {
    child: Child,
    client: HttpClient,
}

impl Drop for Served {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Start `g2r-dataset serve LOCATION` on a free loopback port; `Err(stderr)` when it exits instead of serving.
fn serve(location: &str, moto: &Moto) -> Result<Served, String> {
    let mut child = dataset_cli()
        .args(["serve", "--addr", "127.0.0.1:0", location])
        .envs(moto.env())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let Some(addr) = line
        .split("at http://")
        .nth(1)
        .and_then(|r| r.split('/').next())
    else {
        let out = child.wait_with_output().unwrap();
        return Err(String::from_utf8_lossy(&out.stderr).into_owned());
    };
    let client = HttpClient::new(&format!("http://{addr}")).unwrap();
    Ok(Served { child, client })
}

#[test]
fn a_dataset_in_a_bucket_serves_the_same_bytes_as_its_folder() {
    let root = tempfile::tempdir().unwrap();
    let dir = published(root.path());
    let moto = Moto::start();
    assert_eq!(moto.request("PUT", "/served"), 200);
    upload(&dir, "s3://served/dataset", &moto);
    let local = serve(dir.to_str().unwrap(), &moto).unwrap();
    let remote = serve("s3://served/dataset", &moto).unwrap();

    let first_train_id = samples(Split::Train, 0..1)[0].sample_id.clone();
    for path in [
        "/v1/info".to_string(),
        "/v1/splits".into(),
        "/v1/tiles".into(),
        "/v1/manifest".into(),
        "/v1/croissant".into(),
        "/v1/row-groups?split=train".into(),
        "/v1/rows?split=train&offset=250&length=30&tensors=base64".into(),
        "/v1/filter?split=val&tile=t_1_4".into(),
        format!("/v1/samples/{first_train_id}"),
        format!("/v1/samples/{first_train_id}/image.png"),
        "/v1/shards/train-00000-of-00002.parquet/row-groups/1".into(),
        "/v1/stream?split=train&seed=5&epoch=1&window=2".into(),
    ] {
        let accept = [("Accept", dataset::client::ARROW_STREAM)];
        let headers: &[(&str, &str)] = if path.starts_with("/v1/stream") {
            &accept
        } else {
            &[]
        };
        let expected = local.client.get_ok(&path, headers).unwrap();
        let served = remote.client.get_ok(&path, headers).unwrap();
        assert!(
            served.body == expected.body,
            "{path}: the bucket's answer differs from the folder's"
        );
        assert_eq!(
            served.header("content-type"),
            expected.header("content-type"),
            "{path}"
        );
    }

    // Shard bytes, whole and by range, as pyarrow and polars read a remote shard.
    let name = "train-00000-of-00002.parquet";
    let bytes = std::fs::read(dir.join(name)).unwrap();
    let n = bytes.len();
    let whole = remote
        .client
        .get_ok(&format!("/v1/shards/{name}"), &[])
        .unwrap();
    assert_eq!(whole.status, 200);
    assert!(whole.body == bytes, "the whole shard differs");
    assert_eq!(whole.header("accept-ranges"), Some("bytes"));
    for (range, first, end) in [
        ("bytes=0-99".to_string(), 0, 100),
        ("bytes=-8".to_string(), n - 8, n),
        (format!("bytes={}-", n - 1000), n - 1000, n),
        (format!("bytes={}-{}", n - 10, n + 500), n - 10, n), // clamped to the shard's end
    ] {
        let part = remote
            .client
            .get(&format!("/v1/shards/{name}"), &[("Range", &range)])
            .unwrap();
        assert_eq!(part.status, 206, "{range}");
        assert!(part.body == bytes[first..end], "{range}: bytes differ");
        let content_range = format!("bytes {first}-{}/{n}", end - 1);
        assert_eq!(part.header("content-range"), Some(content_range.as_str()));
    }
    for bad in [
        "bytes=abc".to_string(),
        "bytes=10-5".into(),
        "bytes=0-1,5-9".into(),
        format!("bytes={}-{}", n + 10, n + 20),
    ] {
        let answer = remote
            .client
            .get(&format!("/v1/shards/{name}"), &[("Range", &bad)])
            .unwrap();
        assert_eq!(answer.status, 416, "{bad}");
    }
    let unlisted = remote.client.get("/v1/shards/secret.parquet", &[]).unwrap();
    assert_eq!(unlisted.status, 404);
}

#[test]
fn a_prefix_without_a_dataset_or_with_a_shard_missing_is_refused_in_one_line() {
    let root = tempfile::tempdir().unwrap();
    let dir = published(root.path());
    let moto = Moto::start();
    assert_eq!(moto.request("PUT", "/refused"), 200);

    let error = serve("s3://refused/nothing-here", &moto)
        .err()
        .expect("no dataset there");
    assert!(
        error.contains("s3://refused/nothing-here") && error.contains("no manifest.json"),
        "{error}"
    );
    assert_eq!(error.trim().lines().count(), 1, "{error}");

    // A prefix whose manifest lists a shard that is not there (a `file://` prefix, read through the same
    // object-store client, so the shard can be removed behind the manifest's back).
    let copy = root.path().join("copy");
    std::fs::create_dir(&copy).unwrap();
    for entry in std::fs::read_dir(&dir).unwrap() {
        let entry = entry.unwrap();
        std::fs::copy(entry.path(), copy.join(entry.file_name())).unwrap();
    }
    let shard = "val-00000-of-00001.parquet";
    std::fs::remove_file(copy.join(shard)).unwrap();
    let url = format!("file://{}", copy.display());
    let error = serve(&url, &moto).err().expect("a shard is missing");
    assert!(
        error.contains(&format!("{url}/{shard}")) && error.contains("re-publish"),
        "{error}"
    );
    assert_eq!(error.trim().lines().count(), 1, "{error}");
}

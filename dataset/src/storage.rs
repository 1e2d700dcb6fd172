//! Published datasets in object storage: `s3://bucket/prefix` (any S3-compatible store) and `file://` (arrow-rs
//! `object_store`), next to local directories. `gs://` and `az://` are recognised and refused in one line: their
//! clients are not built.
//!
//! Synchronous on purpose: the callers (upload, verify, the trainer's sample source) are blocking code on their own
//! threads, so each [`RemoteDir`] owns a small Tokio runtime and each call blocks on its request. S3 settings come
//! from the environment as the AWS tools read them (`AWS_ENDPOINT_URL` or `AWS_ENDPOINT`, `AWS_REGION`,
//! `AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`, `AWS_ALLOW_HTTP=true` for a plain-HTTP endpoint).

use std::ops::Range;
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use object_store::path::Path as ObjectPath;
use object_store::{ObjectStore, ObjectStoreExt, PutMode, PutOptions, PutPayload, RetryConfig};

use crate::contract::publication::{DOCUMENT_FILES, MANIFEST_FILE};

/// Whether `location` names object storage rather than a local path.
pub fn is_url(location: &str) -> bool {
    [
        "s3://",
        "s3a://",
        "gs://",
        "az://",
        "abfs://",
        "abfss://",
        "file://",
        "memory://",
    ]
    .iter()
    .any(|scheme| location.starts_with(scheme))
}

/// How often and how long a failed S3 request is retried: a refused connection, a 5xx, or a body cut mid-way (a
/// GET resumes from the byte it reached). object_store's defaults (10 retries within 180 s) unless
/// `G2R_STORE_MAX_RETRIES` or `G2R_STORE_RETRY_TIMEOUT_S` say otherwise: lower them to fail fast, raise them for a
/// flaky link.
fn retry_config() -> Result<RetryConfig> {
    fn parsed<T: std::str::FromStr>(key: &str, what: &str) -> Result<Option<T>> {
        let Ok(text) = std::env::var(key) else {
            return Ok(None);
        };
        match text.trim().parse::<T>() {
            Ok(value) => Ok(Some(value)),
            Err(_) => bail!("{key}={text:?}: give {what} (or unset it for object_store's default)"),
        }
    }
    let mut retry = RetryConfig::default();
    if let Some(n) = parsed::<usize>("G2R_STORE_MAX_RETRIES", "a whole number ≥ 0")? {
        retry.max_retries = n;
    }
    if let Some(seconds) = parsed::<f64>("G2R_STORE_RETRY_TIMEOUT_S", "seconds ≥ 0")? {
        retry.retry_timeout = std::time::Duration::try_from_secs_f64(seconds).map_err(|_| {
            anyhow::anyhow!("G2R_STORE_RETRY_TIMEOUT_S={seconds}: give seconds ≥ 0 (or unset it)")
        })?;
    }
    Ok(retry)
}

/// What identifies one version of an object without reading it: its size and entity tag (the ETag a replacement
/// changes; `None` where a store has none, e.g. some `file://` listings).
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct ObjectVersion {
    pub bytes: u64,
    pub e_tag: Option<String>,
}

impl ObjectVersion {
    fn of(meta: &object_store::ObjectMeta) -> Self {
        Self {
            bytes: meta.size,
            e_tag: meta.e_tag.clone(),
        }
    }
}

/// A "directory" in object storage: every object under one prefix.
pub struct RemoteDir {
    url: String,
    store: Arc<dyn ObjectStore>,
    prefix: ObjectPath,
    /// `Some` until drop, which shuts it down without blocking: a server drops its dataset inside async code,
    /// where dropping a runtime the ordinary way panics.
    runtime: Option<tokio::runtime::Runtime>,
}

impl Drop for RemoteDir {
    fn drop(&mut self) {
        if let Some(runtime) = self.runtime.take() {
            runtime.shutdown_background();
        }
    }
}

impl RemoteDir {
    /// Open the prefix `url` names; contacts nothing until the first request.
    pub fn open(url: &str) -> Result<Self> {
        let parsed = url::Url::parse(url).with_context(|| format!("{url}: not a URL"))?;
        let (store, prefix): (Arc<dyn ObjectStore>, ObjectPath) = match parsed.scheme() {
            "s3" | "s3a" => {
                let store = object_store::aws::AmazonS3Builder::from_env()
                    .with_url(url)
                    .with_retry(retry_config()?)
                    .build()
                    .with_context(|| {
                        format!("{url}: cannot configure S3 (AWS_* environment variables)")
                    })?;
                let prefix = ObjectPath::from_url_path(parsed.path())
                    .with_context(|| format!("{url}: bad object path"))?;
                (Arc::new(store), prefix)
            }
            "file" | "memory" => {
                let (store, prefix) = object_store::parse_url(&parsed)
                    .with_context(|| format!("{url}: unsupported object-store URL"))?;
                (Arc::from(store), prefix)
            }
            // Recognised so they are not taken for a relative folder, but not built: object_store's gcp and azure
            // features would add clients no test here can exercise.
            scheme => bail!(
                "{url}: this build reads s3:// and file:// object storage, not {scheme}://; copy the dataset to S3 \
                 (or an S3-compatible store) or to a local folder"
            ),
        };
        // One worker thread: requests come one at a time from each caller's thread (`block_on` from several
        // threads at once is what the trainer's prefetcher does), and the store's HTTP client is shared.
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .context("starting the object-store runtime")?;
        Ok(Self {
            url: url.trim_end_matches('/').to_string(),
            store,
            prefix,
            runtime: Some(runtime),
        })
    }

    /// The URL of `name` under this prefix, for messages.
    pub fn url_of(&self, name: &str) -> String {
        format!("{}/{name}", self.url)
    }

    pub fn url(&self) -> &str {
        &self.url
    }

    fn path(&self, name: &str) -> ObjectPath {
        self.prefix.clone().join(name)
    }

    /// Run one request to completion on this directory's runtime. Callers are blocking code: a thread of its own,
    /// or `spawn_blocking` / `block_in_place` inside an async server.
    fn block_on<F: std::future::Future>(&self, request: F) -> F::Output {
        self.runtime
            .as_ref()
            .expect("the runtime lives until drop")
            .block_on(request)
    }

    /// The whole object `name`.
    pub fn get(&self, name: &str) -> Result<Vec<u8>> {
        self.get_if_exists(name)?
            .with_context(|| format!("{}: cannot read: no such object", self.url_of(name)))
    }

    /// The whole object `name`, or `None` when there is no such object (any other failure is an error).
    pub fn get_if_exists(&self, name: &str) -> Result<Option<Vec<u8>>> {
        let path = self.path(name);
        match self.block_on(async { self.store.get(&path).await?.bytes().await }) {
            Ok(bytes) => Ok(Some(bytes.to_vec())),
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(e) => Err(e).with_context(|| format!("{}: cannot read", self.url_of(name))),
        }
    }

    /// Bytes `ranges` of object `name`; object_store merges ranges that lie close together into one GET.
    pub fn get_ranges(&self, name: &str, ranges: &[Range<u64>]) -> Result<Vec<bytes::Bytes>> {
        let path = self.path(name);
        self.block_on(self.store.get_ranges(&path, ranges))
            .with_context(|| {
                format!(
                    "{}: cannot read {} byte ranges",
                    self.url_of(name),
                    ranges.len()
                )
            })
    }

    /// Bytes `range` of object `name` (one ranged GET).
    pub fn get_range(&self, name: &str, range: Range<u64>) -> Result<bytes::Bytes> {
        let path = self.path(name);
        self.block_on(self.store.get_range(&path, range.clone()))
            .with_context(|| {
                format!(
                    "{}: cannot read bytes {}..{}",
                    self.url_of(name),
                    range.start,
                    range.end
                )
            })
    }

    /// The size of object `name`, in bytes.
    pub fn size(&self, name: &str) -> Result<u64> {
        let path = self.path(name);
        Ok(self
            .block_on(self.store.head(&path))
            .with_context(|| format!("{}: not found or unreadable", self.url_of(name)))?
            .size)
    }

    /// The size and entity tag of object `name`.
    pub fn version(&self, name: &str) -> Result<ObjectVersion> {
        let path = self.path(name);
        let meta = self
            .block_on(self.store.head(&path))
            .with_context(|| format!("{}: not found or unreadable", self.url_of(name)))?;
        Ok(ObjectVersion::of(&meta))
    }

    /// The objects directly under this prefix (not those under a further `/`), by name, sorted.
    pub fn list(&self) -> Result<Vec<(String, ObjectVersion)>> {
        let listed = self
            .block_on(self.store.list_with_delimiter(Some(&self.prefix)))
            .with_context(|| format!("{}/: cannot list", self.url))?;
        let mut objects: Vec<(String, ObjectVersion)> = listed
            .objects
            .iter()
            .filter_map(|meta| {
                let name = meta.location.filename()?.to_string();
                Some((name, ObjectVersion::of(meta)))
            })
            .collect();
        objects.sort_by(|a, b| a.0.cmp(&b.0));
        Ok(objects)
    }

    /// Write object `name`, replacing any.
    pub fn put(&self, name: &str, bytes: Vec<u8>) -> Result<()> {
        let path = self.path(name);
        self.block_on(self.store.put(&path, PutPayload::from(bytes)))
            .with_context(|| format!("{}: the store refused the write", self.url_of(name)))?;
        Ok(())
    }

    /// Write object `name` only if none exists (a conditional put: S3's `If-None-Match: *`); an object with other
    /// bytes is an error, whoever wrote it, so two publishers of different datasets never both believe they
    /// published. When the put fails or finds an object, the object is read back: if it holds exactly `bytes`, the
    /// write happened (a response lost on the way back, then object_store's retry finding its own object) and
    /// this is success, not a false "already exists".
    pub fn put_new(&self, name: &str, bytes: Vec<u8>) -> Result<()> {
        let path = self.path(name);
        let options = PutOptions {
            mode: PutMode::Create,
            ..Default::default()
        };
        let outcome = self.block_on(self.store.put_opts(
            &path,
            PutPayload::from(bytes.clone()),
            options,
        ));
        let Err(error) = outcome else {
            return Ok(());
        };
        if matches!(self.get_if_exists(name), Ok(Some(found)) if found == bytes) {
            return Ok(());
        }
        match error {
            object_store::Error::AlreadyExists { .. } => bail!(
                "{}: already exists; publish to a new prefix (a published dataset is never overwritten)",
                self.url_of(name)
            ),
            e => Err(e).with_context(|| format!("{}: the store refused the write", self.url_of(name))),
        }
    }
}

/// Files larger than this are copied to and from object storage in parts of this size, never held whole in
/// memory (and S3 caps a single PUT at 5 GB).
const PART_BYTES: u64 = 32 << 20;

impl RemoteDir {
    /// Copy the local file `from` to object `name`, replacing any: one PUT up to `PART_BYTES`, else a multipart
    /// upload streamed from disk (aborted on a read or write error, so no part is left billed). Returns its size.
    pub fn put_file(&self, name: &str, from: &std::path::Path) -> Result<u64> {
        use std::io::Read;
        let size = std::fs::metadata(from)
            .with_context(|| format!("{}: cannot read", from.display()))?
            .len();
        if size <= PART_BYTES {
            let bytes =
                std::fs::read(from).with_context(|| format!("{}: cannot read", from.display()))?;
            self.put(name, bytes)?;
            return Ok(size);
        }
        let path = self.path(name);
        let refused = || format!("{}: the store refused the write", self.url_of(name));
        let mut file = std::fs::File::open(from)
            .with_context(|| format!("{}: cannot read", from.display()))?;
        self.block_on(async {
            let upload = self
                .store
                .put_multipart(&path)
                .await
                .with_context(refused)?;
            let mut writer =
                object_store::WriteMultipart::new_with_chunk_size(upload, PART_BYTES as usize);
            let mut buffer = vec![0u8; PART_BYTES as usize];
            let copied: Result<()> = async {
                loop {
                    let read = file
                        .read(&mut buffer)
                        .with_context(|| format!("{}: cannot read", from.display()))?;
                    if read == 0 {
                        return Ok(());
                    }
                    writer.wait_for_capacity(2).await.with_context(refused)?;
                    writer.write(&buffer[..read]);
                }
            }
            .await;
            match copied {
                Ok(()) => writer.finish().await.map(drop).with_context(refused),
                Err(e) => {
                    let _ = writer.abort().await;
                    Err(e)
                }
            }
        })?;
        Ok(size)
    }

    /// Copy object `name`, of `size` bytes, to the local file `to` (created or replaced), in ranged GETs of at most
    /// `PART_BYTES`. Returns the blake3 of what was written, so the caller checks the copy without reading it
    /// again.
    pub fn get_to_file(&self, name: &str, size: u64, to: &std::path::Path) -> Result<String> {
        use std::io::Write;
        let mut file =
            std::fs::File::create(to).with_context(|| format!("{}: cannot write", to.display()))?;
        let mut hasher = blake3::Hasher::new();
        let mut start = 0;
        while start < size {
            let end = (start + PART_BYTES).min(size);
            let bytes = self.get_range(name, start..end)?;
            hasher.update(&bytes);
            file.write_all(&bytes)
                .with_context(|| format!("{}: cannot write", to.display()))?;
            start = end;
        }
        file.sync_all()
            .with_context(|| format!("{}: cannot write", to.display()))?;
        Ok(hasher.finalize().to_hex().to_string())
    }

    /// Remove object `name`; removing one that does not exist is not an error.
    pub fn delete(&self, name: &str) -> Result<()> {
        let path = self.path(name);
        match self.block_on(self.store.delete(&path)) {
            Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
            Err(e) => Err(e)
                .with_context(|| format!("{}: the store refused the delete", self.url_of(name))),
        }
    }
}

/// Where a published dataset lives: a local directory, or a prefix in object storage. Readers that take either
/// (the dataset server) name files by their place in the dataset (`manifest.json`, a shard's name).
pub enum DatasetLocation {
    Local(std::path::PathBuf),
    Remote(Arc<RemoteDir>),
}

impl DatasetLocation {
    /// A URL ([`is_url`]) is object storage (contacted at the first read); anything else a directory, which must
    /// exist.
    pub fn open(location: &str) -> Result<Self> {
        if is_url(location) {
            return Ok(Self::Remote(Arc::new(RemoteDir::open(location)?)));
        }
        let dir = std::path::Path::new(location)
            .canonicalize()
            .with_context(|| format!("{location}: no such dataset directory"))?;
        Ok(Self::Local(dir))
    }

    /// The directory's path or the prefix's URL, for messages.
    pub fn describe(&self) -> String {
        match self {
            Self::Local(dir) => dir.display().to_string(),
            Self::Remote(remote) => remote.url().to_string(),
        }
    }

    /// The path or URL of `name` in the dataset, for messages.
    pub fn describe_file(&self, name: &str) -> String {
        match self {
            Self::Local(dir) => dir.join(name).display().to_string(),
            Self::Remote(remote) => remote.url_of(name),
        }
    }

    /// The whole file `name`.
    pub fn read(&self, name: &str) -> Result<Vec<u8>> {
        match self {
            Self::Local(dir) => std::fs::read(dir.join(name))
                .with_context(|| format!("{}: cannot read", dir.join(name).display())),
            Self::Remote(remote) => remote.get(name),
        }
    }

    /// The whole file `name`, or `None` when the dataset has no such file.
    pub fn read_if_exists(&self, name: &str) -> Result<Option<Vec<u8>>> {
        match self {
            Self::Local(dir) => match std::fs::read(dir.join(name)) {
                Ok(bytes) => Ok(Some(bytes)),
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
                Err(e) => {
                    Err(e).with_context(|| format!("{}: cannot read", dir.join(name).display()))
                }
            },
            Self::Remote(remote) => remote.get_if_exists(name),
        }
    }

    /// The size of file `name` in bytes.
    pub fn size(&self, name: &str) -> Result<u64> {
        match self {
            Self::Local(dir) => Ok(std::fs::metadata(dir.join(name))
                .with_context(|| format!("{}: not found or unreadable", dir.join(name).display()))?
                .len()),
            Self::Remote(remote) => remote.size(name),
        }
    }

    /// The blake3 hash of file `name`, as manifests record it (hex).
    pub fn blake3(&self, name: &str) -> Result<String> {
        match self {
            Self::Local(dir) => crate::files::hash_file(&dir.join(name))
                .with_context(|| format!("{}: cannot read", dir.join(name).display())),
            Self::Remote(remote) => Ok(blake3::hash(&remote.get(name)?).to_hex().to_string()),
        }
    }
}

/// The files of a published dataset besides its shards, uploaded when present; `manifest.json` goes last.
/// Copy the published dataset in `dir` to `remote`: verify it against its manifest, refuse a destination that
/// already holds a manifest, upload every shard and document, then `manifest.json` last with a conditional put.
/// A reader that finds the manifest finds every shard it lists; a failure before that leaves no manifest, and
/// uploading again replaces the partial objects. Returns the bytes uploaded.
pub fn upload_dataset(dir: &std::path::Path, remote: &RemoteDir) -> Result<u64> {
    let manifest = crate::contract::manifest::DatasetManifest::load_dir(dir)?;
    if let Some(problem) = manifest.verify(dir).into_iter().next() {
        bail!("{problem}; the local dataset does not match its manifest, so nothing was uploaded (re-run publish)");
    }
    if remote.size(MANIFEST_FILE).is_ok() {
        bail!(
            "{}: a dataset is already published there; choose a new prefix (a published dataset is never overwritten)",
            remote.url_of(MANIFEST_FILE)
        );
    }
    let names = manifest
        .shards
        .iter()
        .map(|shard| shard.path.clone())
        .chain(
            DOCUMENT_FILES
                .iter()
                .filter(|name| dir.join(name).exists())
                .map(|name| name.to_string()),
        );
    let mut uploaded = 0;
    for name in names {
        let bytes = std::fs::read(dir.join(&name))
            .with_context(|| format!("{}: cannot read", dir.join(&name).display()))?;
        uploaded += bytes.len() as u64;
        remote.put(&name, bytes)?;
    }
    let text = std::fs::read(dir.join(MANIFEST_FILE))?;
    uploaded += text.len() as u64;
    remote.put_new(MANIFEST_FILE, text)?;
    Ok(uploaded)
}

/// Whether `remote` already holds the dataset in `dir`: its `manifest.json` there, byte for byte, so the shards it
/// lists with their hashes (not the card or other documents, which it does not hash). A rerun of a build that was
/// uploaded before finds it so; a prefix with another dataset's manifest is refused by [`upload_dataset`].
pub fn holds_dataset(dir: &std::path::Path, remote: &RemoteDir) -> Result<bool> {
    let local = std::fs::read(dir.join(MANIFEST_FILE))
        .with_context(|| format!("{}: cannot read", dir.join(MANIFEST_FILE).display()))?;
    Ok(remote.get_if_exists(MANIFEST_FILE)?.as_ref() == Some(&local))
}

/// The published manifest at `remote`.
pub fn remote_manifest(remote: &RemoteDir) -> Result<crate::contract::manifest::DatasetManifest> {
    let text = String::from_utf8(remote.get(MANIFEST_FILE)?)
        .with_context(|| format!("{}: not UTF-8", remote.url_of(MANIFEST_FILE)))?;
    Ok(crate::contract::manifest::DatasetManifest::parse(
        &text,
        std::path::Path::new(&remote.url_of(MANIFEST_FILE)),
    )?)
}

/// Check every shard the manifest at `remote` lists against its size and blake3 (each shard is read once);
/// the problems found, one line each.
pub fn verify_remote(remote: &RemoteDir) -> Result<Vec<String>> {
    let manifest = remote_manifest(remote)?;
    let mut problems = Vec::new();
    for shard in &manifest.shards {
        let url = remote.url_of(&shard.path);
        match remote.size(&shard.path) {
            Err(_) => problems.push(format!("{url}: missing")),
            Ok(size) if size != shard.bytes => problems.push(format!(
                "{url}: {size} bytes, manifest says {} (truncated?)",
                shard.bytes
            )),
            Ok(_) => {
                let hash = blake3::hash(&remote.get(&shard.path)?).to_hex().to_string();
                if hash != shard.blake3 {
                    problems.push(format!(
                        "{url}: blake3 {hash}, manifest says {}",
                        shard.blake3
                    ));
                }
            }
        }
    }
    Ok(problems)
}

/// One object read by byte ranges, as Parquet's reader asks for them: the footer of a remote shard is a suffix
/// read (`ArrowReaderMetadata::load` asks for the last 8 bytes, then the metadata before them).
#[derive(Clone)]
pub struct RemoteObject {
    dir: Arc<RemoteDir>,
    name: String,
    len: u64,
}

impl RemoteObject {
    /// Object `name` under `dir`; one HEAD request for its size.
    pub fn open(dir: Arc<RemoteDir>, name: &str) -> Result<Self> {
        let len = dir.size(name)?;
        Ok(Self {
            dir,
            name: name.to_string(),
            len,
        })
    }

    pub fn url(&self) -> String {
        self.dir.url_of(&self.name)
    }

    /// Bytes `range` in one ranged GET.
    pub fn fetch(&self, range: Range<u64>) -> parquet::errors::Result<bytes::Bytes> {
        self.dir
            .get_range(&self.name, range)
            .map_err(|e| parquet::errors::ParquetError::External(format!("{e:#}").into()))
    }

    /// Bytes `ranges` (ranges close together merged into one GET), as the pieces of a [`ShardBytes::Fetched`].
    pub fn fetch_ranges(&self, ranges: &[Range<u64>]) -> parquet::errors::Result<ShardBytes> {
        let pieces = self
            .dir
            .get_ranges(&self.name, ranges)
            .map_err(|e| parquet::errors::ParquetError::External(format!("{e:#}").into()))?;
        Ok(ShardBytes::Fetched {
            pieces: ranges.iter().map(|r| r.start).zip(pieces).collect(),
            len: self.len,
        })
    }
}

impl parquet::file::reader::Length for RemoteObject {
    fn len(&self) -> u64 {
        self.len
    }
}

impl parquet::file::reader::ChunkReader for RemoteObject {
    type T = bytes::buf::Reader<bytes::Bytes>;

    fn get_read(&self, start: u64) -> parquet::errors::Result<Self::T> {
        use bytes::Buf;
        Ok(self.fetch(start..self.len)?.reader())
    }

    fn get_bytes(&self, start: u64, length: usize) -> parquet::errors::Result<bytes::Bytes> {
        self.fetch(start..start + length as u64)
    }
}

/// Where a shard reader ([`crate::contract::shard::ShardFile`]) takes its bytes from: the local file, or the
/// byte ranges of one row group (all its column chunks, or only the ones a read needs) fetched ahead from object
/// storage.
pub enum ShardBytes {
    File(std::fs::File),
    /// `(offset, bytes)` pieces of a file of `len` bytes.
    Fetched {
        pieces: Vec<(u64, bytes::Bytes)>,
        len: u64,
    },
}

impl ShardBytes {
    /// Bytes `start..start + length`, which must lie inside one fetched piece.
    fn slice(&self, start: u64, length: u64) -> parquet::errors::Result<bytes::Bytes> {
        if let ShardBytes::Fetched { pieces, .. } = self {
            for (offset, bytes) in pieces {
                if start >= *offset && start + length <= offset + bytes.len() as u64 {
                    let from = (start - offset) as usize;
                    return Ok(bytes.slice(from..from + length as usize));
                }
            }
        }
        Err(parquet::errors::ParquetError::General(format!(
            "bytes {start}..{} lie outside what was fetched of the row group",
            start + length
        )))
    }

    /// From `start` to the end of the fetched piece holding it.
    fn rest_of_piece(&self, start: u64) -> parquet::errors::Result<bytes::Bytes> {
        if let ShardBytes::Fetched { pieces, .. } = self {
            // Strictly inside: the column chunks of a row group lie end to end, so a chunk's first byte is also
            // the end of the piece before it.
            let holding = pieces
                .iter()
                .find(|(offset, bytes)| start >= *offset && start < offset + bytes.len() as u64);
            if let Some((offset, bytes)) = holding {
                return Ok(bytes.slice((start - offset) as usize..));
            }
        }
        Err(parquet::errors::ParquetError::General(format!(
            "byte {start} lies outside what was fetched of the row group"
        )))
    }
}

impl parquet::file::reader::Length for ShardBytes {
    fn len(&self) -> u64 {
        match self {
            ShardBytes::File(file) => parquet::file::reader::Length::len(file),
            ShardBytes::Fetched { len, .. } => *len,
        }
    }
}

impl parquet::file::reader::ChunkReader for ShardBytes {
    type T = Box<dyn std::io::Read + Send>;

    fn get_read(&self, start: u64) -> parquet::errors::Result<Self::T> {
        use bytes::Buf;
        match self {
            ShardBytes::File(file) => Ok(Box::new(parquet::file::reader::ChunkReader::get_read(
                file, start,
            )?)),
            ShardBytes::Fetched { .. } => Ok(Box::new(self.rest_of_piece(start)?.reader())),
        }
    }

    fn get_bytes(&self, start: u64, length: usize) -> parquet::errors::Result<bytes::Bytes> {
        match self {
            ShardBytes::File(file) => {
                parquet::file::reader::ChunkReader::get_bytes(file, start, length)
            }
            ShardBytes::Fetched { .. } => self.slice(start, length as u64),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A conditional put whose object already holds exactly its bytes succeeded earlier (its response was lost
    /// and object_store's retry found the object): success. Other bytes there: refused, and left as they were.
    #[test]
    fn a_conditional_put_finding_its_own_bytes_succeeds_and_other_bytes_are_refused() {
        let remote = RemoteDir::open("memory:///datasets/a").unwrap();
        let manifest = br#"{"name": "a"}"#.to_vec();
        remote.put_new("manifest.json", manifest.clone()).unwrap();
        remote.put_new("manifest.json", manifest.clone()).unwrap();
        let refused = format!(
            "{:#}",
            remote
                .put_new("manifest.json", br#"{"name": "b"}"#.to_vec())
                .unwrap_err()
        );
        assert!(refused.contains("already exists"), "{refused}");
        assert_eq!(remote.get("manifest.json").unwrap(), manifest);
        assert_eq!(remote.get_if_exists("missing.json").unwrap(), None);
    }

    #[test]
    fn object_stores_this_build_lacks_are_refused_in_one_line() {
        for url in ["gs://bucket/dataset", "az://container/dataset"] {
            let message = format!("{:#}", RemoteDir::open(url).err().unwrap());
            assert!(
                message.starts_with(url) && message.contains("s3://") && !message.contains('\n'),
                "{message}"
            );
        }
    }
}

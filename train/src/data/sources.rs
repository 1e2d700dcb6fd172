//! Where training samples come from: published shards on disk, a dataset server over HTTP, or object storage.
//! Every source returns the same rows for the same row-group references, so an epoch is the same from any.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use dataset::contract::manifest::DatasetManifest;
use dataset::contract::planner::RowGroupRef;
use dataset::contract::schema::{Sample, Split};

/// Where samples come from. Implementations must return identical rows for identical references, so the same
/// (seed, epoch) gives the same batches from any source.
pub trait SampleSource: Send + Sync {
    /// For messages: a path or URL.
    fn describe(&self) -> String;
    fn manifest(&self) -> &DatasetManifest;
    /// Row groups of one split, in a fixed order (shard name, then row-group index).
    fn row_groups(&self, split: Split) -> Result<Vec<RowGroupRef>>;
    fn read_row_group(&self, group: &RowGroupRef) -> Result<Vec<Sample>>;
}

/// Every row group of `split`'s shards (in the manifest's shard order), from each shard's row-group sizes.
fn row_group_refs(
    manifest: &DatasetManifest,
    split: Split,
    sizes: impl Fn(&str) -> Result<Vec<usize>>,
) -> Result<Vec<RowGroupRef>> {
    let mut groups = Vec::new();
    for shard in manifest.split_shards(split) {
        groups.extend(
            sizes(shard)?
                .into_iter()
                .enumerate()
                .map(|(row_group, rows)| RowGroupRef {
                    shard: shard.to_string(),
                    row_group,
                    rows,
                }),
        );
    }
    Ok(groups)
}

/// A published dataset directory (`manifest.json` + shards).
pub struct LocalSource {
    dir: PathBuf,
    manifest: DatasetManifest,
}

impl LocalSource {
    pub fn open(dir: &Path) -> Result<Self> {
        let manifest = DatasetManifest::load_dir(dir)?;
        Ok(Self {
            dir: dir.to_path_buf(),
            manifest,
        })
    }
}

impl SampleSource for LocalSource {
    fn describe(&self) -> String {
        self.dir.display().to_string()
    }

    fn manifest(&self) -> &DatasetManifest {
        &self.manifest
    }

    fn row_groups(&self, split: Split) -> Result<Vec<RowGroupRef>> {
        row_group_refs(&self.manifest, split, |shard| {
            Ok(dataset::contract::shard::row_group_sizes(
                &self.dir.join(shard),
            )?)
        })
    }

    fn read_row_group(&self, group: &RowGroupRef) -> Result<Vec<Sample>> {
        Ok(dataset::contract::shard::read_row_group(
            &self.dir.join(&group.shard),
            group.row_group,
        )?)
    }
}

/// A dataset served by `g2r-dataset serve`: the manifest, row-group lists and row groups (Arrow IPC) come over
/// HTTP, so the planner runs here on the same row-group list as [`LocalSource`] and yields the same batches.
pub struct HttpSource {
    client: dataset::client::HttpClient,
    manifest: DatasetManifest,
}

impl HttpSource {
    pub fn open(url: &str) -> Result<Self> {
        let client = dataset::client::HttpClient::new(url)?;
        let response = client.get_ok("/v1/manifest", &[])?;
        let origin = PathBuf::from(format!("{}/v1/manifest", client.base_url()));
        let manifest = DatasetManifest::parse(&response.text(), &origin)?;
        Ok(Self { client, manifest })
    }
}

impl SampleSource for HttpSource {
    fn describe(&self) -> String {
        self.client.base_url().to_string()
    }

    fn manifest(&self) -> &DatasetManifest {
        &self.manifest
    }

    fn row_groups(&self, split: Split) -> Result<Vec<RowGroupRef>> {
        #[derive(serde::Deserialize)]
        struct Listed {
            shard: String,
            row_group: usize,
            rows: usize,
        }
        #[derive(serde::Deserialize)]
        struct Answer {
            row_groups: Vec<Listed>,
        }
        let answer: Answer = self
            .client
            .get_json(&format!("/v1/row-groups?split={split}"))?;
        Ok(answer
            .row_groups
            .into_iter()
            .map(|g| RowGroupRef {
                shard: g.shard,
                row_group: g.row_group,
                rows: g.rows,
            })
            .collect())
    }

    fn read_row_group(&self, group: &RowGroupRef) -> Result<Vec<Sample>> {
        let path = format!("/v1/shards/{}/row-groups/{}", group.shard, group.row_group);
        let response = self
            .client
            .get_ok(&path, &[("Accept", dataset::client::ARROW_STREAM)])?;
        let samples = dataset::contract::wire::samples_from_ipc_stream(&response.body)
            .with_context(|| {
                format!(
                    "{}{path}: not an Arrow IPC stream of samples",
                    self.client.base_url()
                )
            })?;
        if samples.len() != group.rows {
            bail!(
                "{}{path}: {} rows, the row-group list said {}",
                self.client.base_url(),
                samples.len(),
                group.rows
            );
        }
        Ok(samples)
    }
}

/// A published dataset in object storage (`s3://bucket/prefix`, [`dataset::storage`]): the manifest is one GET,
/// each shard's footer two ranged GETs (once, then kept), each row group one ranged GET of its column chunks.
/// Rows decode as from local files, so the same (seed, epoch) gives the same batches.
pub struct ObjectStoreSource {
    dir: Arc<dataset::storage::RemoteDir>,
    manifest: DatasetManifest,
    shards: std::sync::Mutex<BTreeMap<String, dataset::contract::shard::ShardFile>>,
}

impl ObjectStoreSource {
    pub fn open(url: &str) -> Result<Self> {
        let dir = Arc::new(dataset::storage::RemoteDir::open(url)?);
        let manifest = dataset::storage::remote_manifest(&dir)?;
        Ok(Self {
            dir,
            manifest,
            shards: Default::default(),
        })
    }

    /// The shard's footer, read on first use.
    fn shard(&self, name: &str) -> Result<dataset::contract::shard::ShardFile> {
        if let Some(shard) = self.shards.lock().expect("shard cache poisoned").get(name) {
            return Ok(shard.clone());
        }
        let object = dataset::storage::RemoteObject::open(self.dir.clone(), name)?;
        let shard = dataset::contract::shard::ShardFile::open_remote(object)?;
        self.shards
            .lock()
            .expect("shard cache poisoned")
            .insert(name.to_string(), shard.clone());
        Ok(shard)
    }
}

impl SampleSource for ObjectStoreSource {
    fn describe(&self) -> String {
        self.dir.url().to_string()
    }

    fn manifest(&self) -> &DatasetManifest {
        &self.manifest
    }

    fn row_groups(&self, split: Split) -> Result<Vec<RowGroupRef>> {
        row_group_refs(&self.manifest, split, |shard| {
            Ok(self.shard(shard)?.row_group_sizes())
        })
    }

    fn read_row_group(&self, group: &RowGroupRef) -> Result<Vec<Sample>> {
        Ok(self.shard(&group.shard)?.read_row_group(group.row_group)?)
    }
}

/// `--data`: an `http://` URL of `g2r-dataset serve`, an object-storage URL (`s3://bucket/prefix`,
/// `file://`) of a published dataset, or a published dataset directory.
pub fn open_source(data: &str) -> Result<Arc<dyn SampleSource>> {
    if data.starts_with("http://") || data.starts_with("https://") {
        Ok(Arc::new(HttpSource::open(data)?))
    } else if dataset::storage::is_url(data) {
        Ok(Arc::new(ObjectStoreSource::open(data)?))
    } else {
        Ok(Arc::new(LocalSource::open(Path::new(data))?))
    }
}

/// Several publications trained on as one (`fit --also-train-on`): the train split is every training member's
/// row groups, the first member's then each further one's in turn; validation is the first member's, then that of
/// each member pooled for validation only (`fit --also-validate-on`: held-out worlds), and test is the first
/// member's alone, so a run is scored against the held-out tiles of the dataset it names first. Shard names carry
/// their member's place in the pool (`1:train-00003.parquet`), so the row-group list is one fixed order and the
/// same (seed, epoch) gives the same batches.
pub struct PooledSource {
    /// The training members (the first, then `--also-train-on`'s), then the validation-only ones.
    members: Vec<Arc<dyn SampleSource>>,
    train_members: usize,
}

impl PooledSource {
    /// `first` pooled with `more`. Every member must be published under the first's schema, with its own
    /// dataset name (the run's config records the names).
    pub fn new(first: Arc<dyn SampleSource>, more: Vec<Arc<dyn SampleSource>>) -> Result<Self> {
        let train_members = 1 + more.len();
        let members: Vec<_> = std::iter::once(first).chain(more).collect();
        Self::check_members(&members)?;
        Ok(Self {
            members,
            train_members,
        })
    }

    /// This pool, its validation split also holding `more`'s (held-out worlds: none of their rows is trained on).
    pub fn also_validating_on(mut self, more: Vec<Arc<dyn SampleSource>>) -> Result<Self> {
        self.members.extend(more);
        Self::check_members(&self.members)?;
        Ok(self)
    }

    /// Every member under the first's schema, each with its own dataset name.
    fn check_members(members: &[Arc<dyn SampleSource>]) -> Result<()> {
        let first = &members[0];
        let (schema, mut names) = (
            first.manifest().schema_version.clone(),
            vec![first.manifest().name.clone()],
        );
        for member in &members[1..] {
            let manifest = member.manifest();
            if manifest.schema_version != schema {
                bail!(
                    "{}: dataset schema {} cannot be trained on beside {}'s {schema}: re-run `g2r-pipeline run` on \
                     the older one",
                    member.describe(),
                    manifest.schema_version,
                    first.describe()
                );
            }
            if names.contains(&manifest.name) {
                bail!(
                    "{}: a dataset named {:?} is already in the pool: give each publication its own \
                     [dataset] name, or drop the repeated --also-train-on or --also-validate-on",
                    member.describe(),
                    manifest.name
                );
            }
            names.push(manifest.name.clone());
        }
        Ok(())
    }

    /// The dataset names of the training members after the first, in pool order.
    pub fn further_names(&self) -> Vec<String> {
        self.names(1..self.train_members)
    }

    /// The dataset names of the validation-only members, in pool order.
    pub fn validation_names(&self) -> Vec<String> {
        self.names(self.train_members..self.members.len())
    }

    fn names(&self, members: std::ops::Range<usize>) -> Vec<String> {
        self.members[members]
            .iter()
            .map(|m| m.manifest().name.clone())
            .collect()
    }

    /// The member a row group belongs to, and its shard name there.
    fn member_of<'a>(&self, shard: &'a str) -> Result<(&dyn SampleSource, &'a str)> {
        let place = shard
            .split_once(':')
            .and_then(|(place, name)| Some((place.parse::<usize>().ok()?, name)));
        match place {
            Some((place, name)) if place < self.members.len() => {
                Ok((self.members[place].as_ref(), name))
            }
            _ => bail!(
                "{shard}: not a row group of this pool of {} datasets",
                self.members.len()
            ),
        }
    }
}

impl SampleSource for PooledSource {
    fn describe(&self) -> String {
        let all: Vec<String> = self.members.iter().map(|m| m.describe()).collect();
        all.join(" + ")
    }

    fn manifest(&self) -> &DatasetManifest {
        self.members[0].manifest()
    }

    fn row_groups(&self, split: Split) -> Result<Vec<RowGroupRef>> {
        let places: Vec<usize> = match split {
            Split::Train => (0..self.train_members).collect(),
            // The first member's held-out tiles, then the validation-only members'.
            Split::Val => std::iter::once(0)
                .chain(self.train_members..self.members.len())
                .collect(),
            Split::Test => vec![0],
        };
        let mut groups = Vec::new();
        for place in places {
            let member = &self.members[place];
            groups.extend(
                member
                    .row_groups(split)?
                    .into_iter()
                    .map(|group| RowGroupRef {
                        shard: format!("{place}:{}", group.shard),
                        ..group
                    }),
            );
        }
        Ok(groups)
    }

    fn read_row_group(&self, group: &RowGroupRef) -> Result<Vec<Sample>> {
        let (member, shard) = self.member_of(&group.shard)?;
        member.read_row_group(&RowGroupRef {
            shard: shard.to_string(),
            ..group.clone()
        })
    }
}

//! Streaming training data: a [`SampleSource`] (local shards, a dataset server over HTTP, or object storage),
//! the epoch order from [`dataset::contract::planner`], dihedral augmentation, and a background thread that prefetches host
//! batches while the device computes.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::mpsc::{sync_channel, Receiver};
use std::sync::Arc;
use std::thread::JoinHandle;

use anyhow::{bail, Context, Result};
use dataset::contract::manifest::DatasetManifest;
use dataset::contract::planner::{plan_epoch, plan_weighted_epoch, RowGroupRef};
use dataset::contract::rng::keyed_rng;
use dataset::contract::schema::{Sample, Split, CONTEXT_PX, DEM_PX};
use rand::Rng;
use rayon::prelude::*;

use crate::augment::Dihedral;
use crate::replicas::Replica;

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
        let samples = dataset::contract::shard::samples_from_ipc_stream(&response.body)
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

/// `--data`: an `http://` URL of `g2r-dataset serve`, an object-storage URL (`s3://bucket/prefix`, `gs://`, `az://`,
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

/// One batch on the host, f64 (the device's float type decides the precision on upload). Rasters are
/// `N × edge²` row-major, north row first.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct HostBatch {
    pub sample_ids: Vec<String>,
    /// Network input `N × C × 128²` ([`InputNormalisation::push_planes`]): interior heights minus the crop mean over
    /// the train-split std, then (when the run uses it) absolute elevation.
    pub net_input: Vec<f64>,
    /// Input planes per sample (`C`).
    pub input_channels: usize,
    /// Context input `N × C' × 32²` ([`InputNormalisation::push_context`]); empty when the run has none.
    pub context_input: Vec<f64>,
    /// Context planes per sample (`C'`; 0 without a context input).
    pub context_channels: usize,
    /// `N × 130²` heights relative to each crop's ENU origin (with apron), metres.
    pub relative_heights_m: Vec<f64>,
    pub image: Vec<f64>,
    pub valid: Vec<f64>,
    pub lit: Vec<f64>,
    pub sun_dir_enu: Vec<f64>,
    pub camera_pos_enu_m: Vec<f64>,
    pub map_to_en: Vec<f64>,
    pub gsd_m: Vec<f64>,
    pub origin_height_m: Vec<f64>,
}

impl HostBatch {
    pub fn len(&self) -> usize {
        self.sample_ids.len()
    }

    pub fn is_empty(&self) -> bool {
        self.sample_ids.is_empty()
    }

    /// Assemble a batch, with the network input normalised as `input` says (docs/design.md, Data contract).
    pub fn from_samples(samples: &[Sample], input: &InputNormalisation) -> Self {
        let mut b = HostBatch {
            input_channels: input.channels(),
            context_channels: input.context_channels(),
            ..HostBatch::default()
        };
        for s in samples {
            b.sample_ids.push(s.sample_id.clone());
            let crop = crop_interior_m(s);
            input.push_planes(&crop, &mut b.net_input);
            if input.context.is_some() {
                let context = s.context.as_ref().unwrap_or_else(|| {
                    panic!(
                        "sample {} has no context window, but the run feeds one (checked when a run starts)",
                        s.sample_id
                    )
                });
                input.push_context(&crop, &context.heights_m, &mut b.context_input);
            }
            b.relative_heights_m
                .extend(s.dem_m.iter().map(|&h| h as f64 - s.enu_origin_height_m));
            b.image.extend(s.image.iter().map(|&v| v as f64));
            b.valid.extend(s.valid.iter().map(|&v| f64::from(v != 0)));
            b.lit.extend(s.sun_lit.iter().map(|&v| v as f64));
            b.sun_dir_enu.extend(s.sun_dir_enu);
            b.camera_pos_enu_m.extend(s.camera_pos_enu_m);
            b.map_to_en.extend(s.map_to_en);
            b.gsd_m.push(s.gsd_m);
            b.origin_height_m.push(s.enu_origin_height_m);
        }
        b
    }
}

/// A sample's interior heights (the `128²` crop inside the one-pixel apron), row-major, metres.
pub fn crop_interior_m(sample: &Sample) -> Vec<f64> {
    dataset::contract::schema::crop_interior(&sample.dem_m).collect()
}

/// Mean slope of the crop's delivered DEM in degrees: the tilt of [`dataset::science::geometry::plane_normal`] from central
/// differences over the crop's own cells (the apron gives their neighbours), on the map grid (the slope's size
/// does not depend on which way rows run).
pub fn mean_slope_deg(sample: &Sample) -> f64 {
    let (n, gsd) = (DEM_PX, sample.gsd_m);
    let h = |c: usize, r: usize| sample.dem_m[r * n + c] as f64;
    let mut sum = 0.0;
    for r in 1..n - 1 {
        for c in 1..n - 1 {
            let dx = (h(c + 1, r) - h(c - 1, r)) / (2.0 * gsd);
            let dy = (h(c, r + 1) - h(c, r - 1)) / (2.0 * gsd);
            sum += dataset::science::geometry::plane_normal(dx, dy)
                .z
                .clamp(-1.0, 1.0)
                .acos();
        }
    }
    (sum / ((n - 2) * (n - 2)) as f64).to_degrees()
}

/// Crops at least this steep (mean slope of the delivered DEM, [`mean_slope_deg`]) are the ones a steep-weighted
/// epoch draws more often: on tycho-full they are 28 % of the test crops and hold the complex crater's walls.
pub const STEEP_SLOPE_DEG: f64 = 20.0;

/// Each row's draw weight for a steep-weighted epoch ([`dataset::contract::planner::plan_weighted_epoch`]), in the split's
/// row-group order, then row order: `steep_weight` for a crop whose mean slope is at least [`STEEP_SLOPE_DEG`],
/// 1 otherwise. The slope is the delivered DEM's, so the weighting needs no truth. One pass over the split.
pub fn steep_row_weights(
    source: &dyn SampleSource,
    split: Split,
    steep_weight: f64,
) -> Result<Vec<f64>> {
    let mut weights = Vec::new();
    for_each_sample_group(source, split, None, |samples| {
        weights.extend(
            samples
                .par_iter()
                .map(|s| {
                    if mean_slope_deg(s) >= STEEP_SLOPE_DEG {
                        steep_weight
                    } else {
                        1.0
                    }
                })
                .collect::<Vec<f64>>(),
        );
    })?;
    Ok(weights)
}

/// How a crop's heights become the network's input planes; saved with a run (`normalisation.json`) so that
/// evaluation and inference on a new DEM feed the network exactly what training did.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct InputNormalisation {
    /// Train-split DEM std: the relief plane is (height − crop mean) / this (docs/design.md, Data contract).
    pub dem_std_m: f64,
    /// Absolute-elevation plane, (height − mean) / std over train crops, when the run uses one. The relief plane
    /// hides where a crop sits (crater floor, mare plain or rim), and at the crop scale that explains much of the
    /// albedo (`--elevation-input`); runs written before it existed have none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub elevation: Option<ElevationNormalisation>,
    /// Context input, when the run uses one (`--context-input`): the sample's wide coarse DEM window
    /// (`dataset::contract::context`) relative to the crop's mean height, so the network sees whether the crop lies in a
    /// crater, on its wall or on a plain kilometres across.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub context: Option<ContextNormalisation>,
}

/// The context window's cell size (the one the training data was cut with; inference cuts the same) and the std
/// its heights relative to the crop mean are divided by.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ContextNormalisation {
    pub gsd_m: f64,
    pub std_m: f64,
    /// Also feed the window's absolute heights, normalised as the elevation plane is (`--context-absolute`).
    /// Relative heights show where the crop lies in the terrain; absolute ones show how high that terrain
    /// stands, which on a crater wall is what tells the unit under it (docs/crater-diagnosis.md). Runs written
    /// before it existed have none.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub absolute: bool,
}

/// Planes of the relative context input: relative height, then a mask (1 where the cell has DEM). An absolute
/// context adds its plane between the two.
pub const CONTEXT_CHANNELS: usize = 2;

impl ContextNormalisation {
    /// From train samples' context windows: their common cell size, and the pooled std of every finite cell's
    /// height relative to its crop's mean.
    pub fn of_samples<'a>(samples: impl IntoIterator<Item = &'a Sample>) -> Result<Self> {
        let (mut gsd_m, mut n, mut sum_sq) = (None::<f64>, 0usize, 0f64);
        for s in samples {
            let Some(context) = &s.context else {
                bail!(
                    "sample {} has no context window: the dataset predates schema 1.2; re-run `g2r-pipeline run` to publish one with context_dem",
                    s.sample_id
                );
            };
            match gsd_m {
                Some(g) if g != context.gsd_m => bail!(
                    "samples' context windows have different cell sizes ({g} m and {} m at {})",
                    context.gsd_m,
                    s.sample_id
                ),
                _ => gsd_m = Some(context.gsd_m),
            }
            let mean = crop_mean(&crop_interior_m(s));
            for &z in context.heights_m.iter().filter(|z| z.is_finite()) {
                n += 1;
                sum_sq += (z as f64 - mean).powi(2);
            }
        }
        let (Some(gsd_m), true) = (gsd_m, n >= 2) else {
            bail!("no finite context heights to normalise the context input with");
        };
        let std_m = (sum_sq / n as f64).sqrt();
        if std_m <= 0.0 {
            bail!("every context window is flat at its crop's height: the context input would divide by zero");
        }
        Ok(Self {
            gsd_m,
            std_m,
            absolute: false,
        })
    }
}

/// Mean of the finite heights (0 when there are none).
fn crop_mean(heights_m: &[f64]) -> f64 {
    let finite = heights_m.iter().filter(|z| z.is_finite());
    let count = finite.clone().count();
    finite.sum::<f64>() / count.max(1) as f64
}

/// Mean and std of absolute heights over train crops' pixels.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ElevationNormalisation {
    pub mean_m: f64,
    pub std_m: f64,
}

impl ElevationNormalisation {
    /// Pooled mean and std of the crops' heights (`crops` of `CROP_PX²` each; non-finite heights skipped).
    pub fn of_crops<'a>(crops: impl IntoIterator<Item = &'a [f64]>) -> Result<Self> {
        let (mut n, mut sum, mut sum_sq) = (0usize, 0f64, 0f64);
        for crop in crops {
            for &z in crop.iter().filter(|z| z.is_finite()) {
                n += 1;
                sum += z;
                sum_sq += z * z;
            }
        }
        if n < 2 {
            bail!("no finite heights to normalise the elevation input with");
        }
        let mean_m = sum / n as f64;
        // Heights are ~−1e3 m with ~1e2 m spread: the one-pass form loses ~1e-10 relative here, far below need.
        let std_m = ((sum_sq / n as f64 - mean_m * mean_m).max(0.0)).sqrt();
        if std_m <= 0.0 {
            bail!("train crops all have the same height: the elevation input would divide by zero");
        }
        Ok(Self { mean_m, std_m })
    }
}

impl InputNormalisation {
    /// Relief only (the paper's input).
    pub fn relief(dem_std_m: f64) -> Self {
        Self {
            dem_std_m,
            elevation: None,
            context: None,
        }
    }

    pub fn channels(&self) -> usize {
        1 + usize::from(self.elevation.is_some())
    }

    /// Refuse a dataset that cannot feed this input: a context input needs schema 1.2 or later (`context_dem`).
    pub fn check_dataset(&self, source: &dyn SampleSource) -> Result<()> {
        let version = &source.manifest().schema_version;
        let minor = version
            .split('.')
            .nth(1)
            .and_then(|m| m.parse::<u32>().ok());
        if self.context.is_some() && minor.is_none_or(|m| m < 2) {
            bail!(
                "{}: dataset schema {version} has no context windows, but the run feeds one (--context-input): re-run `g2r-pipeline run` to publish schema 1.2",
                source.describe()
            );
        }
        Ok(())
    }

    /// Context planes per sample (0 without a context input).
    pub fn context_channels(&self) -> usize {
        self.context
            .map_or(0, |c| CONTEXT_CHANNELS + usize::from(c.absolute))
    }

    /// Append one crop's planes (`CROP_PX²` heights, row-major, metres) channel after channel. A non-finite height
    /// (a DEM hole at inference) is fed as the crop's mean height in every plane: a function of the crop alone,
    /// so the same terrain gives the same input whatever the DEM's extent.
    pub fn push_planes(&self, heights_m: &[f64], out: &mut Vec<f64>) {
        let mean = crop_mean(heights_m);
        let filled = |z: f64| if z.is_finite() { z } else { mean };
        out.extend(
            heights_m
                .iter()
                .map(|&z| (filled(z) - mean) / self.dem_std_m),
        );
        if let Some(e) = self.elevation {
            out.extend(heights_m.iter().map(|&z| (filled(z) - e.mean_m) / e.std_m));
        }
    }

    /// Append one crop's context planes (`CONTEXT_PX²` each): the window's heights minus the crop's mean height
    /// (`heights_m`, as in [`Self::push_planes`]) over the context std, 0 where a cell has no DEM; with an
    /// absolute context, the window's heights normalised as the elevation plane, 0 where no DEM; then the mask.
    /// Panics when the run has no context input.
    pub fn push_context(&self, heights_m: &[f64], context_m: &[f32], out: &mut Vec<f64>) {
        let c = self
            .context
            .expect("push_context on a run without context input");
        assert_eq!(
            context_m.len(),
            CONTEXT_PX * CONTEXT_PX,
            "context window size"
        );
        let mean = crop_mean(heights_m);
        out.extend(context_m.iter().map(|&z| {
            if z.is_finite() {
                (z as f64 - mean) / c.std_m
            } else {
                0.0
            }
        }));
        if c.absolute {
            let e = self
                .elevation
                .expect("an absolute context is normalised as the elevation plane (checked when a run starts)");
            out.extend(context_m.iter().map(|&z| {
                if z.is_finite() {
                    (z as f64 - e.mean_m) / e.std_m
                } else {
                    0.0
                }
            }));
        }
        out.extend(context_m.iter().map(|z| f64::from(u8::from(z.is_finite()))));
    }
}

/// How an epoch is streamed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct StreamConfig {
    pub seed: u64,
    pub batch_size: usize,
    /// Row groups shuffled together (memory ≈ window × 256 rows × 215 KB).
    pub window_groups: usize,
    /// Apply a random dihedral transform per sample.
    pub augment: bool,
    /// Cap on samples per epoch (CPU budgets); `None` = the whole split.
    pub max_samples: Option<usize>,
}

/// The dihedral transform of the sample at `position` of epoch `epoch` (keyed, so resuming reproduces it).
pub fn augmentation_for(seed: u64, epoch: u64, position: usize) -> Dihedral {
    let index = keyed_rng(seed, "augment", (epoch << 32) | position as u64).random_range(0..8u8);
    Dihedral::from_index(index)
}

/// Batches of one epoch from `start_batch` on, produced by a background thread (bounded queue of 2). A replica
/// of a data-parallel fit gets its stride of the epoch's rows; every replica gets as many as the others (the
/// epoch's rows cut to a multiple of the replica count), so all take the same steps.
pub struct EpochStream {
    receiver: Receiver<Result<HostBatch>>,
    worker: Option<JoinHandle<()>>,
    pub batches: usize,
}

impl EpochStream {
    // What to read (source, split, stream, input, weights) and where in the run (epoch, batch, replica).
    #[allow(clippy::too_many_arguments)]
    pub fn start(
        source: Arc<dyn SampleSource>,
        split: Split,
        config: StreamConfig,
        input: InputNormalisation,
        row_weights: Option<Arc<[f64]>>,
        epoch: u64,
        start_batch: usize,
        replica: Replica,
    ) -> Result<Self> {
        let Replica { rank, world } = replica;
        let groups = source.row_groups(split)?;
        if groups.is_empty() {
            bail!(
                "{}: split '{split}' has no shards: check the manifest's split counts",
                source.describe()
            );
        }
        let plan = match (&row_weights, config.max_samples) {
            // Weighted: the epoch is `max` rows drawn in proportion to their weights.
            (Some(weights), Some(max)) => plan_weighted_epoch(
                &groups,
                weights,
                max.min(weights.len()),
                config.seed,
                epoch,
                config.window_groups,
                rank,
                world,
            ),
            (Some(_), None) => bail!(
                "row weights need a cap on samples per epoch (--max-train-samples): every row is visited otherwise"
            ),
            (None, _) => plan_epoch(
                &groups,
                config.seed,
                epoch,
                config.window_groups,
                rank,
                world,
            ),
        };
        let epoch_rows = match (&row_weights, config.max_samples) {
            (Some(weights), Some(max)) => max.min(weights.len()),
            _ => groups.iter().map(|g| g.rows).sum(),
        };
        // This replica's share of the epoch's (capped) rows: the same for every replica.
        let total = config.max_samples.map_or(epoch_rows, |m| m.min(epoch_rows)) / world;
        let batches = total.div_ceil(config.batch_size);
        let (sender, receiver) = sync_channel(2);
        let worker = std::thread::spawn(move || {
            let mut cache: BTreeMap<usize, Vec<Sample>> = BTreeMap::new();
            let mut cached_window = usize::MAX;
            for batch in start_batch..batches {
                let range = batch * config.batch_size..((batch + 1) * config.batch_size).min(total);
                let mut samples = Vec::with_capacity(range.len());
                for position in range {
                    let row = plan.rows[position];
                    let window = plan.window_of[position];
                    if window != cached_window {
                        // Hold one window's row groups at a time: bounded memory whatever the split size.
                        cache.clear();
                        for &g in &plan.windows[window] {
                            match source.read_row_group(&groups[g]) {
                                Ok(rows) => {
                                    cache.insert(g, rows);
                                }
                                Err(e) => {
                                    let _ = sender.send(Err(e));
                                    return;
                                }
                            }
                        }
                        cached_window = window;
                    }
                    let sample = &cache[&row.group][row.row];
                    // Keyed by the row's place in the whole epoch, so a replica turns its rows as one process would.
                    let epoch_position = position * world + rank;
                    samples.push(if config.augment {
                        augmentation_for(config.seed, epoch, epoch_position).apply(sample)
                    } else {
                        sample.clone()
                    });
                }
                if sender
                    .send(Ok(HostBatch::from_samples(&samples, &input)))
                    .is_err()
                {
                    return; // the consumer stopped early
                }
            }
        });
        Ok(Self {
            receiver,
            worker: Some(worker),
            batches,
        })
    }
}

impl Iterator for EpochStream {
    type Item = Result<HostBatch>;
    fn next(&mut self) -> Option<Self::Item> {
        match self.receiver.recv() {
            Ok(item) => Some(item),
            Err(_) => {
                if let Some(worker) = self.worker.take() {
                    if worker.join().is_err() {
                        return Some(Err(anyhow::anyhow!("data loader thread panicked")));
                    }
                }
                None
            }
        }
    }
}

/// Call `f` with the samples of each row group of a split in file order, one row group in memory at a time,
/// whatever the split's size. With `max` below the split's size, the samples are `max` rows spread evenly over the
/// whole split ([`dataset::contract::planner::spread_rows`]), not its first rows: evaluation, validation and calibration
/// subsets then see every ortho and tile.
pub fn for_each_sample_group(
    source: &dyn SampleSource,
    split: Split,
    max: Option<usize>,
    mut f: impl FnMut(&[Sample]),
) -> Result<()> {
    let groups = source.row_groups(split)?;
    let picks = dataset::contract::planner::spread_rows(&groups, max.unwrap_or(usize::MAX));
    // Picks are in file order, so each group is read once, and only groups that hold a pick are read.
    for chunk in picks.chunk_by(|a, b| a.group == b.group) {
        let group = &groups[chunk[0].group];
        let samples = source.read_row_group(group)?;
        if samples.len() != group.rows {
            bail!(
                "{}: row group {} of {} holds {} rows, but its listing says {}; the dataset changed while being \
                 read: re-run with a consistent copy (`g2r-dataset verify` checks the shards)",
                source.describe(),
                group.row_group,
                group.shard,
                samples.len(),
                group.rows
            );
        }
        if chunk.len() == samples.len() {
            f(&samples);
        } else {
            let wanted: Vec<Sample> = chunk.iter().map(|r| samples[r.row].clone()).collect();
            f(&wanted);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn planes_are_relief_then_elevation_and_a_hole_is_fed_at_the_crop_mean() {
        let input = InputNormalisation {
            dem_std_m: 2.0,
            elevation: Some(ElevationNormalisation {
                mean_m: 10.0,
                std_m: 4.0,
            }),
            context: None,
        };
        // Crop mean over the finite heights: (10 + 12 + 20) / 3 = 14.
        let mut out = Vec::new();
        input.push_planes(&[10.0, 12.0, f64::NAN, 20.0], &mut out);
        assert_eq!(out, vec![-2.0, -1.0, 0.0, 3.0, 0.0, 0.5, 1.0, 2.5]);
        assert_eq!(input.channels(), 2);

        let mut relief = Vec::new();
        InputNormalisation::relief(2.0).push_planes(&[10.0, 12.0, f64::NAN, 20.0], &mut relief);
        assert_eq!(relief, out[..4]);
        assert_eq!(InputNormalisation::relief(2.0).channels(), 1);
    }

    #[test]
    fn elevation_statistics_pool_every_finite_height_of_every_crop() {
        // Heights 1, 2, 3, 5: mean 2.75, population variance (3.0625 + 0.5625 + 0.0625 + 5.0625) / 4 = 2.1875.
        let crops = [vec![1.0, 2.0, f64::NAN, 3.0], vec![5.0, f64::INFINITY]];
        let e = ElevationNormalisation::of_crops(crops.iter().map(Vec::as_slice)).unwrap();
        assert_eq!(e.mean_m, 2.75);
        assert!((e.std_m - 2.1875f64.sqrt()).abs() < 1e-15);
        // Lunar-scale heights keep their precision in the one-pass form.
        let far = [vec![-1201.0, -1199.0]];
        let e = ElevationNormalisation::of_crops(far.iter().map(Vec::as_slice)).unwrap();
        assert_eq!((e.mean_m, e.std_m), (-1200.0, 1.0));

        let flat = [vec![3.0, 3.0]];
        let err = ElevationNormalisation::of_crops(flat.iter().map(Vec::as_slice)).unwrap_err();
        assert!(err.to_string().contains("same height"), "{err}");
        let empty: [Vec<f64>; 0] = [];
        assert!(ElevationNormalisation::of_crops(empty.iter().map(Vec::as_slice)).is_err());
    }

    /// A sample whose crop heights are all `crop_m` and whose context is `context_m` (cells beyond those given
    /// are NaN: off the DEM).
    fn sample_with_context(crop_m: f32, context_m: &[f32], gsd_m: f64) -> Sample {
        let mut s = dataset::testing::synthetic_sample(0);
        s.dem_m = vec![crop_m; DEM_PX * DEM_PX];
        let mut heights_m = vec![f32::NAN; CONTEXT_PX * CONTEXT_PX];
        heights_m[..context_m.len()].copy_from_slice(context_m);
        s.context = Some(dataset::contract::schema::ContextWindow { gsd_m, heights_m });
        s
    }

    #[test]
    fn context_planes_are_height_above_the_crop_mean_then_the_mask() {
        let input = InputNormalisation {
            context: Some(ContextNormalisation {
                gsd_m: 512.0,
                std_m: 4.0,
                absolute: false,
            }),
            ..InputNormalisation::relief(2.0)
        };
        let mut context = vec![f32::NAN; CONTEXT_PX * CONTEXT_PX];
        context[..3].copy_from_slice(&[-1190.0, -1210.0, -1202.0]);
        // Crop mean over the finite heights: (−1200 − 1204) / 2 = −1202.
        let mut out = Vec::new();
        input.push_context(&[-1200.0, f64::NAN, -1204.0], &context, &mut out);
        let n = CONTEXT_PX * CONTEXT_PX;
        assert_eq!(out.len(), 2 * n);
        assert_eq!(out[..4], [3.0, -2.0, 0.0, 0.0]);
        assert!(out[3..n].iter().all(|&v| v == 0.0), "holes are fed as 0");
        assert_eq!(out[n..n + 4], [1.0, 1.0, 1.0, 0.0]);
        assert_eq!(out[n..].iter().sum::<f64>(), 3.0);
        assert_eq!((input.channels(), input.context_channels()), (1, 2));
        assert_eq!(InputNormalisation::relief(2.0).context_channels(), 0);
        // Written without the absolute flag, as runs before it were (their normalisation.json stays the same).
        let json = serde_json::to_string(&input.context).unwrap();
        assert_eq!(json, r#"{"gsd_m":512.0,"std_m":4.0}"#);
        assert_eq!(
            serde_json::from_str::<Option<ContextNormalisation>>(&json).unwrap(),
            input.context
        );
    }

    #[test]
    fn an_absolute_context_adds_the_window_normalised_as_the_elevation_plane() {
        let input = InputNormalisation {
            elevation: Some(ElevationNormalisation {
                mean_m: -1200.0,
                std_m: 5.0,
            }),
            context: Some(ContextNormalisation {
                gsd_m: 512.0,
                std_m: 4.0,
                absolute: true,
            }),
            ..InputNormalisation::relief(2.0)
        };
        let mut context = vec![f32::NAN; CONTEXT_PX * CONTEXT_PX];
        context[..3].copy_from_slice(&[-1190.0, -1210.0, -1202.0]);
        let mut out = Vec::new();
        input.push_context(&[-1200.0, f64::NAN, -1204.0], &context, &mut out);
        let n = CONTEXT_PX * CONTEXT_PX;
        assert_eq!(out.len(), 3 * n);
        assert_eq!(input.context_channels(), 3);
        // Relative plane as without the flag; then (z + 1200) / 5; then the mask.
        assert_eq!(out[..3], [3.0, -2.0, 0.0]);
        assert_eq!(out[n..n + 4], [2.0, -2.0, -0.4, 0.0]);
        assert!(
            out[n + 3..2 * n].iter().all(|&v| v == 0.0),
            "holes are fed as 0"
        );
        assert_eq!(out[2 * n..2 * n + 4], [1.0, 1.0, 1.0, 0.0]);
        // The same terrain raised by 50 m: the relative plane is unchanged, the absolute one moves by 50 / 5.
        let raised: Vec<f32> = context.iter().map(|z| z + 50.0).collect();
        let mut moved = Vec::new();
        input.push_context(&[-1150.0, f64::NAN, -1154.0], &raised, &mut moved);
        assert_eq!(moved[..n], out[..n]);
        assert_eq!(moved[n..n + 3], [12.0, 8.0, 9.6]);
        let json = serde_json::to_string(&input.context).unwrap();
        assert!(json.contains(r#""absolute":true"#), "{json}");
    }

    #[test]
    fn context_statistics_pool_cells_relative_to_their_own_crop() {
        // Crop at −1000 with cells −1003, −997; crop at −2000 with cell −1996: deviations −3, 3, 4 → std √(34/3).
        let samples = [
            sample_with_context(-1000.0, &[-1003.0, -997.0], 512.0),
            sample_with_context(-2000.0, &[-1996.0], 512.0),
        ];
        let c = ContextNormalisation::of_samples(&samples).unwrap();
        assert_eq!(c.gsd_m, 512.0);
        assert!(
            (c.std_m - (34.0f64 / 3.0).sqrt()).abs() < 1e-12,
            "{}",
            c.std_m
        );

        let mixed = [
            samples[0].clone(),
            sample_with_context(-1000.0, &[-990.0], 256.0),
        ];
        let err = ContextNormalisation::of_samples(&mixed).unwrap_err();
        assert!(err.to_string().contains("cell sizes"), "{err}");
        let mut old = samples[0].clone();
        old.context = None;
        let err = ContextNormalisation::of_samples(&[old]).unwrap_err();
        assert!(err.to_string().contains("schema 1.2"), "{err}");
        let flat = [sample_with_context(-1000.0, &[-1000.0, -1000.0], 512.0)];
        assert!(ContextNormalisation::of_samples(&flat).is_err());
    }
}

//! Streaming training data: a [`SampleSource`] (local shards, a dataset server over HTTP, or object storage),
//! the epoch order from [`dataset::contract::planner`], dihedral augmentation, and a background thread that prefetches host
//! batches while the device computes. In data-flow order: `sources` → `normalisation` and `input_range` (fitted once) →
//! `batch` (samples to a host batch) → the epoch stream here.

mod batch;
mod input_range;
mod normalisation;
mod sources;

pub use batch::*;
pub use input_range::*;
pub use normalisation::*;
pub use sources::*;

use std::collections::BTreeMap;
use std::sync::mpsc::{sync_channel, Receiver};
use std::sync::Arc;
use std::thread::JoinHandle;

use anyhow::{bail, Result};
use dataset::contract::planner::{plan_epoch, plan_weighted_epoch};
use dataset::contract::rng::keyed_rng;
use dataset::contract::schema::{Sample, Split};
use rand::Rng;

use crate::augment::Dihedral;
use crate::data_parallel::Replica;

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

/// Batches of one epoch from `start_batch` on, produced by a background thread (bounded queue of 2), each passed
/// through the consumer's `prepare` there (a fit evaluates the renderer's terms ahead; `T` is then the batch
/// with them). A replica of a data-parallel fit gets its stride of the epoch's rows; every replica gets as many
/// as the others (the epoch's rows cut to a multiple of the replica count), so all take the same steps.
pub struct EpochStream<T = HostBatch> {
    receiver: Receiver<Result<T>>,
    worker: Option<JoinHandle<()>>,
    pub batches: usize,
}

impl<T: Send + 'static> EpochStream<T> {
    // What to read (source, split, stream, input, weights), where in the run (epoch, batch, replica), and what
    // the loader thread makes of each batch (`std::convert::identity` for the host batch itself).
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
        prepare: impl Fn(HostBatch) -> T + Send + 'static,
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
                    .send(Ok(prepare(HostBatch::from_samples(&samples, &input))))
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

impl<T> Iterator for EpochStream<T> {
    type Item = Result<T>;
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
/// subsets then see every ortho and tile. Progress is reported as `task`, in crops ([`dataset::progress`]).
pub fn for_each_sample_group(
    source: &dyn SampleSource,
    split: Split,
    max: Option<usize>,
    task: &str,
    mut f: impl FnMut(&[Sample]),
) -> Result<()> {
    let groups = source.row_groups(split)?;
    let picks = dataset::contract::planner::spread_rows(&groups, max.unwrap_or(usize::MAX));
    let progress = dataset::progress::Progress::start(task, "crops", picks.len() as u64);
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
        progress.inc(chunk.len() as u64);
    }
    progress.finish();
    Ok(())
}

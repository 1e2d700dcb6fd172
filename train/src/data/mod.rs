//! Streaming training data: a [`SampleSource`] (local shards, a dataset server over HTTP, or object storage),
//! the epoch order from [`dataset::contract::planner`], dihedral augmentation, and a background thread that prefetches host
//! batches while the device computes. In data-flow order: [`sources`] → [`normalisation`] (fitted once) →
//! [`batch`] (samples to a host batch) → the epoch stream here.

mod batch;
mod normalisation;
mod sources;

pub use batch::*;
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
use crate::replicas::Replica;

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
    use dataset::contract::schema::{CONTEXT_PX, DEM_PX};

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

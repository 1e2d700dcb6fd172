//! Epoch planning: which rows a training epoch visits and in what order, as a pure function of
//! (seed, epoch, rank, world). The trainer and the dataset server both use it, so streaming from local
//! shards and over HTTP yields the same batches.
//!
//! Order = row groups shuffled, then rows shuffled within consecutive windows of `window_groups` row groups.
//! A window is what a streaming reader holds in memory (≈ 256 rows × 215 KB per group), so the shuffle quality /
//! memory trade-off is one number. Rows go to rank `r` of `world` by stride, after shuffling.

use rand::seq::SliceRandom;

use crate::contract::rng::keyed_rng;

/// One row group of one shard (`shard` is the file name relative to the dataset directory).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RowGroupRef {
    pub shard: String,
    pub row_group: usize,
    pub rows: usize,
}

/// One row: index into the row-group list the plan was made from, and row within that group.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RowRef {
    pub group: usize,
    pub row: usize,
}

/// The rows of one epoch, in visiting order, grouped by window.
#[derive(Debug, Clone, PartialEq)]
pub struct EpochPlan {
    /// Row-group indices of each window, in the order they are read.
    pub windows: Vec<Vec<usize>>,
    /// Every row of the epoch for this rank, in order; `window_of[i]` is the window row `i` comes from.
    pub rows: Vec<RowRef>,
    pub window_of: Vec<usize>,
}

/// Plan epoch `epoch` over `groups` for `rank` of `world` (use 0 of 1 on one process).
pub fn plan_epoch(
    groups: &[RowGroupRef],
    seed: u64,
    epoch: u64,
    window_groups: usize,
    rank: usize,
    world: usize,
) -> EpochPlan {
    plan_rows(groups, None, seed, epoch, window_groups, rank, world)
}

/// Plan epoch `epoch` over `take` rows drawn with probability proportional to `weights` (one per row, in group
/// order then row order), without replacement ([`weighted_pick`]). The drawn rows keep the order [`plan_epoch`]
/// gives them, so streaming, windows and ranks behave as in an unweighted epoch of `take` rows.
#[allow(clippy::too_many_arguments)]
pub fn plan_weighted_epoch(
    groups: &[RowGroupRef],
    weights: &[f64],
    take: usize,
    seed: u64,
    epoch: u64,
    window_groups: usize,
    rank: usize,
    world: usize,
) -> EpochPlan {
    let keep = weighted_pick(weights, take, seed, epoch);
    plan_rows(groups, Some(&keep), seed, epoch, window_groups, rank, world)
}

/// Which `take` of `weights.len()` rows an epoch visits when each is drawn with probability proportional to its
/// weight, without replacement: Efraimidis–Spirakis, keep the `take` largest `ln(u) / w` with `u` uniform in
/// (0, 1). Every row's `u` is its own counter-based draw keyed by (seed, epoch, row), so the pick does not depend
/// on how rows are split among threads or ranks.
pub fn weighted_pick(weights: &[f64], take: usize, seed: u64, epoch: u64) -> Vec<bool> {
    assert!(
        weights.iter().all(|w| w.is_finite() && *w > 0.0),
        "row weights must be finite and positive"
    );
    let key = crate::contract::rng::keyed_u64(seed, "epoch-weighted-rows", epoch);
    let mut order: Vec<(f64, usize)> = weights
        .iter()
        .enumerate()
        .map(|(i, w)| {
            // 53 random bits, offset by half a step: u in (0, 1), never 0.
            let u = ((crate::contract::rng::draw_at(key, i as u64) >> 11) as f64 + 0.5)
                / (1u64 << 53) as f64;
            (u.ln() / w, i)
        })
        .collect();
    order.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    let mut keep = vec![false; weights.len()];
    for &(_, i) in order.iter().take(take) {
        keep[i] = true;
    }
    keep
}

fn plan_rows(
    groups: &[RowGroupRef],
    keep: Option<&[bool]>,
    seed: u64,
    epoch: u64,
    window_groups: usize,
    rank: usize,
    world: usize,
) -> EpochPlan {
    assert!(window_groups >= 1 && world >= 1 && rank < world);
    // Global index (group order, then row) of each group's first row: what `keep` is indexed by.
    let first_row: Vec<usize> = groups
        .iter()
        .scan(0, |next, g| {
            let first = *next;
            *next += g.rows;
            Some(first)
        })
        .collect();
    if let Some(keep) = keep {
        assert_eq!(keep.len(), groups.iter().map(|g| g.rows).sum::<usize>());
    }
    let mut order: Vec<usize> = (0..groups.len()).collect();
    order.shuffle(&mut keyed_rng(seed, "epoch-row-groups", epoch));
    let windows: Vec<Vec<usize>> = order.chunks(window_groups).map(<[usize]>::to_vec).collect();
    let (mut rows, mut window_of) = (Vec::new(), Vec::new());
    let mut position = 0usize;
    for (w, window) in windows.iter().enumerate() {
        let mut window_rows: Vec<RowRef> = window
            .iter()
            .flat_map(|&group| (0..groups[group].rows).map(move |row| RowRef { group, row }))
            .collect();
        // Keyed by (epoch, window): a window's shuffle never depends on another's.
        window_rows.shuffle(&mut keyed_rng(
            seed,
            "epoch-window-rows",
            (epoch << 24) | w as u64,
        ));
        for row in window_rows {
            if keep.is_some_and(|keep| !keep[first_row[row.group] + row.row]) {
                continue;
            }
            if position % world == rank {
                rows.push(row);
                window_of.push(w);
            }
            position += 1;
        }
    }
    EpochPlan {
        windows,
        rows,
        window_of,
    }
}

/// `max` rows spread evenly over `groups` in their fixed order (row ⌊k·total/max⌋ for k = 0..max), or every row
/// when `max` ≥ the total. A capped evaluation or validation set then covers every shard, ortho and tile instead
/// of the first few in file order (shards are written ortho by ortho, so the first N rows are one or two orthos).
pub fn spread_rows(groups: &[RowGroupRef], max: usize) -> Vec<RowRef> {
    let total: usize = groups.iter().map(|g| g.rows).sum();
    let take = max.min(total);
    let mut picks = Vec::with_capacity(take);
    let (mut k, mut first_row) = (0usize, 0usize);
    for (group, g) in groups.iter().enumerate() {
        let end = first_row + g.rows;
        loop {
            if k == take {
                return picks;
            }
            // u128: k·total overflows u64 only for absurd sizes, but the cost is nil.
            let global = (k as u128 * total as u128 / take as u128) as usize;
            if global >= end {
                break;
            }
            picks.push(RowRef {
                group,
                row: global - first_row,
            });
            k += 1;
        }
        first_row = end;
    }
    picks
}

#[cfg(test)]
mod tests {
    use super::*;

    fn groups(sizes: &[usize]) -> Vec<RowGroupRef> {
        sizes
            .iter()
            .enumerate()
            .map(|(i, &rows)| RowGroupRef {
                shard: format!("train-{:05}-of-00001.parquet", i / 3),
                row_group: i % 3,
                rows,
            })
            .collect()
    }

    #[test]
    fn every_row_once_per_epoch_and_order_depends_on_seed_and_epoch() {
        let g = groups(&[256, 256, 100, 256, 7]);
        let plan = plan_epoch(&g, 42, 0, 2, 0, 1);
        let mut seen: Vec<(usize, usize)> = plan.rows.iter().map(|r| (r.group, r.row)).collect();
        assert_eq!(seen.len(), 875);
        seen.sort();
        seen.dedup();
        assert_eq!(seen.len(), 875, "no row twice");
        assert_eq!(plan, plan_epoch(&g, 42, 0, 2, 0, 1), "pure function");
        assert_ne!(plan.rows, plan_epoch(&g, 42, 1, 2, 0, 1).rows);
        assert_ne!(plan.rows, plan_epoch(&g, 43, 0, 2, 0, 1).rows);
        // Rows only come from their own window's groups, windows in order.
        for (row, &w) in plan.rows.iter().zip(&plan.window_of) {
            assert!(plan.windows[w].contains(&row.group));
        }
        assert!(plan.window_of.windows(2).all(|p| p[0] <= p[1]));
    }

    #[test]
    fn spread_rows_are_evenly_spaced_distinct_and_reach_the_last_group() {
        let g = groups(&[256, 256, 100, 256, 7]);
        let total = 875;
        let global = |r: &RowRef| g[..r.group].iter().map(|x| x.rows).sum::<usize>() + r.row;
        for max in [1, 2, 3, 10, 100, 874] {
            let rows = spread_rows(&g, max);
            assert_eq!(rows.len(), max);
            let at: Vec<usize> = rows.iter().map(global).collect();
            assert!(
                at.windows(2).all(|p| p[0] < p[1]),
                "distinct, in file order"
            );
            assert!(rows.iter().all(|r| r.row < g[r.group].rows));
            assert_eq!(at[0], 0);
            // Gaps differ by at most one row: ⌊total/max⌋ or ⌈total/max⌉.
            let (lo, hi) = (total / max, total.div_ceil(max));
            assert!(
                at.windows(2).all(|p| (lo..=hi).contains(&(p[1] - p[0]))),
                "max {max}"
            );
            assert!(total - at[max - 1] <= hi, "reaches the end, max {max}");
        }
        // Five spread rows reach four of the five groups; the first five rows in file order are all in group 0.
        let groups_hit: Vec<usize> = spread_rows(&g, 5).iter().map(|r| r.group).collect();
        assert_eq!(groups_hit, vec![0, 0, 1, 2, 3]);
        // At or above the total: every row once, in order.
        for max in [875, 10_000] {
            let rows = spread_rows(&g, max);
            assert_eq!(
                rows.iter().map(global).collect::<Vec<_>>(),
                (0..total).collect::<Vec<_>>()
            );
        }
        assert!(spread_rows(&g, 0).is_empty());
        assert!(spread_rows(&[], 5).is_empty());
    }

    #[test]
    fn weighted_pick_draws_like_successive_sampling_proportional_to_weight() {
        // 100 rows of weight 3 among 1,000; 50 drawn per epoch. Efraimidis–Spirakis must give the same law as
        // drawing one row at a time with probability weight / remaining weight, simulated here directly.
        use rand::Rng;
        let weights: Vec<f64> = (0..1000).map(|i| if i < 100 { 3.0 } else { 1.0 }).collect();
        let (take, epochs) = (50, 2000u64);
        let mut picked_heavy = 0usize;
        for epoch in 0..epochs {
            let keep = weighted_pick(&weights, take, 9, epoch);
            assert_eq!(keep.iter().filter(|k| **k).count(), take);
            picked_heavy += keep[..100].iter().filter(|k| **k).count();
        }
        let mut rng = keyed_rng(1, "test-successive", 0);
        let mut successive_heavy = 0usize;
        for _ in 0..epochs {
            let mut left = weights.clone();
            for _ in 0..take {
                let total: f64 = left.iter().sum();
                let mut x = rng.random::<f64>() * total;
                let i = left
                    .iter()
                    .position(|w| {
                        x -= w;
                        x < 0.0
                    })
                    .unwrap_or(left.len() - 1);
                successive_heavy += usize::from(i < 100);
                left[i] = 0.0;
            }
        }
        let (es, sequential) = (
            picked_heavy as f64 / epochs as f64,
            successive_heavy as f64 / epochs as f64,
        );
        // About 12.1 heavy rows per epoch (12.5 if drawn with replacement), each mean's standard error ≈ 0.07.
        assert!((es - sequential).abs() < 0.4, "{es} vs {sequential}");
        assert!((11.0..12.5).contains(&es), "{es}");
        // Keyed: the same (seed, epoch) picks the same rows; another epoch others.
        assert_eq!(
            weighted_pick(&weights, take, 9, 3),
            weighted_pick(&weights, take, 9, 3)
        );
        assert_ne!(
            weighted_pick(&weights, take, 9, 3),
            weighted_pick(&weights, take, 9, 4)
        );
        // Equal weights keep every row when take covers them all.
        assert!(weighted_pick(&[1.0; 7], 7, 9, 0).iter().all(|k| *k));
    }

    #[test]
    fn a_weighted_epoch_visits_the_picked_rows_in_the_unweighted_order_and_ranks_partition_it() {
        let g = groups(&[256, 256, 100, 256, 7]);
        let weights: Vec<f64> = (0..875).map(|i| 1.0 + (i % 5) as f64).collect();
        let keep = weighted_pick(&weights, 300, 4, 2);
        let global = |r: &RowRef| g[..r.group].iter().map(|x| x.rows).sum::<usize>() + r.row;
        let unweighted: Vec<RowRef> = plan_epoch(&g, 4, 2, 2, 0, 1)
            .rows
            .into_iter()
            .filter(|r| keep[global(r)])
            .collect();
        let weighted = plan_weighted_epoch(&g, &weights, 300, 4, 2, 2, 0, 1);
        assert_eq!(weighted.rows, unweighted);
        for (row, &w) in weighted.rows.iter().zip(&weighted.window_of) {
            assert!(weighted.windows[w].contains(&row.group));
        }
        let parts: Vec<Vec<RowRef>> = (0..3)
            .map(|r| plan_weighted_epoch(&g, &weights, 300, 4, 2, 2, r, 3).rows)
            .collect();
        for (i, row) in weighted.rows.iter().enumerate() {
            assert_eq!(parts[i % 3][i / 3], *row);
        }
    }

    #[test]
    fn ranks_partition_the_epoch() {
        let g = groups(&[256, 256, 100]);
        let all = plan_epoch(&g, 1, 3, 2, 0, 1).rows;
        let parts: Vec<Vec<RowRef>> = (0..3).map(|r| plan_epoch(&g, 1, 3, 2, r, 3).rows).collect();
        assert_eq!(parts.iter().map(Vec::len).sum::<usize>(), all.len());
        for (i, row) in all.iter().enumerate() {
            assert_eq!(parts[i % 3][i / 3], *row);
        }
    }
}

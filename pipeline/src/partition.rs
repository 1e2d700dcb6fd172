//! A build split across processes or machines (a Slurm job array, docs/scale-out.md): partition I of N runs ingest
//! through project over its own run of orthos, in its own directory and lock ([`crate::stages::Scope`]); one merge
//! ([`crate::stages::merge`]) joins the N partitions' outputs into the single-process layout and publishes.
//!
//! The published bytes do not depend on N. Every draw is keyed by purpose and ortho or tile (never by position in
//! a list), and each partition is a run of consecutive orthos in the single-process order, which the merge keeps.

use std::ops::Range;
use std::path::{Path, PathBuf};

use anyhow::bail;

use crate::manifest::PipelineManifest;

/// Partition `index` of `count` (0-based, as Slurm's `SLURM_ARRAY_TASK_ID`); written `I/N` on command lines.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Partition {
    pub index: usize,
    pub count: usize,
}

impl std::str::FromStr for Partition {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let usage = || {
            format!("'{text}': a partition is I/N with 0 ≤ I < N, e.g. 0/4 (Slurm: $SLURM_ARRAY_TASK_ID/N)")
        };
        let (index, count) = text.split_once('/').ok_or_else(usage)?;
        let (index, count) = (
            index.trim().parse::<usize>().map_err(|_| usage())?,
            count.trim().parse::<usize>().map_err(|_| usage())?,
        );
        if index >= count {
            return Err(usage());
        }
        Ok(Self { index, count })
    }
}

impl std::fmt::Display for Partition {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

/// Where partition `part` keeps its stage outputs and lock: `OUT/partitions/{N}/{I}/`.
pub fn dir(manifest: &PipelineManifest, part: Partition) -> PathBuf {
    manifest
        .out_dir()
        .join("partitions")
        .join(part.count.to_string())
        .join(part.index.to_string())
}

/// Cut the orthos (in single-process order) into `count` runs of consecutive orthos with about equal work.
///
/// Work is the ortho's footprint on the DEM (its bounds clipped to the DEM's), read from the file headers: the
/// crops an ortho yields are proportional to its valid area, which is known only after erosion, and the footprint
/// is the area known before any pixel is read. Each cut falls where the running total is nearest to a multiple of
/// total / count; every partition gets at least one ortho.
pub fn plan(dem: &Path, images: &[PathBuf], count: usize) -> anyhow::Result<Vec<Range<usize>>> {
    if count == 0 || count > images.len() {
        bail!(
            "{count} partitions for {} orthos: use between 1 and {} partitions",
            images.len(),
            images.len()
        );
    }
    let (_, dem_info) = dataset::science::raster::open_lunar(dem)?;
    let (dx0, dy0, dx1, dy1) = dem_info.transform.bounds(dem_info.width, dem_info.height);
    let areas = images
        .iter()
        .map(|image| -> anyhow::Result<f64> {
            let (_, info) = dataset::science::raster::open_lunar(image)?;
            let (x0, y0, x1, y1) = info.transform.bounds(info.width, info.height);
            Ok((x1.min(dx1) - x0.max(dx0)).max(0.0) * (y1.min(dy1) - y0.max(dy0)).max(0.0))
        })
        .collect::<anyhow::Result<Vec<f64>>>()?;
    Ok(cut_by_work(&areas, count))
}

/// Runs of consecutive items, `count` of them, each non-empty, cut where the running work is nearest to k × total
/// / count.
pub fn cut_by_work(work: &[f64], count: usize) -> Vec<Range<usize>> {
    let n = work.len();
    assert!((1..=n).contains(&count), "1 ≤ count ≤ items");
    let mut prefix = vec![0.0];
    for w in work {
        prefix.push(prefix.last().expect("starts with 0") + w.max(0.0));
    }
    let total = prefix[n];
    let mut cuts = vec![0];
    for k in 1..count {
        let target = total * k as f64 / count as f64;
        // The cut nearest the target, leaving at least one item before it (after the previous cut) and one for
        // each partition still to come.
        let lowest = cuts[k - 1] + 1;
        let highest = n - (count - k);
        let cut = (lowest..=highest)
            .min_by(|&a, &b| {
                (prefix[a] - target)
                    .abs()
                    .total_cmp(&(prefix[b] - target).abs())
            })
            .expect("lowest ≤ highest");
        cuts.push(cut);
    }
    cuts.push(n);
    cuts.windows(2).map(|w| w[0]..w[1]).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn partitions_parse_as_index_over_count() {
        assert_eq!(
            "2/4".parse::<Partition>(),
            Ok(Partition { index: 2, count: 4 })
        );
        assert_eq!(Partition { index: 0, count: 1 }.to_string(), "0/1");
        for bad in ["4/4", "1", "a/2", "1/0", "-1/3"] {
            let err = bad.parse::<Partition>().unwrap_err();
            assert!(err.contains("I/N"), "{bad}: {err}");
        }
    }

    #[test]
    fn cuts_balance_work_not_item_count() {
        // One heavy item and many light ones: halves by work put the heavy one alone.
        let work = [10.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0];
        assert_eq!(cut_by_work(&work, 2), vec![0..1, 1..11]);
        // Equal work: equal runs.
        assert_eq!(cut_by_work(&[1.0; 8], 4), vec![0..2, 2..4, 4..6, 6..8]);
        // As many partitions as items: one each, even when all the work sits in the first.
        assert_eq!(cut_by_work(&[5.0, 0.0, 0.0], 3), vec![0..1, 1..2, 2..3]);
        assert_eq!(cut_by_work(&[1.0, 2.0, 3.0], 1), vec![0..3]);
    }

    #[test]
    fn cuts_are_consecutive_nonempty_and_cover_everything() {
        // Property over many sizes and work patterns.
        for n in 1..40usize {
            let work: Vec<f64> = (0..n).map(|i| ((i * 7919) % 13) as f64 + 0.5).collect();
            for count in 1..=n {
                let cuts = cut_by_work(&work, count);
                assert_eq!(cuts.len(), count);
                assert_eq!(cuts[0].start, 0);
                assert_eq!(cuts[count - 1].end, n);
                assert!(cuts.windows(2).all(|w| w[0].end == w[1].start));
                assert!(cuts.iter().all(|r| !r.is_empty()), "{n} {count} {cuts:?}");
            }
        }
    }
}

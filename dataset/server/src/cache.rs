//! What the server keeps between requests, within one byte budget: decoded rows and rendered PNG previews.
//!
//! A tensor or preview request first needs its row decoded from Parquet (the zstd pages that hold it: the largest
//! cost of a mixed load when profiled), and a preview then a PNG encode. Both are kept, weighed by the bytes they
//! hold, and evicted by quick_cache's CLOCK-Pro policy once the budget is spent, so memory stays bounded whatever
//! the dataset's size. A cold entry costs exactly what an uncached request did. Two requests that miss the same
//! row at once both decode it (rows are not locked while read), and a row evicted while a response still holds it
//! lives until that response is sent: memory is the budget plus what requests in flight hold.

use std::sync::Arc;

use axum::body::Bytes;
use quick_cache::sync::Cache;
use quick_cache::Weighter;

use dataset::contract::schema::Sample;

use crate::preview::Preview;

/// The default budget of `serve --cache-mib`.
pub const DEFAULT_CACHE_MIB: u64 = 1024;

/// The share of the budget previews may hold (a preview is ~10–50 kB against a decoded row's ~220 kB).
const PREVIEW_SHARE: u64 = 8;

/// Bytes an entry costs besides its payload: the key, the `Arc` or `Bytes` header, the map slot.
const ENTRY_OVERHEAD: u64 = 128;

/// Heap bytes a decoded sample holds: its rasters and strings.
pub fn sample_bytes(s: &Sample) -> u64 {
    let floats = s.dem_m.len()
        + s.image.len()
        + s.sun_lit.len()
        + s.context.as_ref().map_or(0, |c| {
            c.heights_m.len() + c.highland.as_ref().map_or(0, Vec::len)
        });
    let strings = s.sample_id.len()
        + s.tile_id.len()
        + s.ortho_id.len()
        + s.acq_time.len()
        + s.provenance.len();
    (floats * 4 + s.valid.len() + strings + std::mem::size_of::<Sample>()) as u64
}

#[derive(Clone)]
struct RowWeight;

impl Weighter<usize, Arc<Sample>> for RowWeight {
    fn weight(&self, _: &usize, sample: &Arc<Sample>) -> u64 {
        sample_bytes(sample) + ENTRY_OVERHEAD
    }
}

#[derive(Clone)]
struct PreviewWeight;

impl Weighter<(usize, Preview), Bytes> for PreviewWeight {
    fn weight(&self, _: &(usize, Preview), png: &Bytes) -> u64 {
        png.len() as u64 + ENTRY_OVERHEAD
    }
}

/// Decoded rows by row index, and previews by (row index, which preview).
pub struct ServerCache {
    rows: Cache<usize, Arc<Sample>, RowWeight>,
    previews: Cache<(usize, Preview), Bytes, PreviewWeight>,
}

impl ServerCache {
    /// A cache holding at most `budget_bytes` (0: nothing is kept).
    pub fn new(budget_bytes: u64) -> Self {
        let preview_bytes = budget_bytes / PREVIEW_SHARE;
        let row_bytes = budget_bytes - preview_bytes;
        // quick_cache sizes its table from an item estimate; a generous one costs only a few bytes a slot.
        Self {
            rows: Cache::with_weighter(
                (row_bytes / 220_000).max(16) as usize,
                row_bytes,
                RowWeight,
            ),
            previews: Cache::with_weighter(
                (preview_bytes / 20_000).max(16) as usize,
                preview_bytes,
                PreviewWeight,
            ),
        }
    }

    pub fn row(&self, row: usize) -> Option<Arc<Sample>> {
        self.rows.get(&row)
    }

    pub fn keep_row(&self, row: usize, sample: Arc<Sample>) {
        self.rows.insert(row, sample);
    }

    pub fn preview(&self, row: usize, preview: Preview) -> Option<Bytes> {
        self.previews.get(&(row, preview))
    }

    pub fn keep_preview(&self, row: usize, preview: Preview, png: Bytes) {
        self.previews.insert((row, preview), png);
    }

    /// Bytes held now, rows and previews together (at most the budget).
    pub fn weight(&self) -> u64 {
        self.rows.weight() + self.previews.weight()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(i: usize) -> Arc<Sample> {
        Arc::new(dataset::testing::synthetic_sample(i))
    }

    #[test]
    fn rows_come_back_until_the_budget_evicts_them_and_the_weight_stays_within_it() {
        let one = sample_bytes(&sample(0)) + ENTRY_OVERHEAD;
        // Room for about ten rows (the rows' share is 7/8 of the budget).
        let budget = one * 10 * PREVIEW_SHARE / (PREVIEW_SHARE - 1) + 1;
        let cache = ServerCache::new(budget);
        cache.keep_row(3, sample(3));
        assert_eq!(
            cache.row(3).map(|s| s.sample_id.clone()),
            Some(sample(3).sample_id.clone())
        );
        assert!(cache.row(4).is_none());
        for i in 0..100 {
            cache.keep_row(i, sample(i));
            assert!(cache.weight() <= budget, "{} > {budget}", cache.weight());
        }
        let kept = (0..100).filter(|&i| cache.row(i).is_some()).count();
        assert!((5..=10).contains(&kept), "{kept} rows kept");
    }

    #[test]
    fn a_zero_budget_keeps_nothing() {
        let cache = ServerCache::new(0);
        cache.keep_row(1, sample(1));
        cache.keep_preview(1, Preview::Dem, Bytes::from_static(b"png"));
        assert!(cache.row(1).is_none() && cache.preview(1, Preview::Dem).is_none());
        assert_eq!(cache.weight(), 0);
    }

    #[test]
    fn a_sample_weighs_its_rasters() {
        let s = sample(0);
        let context = s.context.as_ref().map_or(0, |c| {
            c.heights_m.len() + c.highland.as_ref().map_or(0, Vec::len)
        });
        let rasters =
            (s.dem_m.len() + s.image.len() + s.sun_lit.len() + context) * 4 + s.valid.len();
        assert!(sample_bytes(&s) >= rasters as u64);
        assert!(sample_bytes(&s) < rasters as u64 + 4096);
    }
}

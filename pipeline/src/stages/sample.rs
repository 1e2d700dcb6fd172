//! Valid-position sampling: per ortho, count = ⌊coverage × eroded_area / crop_area⌋ crop centres drawn
//! **without replacement** from the eroded-valid positions, with a ChaCha stream keyed by (seed, ortho id) so that
//! adding or removing an ortho never changes another ortho's samples, and nothing depends on listing order.

use rand::seq::index;

use super::erode::Run;
use crate::rng::keyed_rng;

/// Number of crops to draw for an ortho: ⌊coverage × eroded_area / crop_area⌋.
pub fn crop_count(coverage: f64, eroded_area_m2: f64, crop_area_m2: f64) -> usize {
    (coverage * eroded_area_m2 / crop_area_m2).floor().max(0.0) as usize
}

/// Draw `count` distinct positions (col, row) from the run-encoded valid set, keyed by (seed, ortho id).
/// The result is in draw order; `count` larger than the set is capped at its size (every position once).
pub fn sample_positions(runs: &[Run], count: usize, seed: u64, ortho_id: &str) -> Vec<(u32, u32)> {
    // Prefix sums over run lengths map a flat index into (row, col) with one binary search.
    let mut ends = Vec::with_capacity(runs.len());
    let mut total = 0u64;
    for r in runs {
        total += r.len as u64;
        ends.push(total);
    }
    let count = count.min(total as usize);
    if count == 0 {
        return Vec::new();
    }
    let mut rng = keyed_rng(seed, &format!("sample/{ortho_id}"), 0);
    // `index::sample` draws distinct indices (Floyd's / rejection / shuffle by size): no duplicates by construction.
    index::sample(&mut rng, total as usize, count)
        .into_iter()
        .map(|flat| {
            let flat = flat as u64;
            let k = ends.partition_point(|&end| end <= flat);
            let run = runs[k];
            let before = if k == 0 { 0 } else { ends[k - 1] };
            (run.start + (flat - before) as u32, run.row)
        })
        .collect()
}

/// Stage: read the eroded runs, draw each ortho's crop centres, write (ortho_id, col, row) in draw order.
pub fn run(
    runs_path: &std::path::Path,
    coverage: f64,
    dem_gsd_m: f64,
    seed: u64,
    out: &std::path::Path,
) -> anyhow::Result<()> {
    use super::table::{read_table, strings, u32s, write_table, Col};
    let batches = read_table(runs_path)?;
    let (ids, rows, starts, lens) = (
        strings(&batches, "ortho_id")?,
        u32s(&batches, "row")?,
        u32s(&batches, "start_col")?,
        u32s(&batches, "len")?,
    );
    let crop_area_m2 = (dataset::contract::schema::CROP_PX as f64 * dem_gsd_m).powi(2);
    let (mut out_ids, mut out_cols, mut out_rows) = (Vec::new(), Vec::new(), Vec::new());
    let mut i = 0;
    while i < ids.len() {
        let id = ids[i].clone();
        let mut ortho_runs = Vec::new();
        while i < ids.len() && ids[i] == id {
            ortho_runs.push(Run {
                row: rows[i],
                start: starts[i],
                len: lens[i],
            });
            i += 1;
        }
        let area_m2 = super::erode::run_area_px(&ortho_runs) as f64 * dem_gsd_m * dem_gsd_m;
        for (col, row) in sample_positions(
            &ortho_runs,
            crop_count(coverage, area_m2, crop_area_m2),
            seed,
            &id,
        ) {
            out_ids.push(id.clone());
            out_cols.push(col);
            out_rows.push(row);
        }
    }
    write_table(
        out,
        vec![
            ("ortho_id", Col::Str(out_ids)),
            ("col", Col::U32(out_cols)),
            ("row", Col::U32(out_rows)),
        ],
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stages::erode::to_runs;
    use std::collections::BTreeSet;

    fn strip_mask(w: usize, h: usize, seed: usize) -> Vec<u8> {
        (0..w * h)
            .map(|i| (!(i % w + seed).is_multiple_of(11) && (i / w) % 7 != 3) as u8)
            .collect()
    }

    #[test]
    fn samples_are_distinct_valid_positions() {
        let (w, h) = (60, 40);
        let mask = strip_mask(w, h, 1);
        let runs = to_runs(&mask, w);
        let picks = sample_positions(&runs, 500, 7, "M1");
        assert_eq!(picks.len(), 500);
        let distinct: BTreeSet<_> = picks.iter().collect();
        assert_eq!(distinct.len(), 500, "drawn without replacement");
        assert!(
            picks
                .iter()
                .all(|&(c, r)| mask[r as usize * w + c as usize] == 1),
            "only valid positions"
        );
        // Asking for more than exists yields every position exactly once.
        let all = sample_positions(&runs, 1_000_000, 7, "M1");
        assert_eq!(all.len() as u64, crate::stages::erode::run_area_px(&runs));
        assert_eq!(all.iter().collect::<BTreeSet<_>>().len(), all.len());
    }

    #[test]
    fn counts_are_proportional_to_eroded_area() {
        let crop_area = 640.0 * 640.0;
        // Exact floor of coverage × area / crop area: doubling the area doubles the count.
        assert_eq!(crop_count(4.0, 10.0 * crop_area, crop_area), 40);
        assert_eq!(crop_count(4.0, 20.0 * crop_area, crop_area), 80);
        assert_eq!(crop_count(1.5, 3.0 * crop_area + 1.0, crop_area), 4);
        assert_eq!(crop_count(1.0, 0.0, crop_area), 0);
    }

    #[test]
    fn adding_an_ortho_leaves_the_others_unchanged() {
        let (w, h) = (50, 50);
        let orthos = [
            ("M1", strip_mask(w, h, 0)),
            ("M2", strip_mask(w, h, 3)),
            ("M3", strip_mask(w, h, 5)),
        ];
        let draw = |ids: &[usize]| -> Vec<Vec<(u32, u32)>> {
            ids.iter()
                .map(|&i| sample_positions(&to_runs(&orthos[i].1, w), 200, 42, orthos[i].0))
                .collect()
        };
        let before = draw(&[0, 2]);
        let after = draw(&[0, 1, 2]);
        assert_eq!(before[0], after[0]);
        assert_eq!(before[1], after[2]);
        // And a different seed moves them.
        assert_ne!(
            sample_positions(&to_runs(&orthos[0].1, w), 200, 43, "M1"),
            before[0]
        );
    }

    #[test]
    fn draws_cover_the_valid_set_uniformly() {
        // Chi-square over 4 equal quadrants of a fully valid 40 × 40 mask: 800 draws, 3 degrees of freedom.
        let (w, h) = (40, 40);
        let runs = to_runs(&vec![1u8; w * h], w);
        let picks = sample_positions(&runs, 800, 11, "M9");
        let mut counts = [0f64; 4];
        for (c, r) in picks {
            counts[(c as usize >= w / 2) as usize + 2 * (r as usize >= h / 2) as usize] += 1.0;
        }
        let chi2: f64 = counts
            .iter()
            .map(|&o| (o - 200.0) * (o - 200.0) / 200.0)
            .sum();
        // 99.9th percentile of chi-square with 3 dof is 16.27.
        assert!(chi2 < 16.27, "quadrant counts {counts:?}, chi² {chi2}");
    }
}

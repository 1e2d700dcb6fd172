//! Erosion of valid masks by the crop footprint: a position is usable as a crop only if every pixel of the
//! footprint is valid (ortho ∧ DEM ∧ finite). Outside the raster counts as invalid.
//!
//! The square structuring element is separable (min over a rectangle = min over rows of mins over columns), and
//! for a binary mask the 1-D min filter is O(1) per pixel with run lengths: a window of `k` pixels is all valid
//! iff the run of consecutive valid pixels ending at its last pixel is at least `k` long. This is the binary case of
//! the van Herk/Gil-Werman filter, with no k² loop. The result is stored as run-length rows.

/// Window of `k` pixels around position `i`: `[i − k/2, i + k − 1 − k/2]` (for even `k`, the centre is the pixel
/// just after the middle corner, as for a 128-pixel crop whose centre pixel is index 64).
#[inline]
pub fn window_offsets(k: usize) -> (usize, usize) {
    (k / 2, k - 1 - k / 2)
}

/// 1-D erosion of `line` by a window of `k` pixels (see [`window_offsets`]); writes into `out`.
fn erode_line(line: &[u8], k: usize, out: &mut [u8]) {
    let n = line.len();
    let (before, after) = window_offsets(k);
    let mut run = 0usize;
    // run length ending at j, evaluated lazily as j = i + after walks forward.
    let mut runs = vec![0usize; n];
    for (j, &v) in line.iter().enumerate() {
        run = if v != 0 { run + 1 } else { 0 };
        runs[j] = run;
    }
    for (i, o) in out.iter_mut().enumerate() {
        let last = i + after;
        *o = (i >= before && last < n && runs[last] >= k) as u8;
    }
}

/// Erode a row-major binary mask (non-zero = valid) by a `k × k` square; pixels outside the raster are invalid.
pub fn erode_square(mask: &[u8], width: usize, height: usize, k: usize) -> Vec<u8> {
    assert_eq!(mask.len(), width * height);
    assert!(k >= 1, "structuring element must be at least one pixel");
    let mut rows_done = vec![0u8; width * height];
    for (src, dst) in mask.chunks(width).zip(rows_done.chunks_mut(width)) {
        erode_line(src, k, dst);
    }
    let mut out = vec![0u8; width * height];
    let (mut column, mut eroded) = (vec![0u8; height], vec![0u8; height]);
    for col in 0..width {
        for (row, v) in column.iter_mut().enumerate() {
            *v = rows_done[row * width + col];
        }
        erode_line(&column, k, &mut eroded);
        for (row, &v) in eroded.iter().enumerate() {
            out[row * width + col] = v;
        }
    }
    out
}

/// A run of valid pixels in one row: columns `start..start + len`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Run {
    pub row: u32,
    pub start: u32,
    pub len: u32,
}

/// Run-length encoding of a mask, row-major order (compact: strips are long and convex-ish).
pub fn to_runs(mask: &[u8], width: usize) -> Vec<Run> {
    let mut runs = Vec::new();
    for (row, line) in mask.chunks(width).enumerate() {
        let mut col = 0;
        while col < width {
            if line[col] == 0 {
                col += 1;
                continue;
            }
            let start = col;
            while col < width && line[col] != 0 {
                col += 1;
            }
            runs.push(Run {
                row: row as u32,
                start: start as u32,
                len: (col - start) as u32,
            });
        }
    }
    runs
}

/// Number of pixels covered by runs.
pub fn run_area_px(runs: &[Run]) -> u64 {
    runs.iter().map(|r| r.len as u64).sum()
}

/// Stage: per ortho, the DEM-grid mask of usable cells (DEM finite ∧ every overlapping ortho pixel valid), eroded
/// by the crop + apron square (130 DEM cells), as run-length rows in DEM pixel coordinates.
///
/// Erosion runs on the DEM grid rather than at ortho resolution: a cell is valid only if *all* ortho pixels it
/// overlaps are, so this is exact for crops aligned to the DEM grid, and 6× fewer cells for 2 m orthos.
pub fn run(
    dem: &dataset::science::raster::Raster,
    orthos: &[super::ingest::OrthoRecord],
    out: &std::path::Path,
) -> anyhow::Result<()> {
    use super::table::{write_table, Col};
    use rayon::prelude::*;
    // Orthos in parallel (GDAL decode and the mask sweep were serial; at most one ortho per pool thread is in
    // memory), gathered in manifest order so the table's bytes don't depend on scheduling.
    let per_ortho: Vec<Vec<Run>> = orthos
        .par_iter()
        .map(|record| -> anyhow::Result<Vec<Run>> {
            let ortho = dataset::science::raster::read_raster(&record.image_path)?;
            let (c0, r0, w, h, mask) = dem_cell_validity(&ortho, dem);
            drop(ortho);
            let eroded = erode_square(&mask, w, h, dataset::contract::schema::DEM_PX);
            Ok(to_runs(&eroded, w)
                .into_iter()
                .map(|run| Run {
                    row: run.row + r0 as u32,
                    start: run.start + c0 as u32,
                    len: run.len,
                })
                .collect())
        })
        .collect::<anyhow::Result<_>>()?;
    let (mut ids, mut rows, mut starts, mut lens) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for (record, runs) in orthos.iter().zip(per_ortho) {
        for run in runs {
            ids.push(record.ortho_id.clone());
            rows.push(run.row);
            starts.push(run.start);
            lens.push(run.len);
        }
    }
    write_table(
        out,
        vec![
            ("ortho_id", Col::Str(ids)),
            ("row", Col::U32(rows)),
            ("start_col", Col::U32(starts)),
            ("len", Col::U32(lens)),
        ],
    )
}

/// The DEM window (c0, r0, width, height) under an ortho and its cell validity mask.
pub fn dem_cell_validity(
    ortho: &dataset::science::raster::Raster,
    dem: &dataset::science::raster::Raster,
) -> (usize, usize, usize, usize, Vec<u8>) {
    let (dt, ot) = (&dem.transform, &ortho.transform);
    let (oc0, or0) = dt.map_to_pixel(ot.origin_x, ot.origin_y);
    let (oc1, or1) = dt.map_to_pixel(
        ot.origin_x + ortho.width as f64 * ot.pixel_width,
        ot.origin_y + ortho.height as f64 * ot.pixel_height,
    );
    let c0 = (oc0 + 0.5).floor().max(0.0) as usize;
    let r0 = (or0 + 0.5).floor().max(0.0) as usize;
    let c1 = ((oc1 + 0.5).ceil().max(0.0) as usize).min(dem.width);
    let r1 = ((or1 + 0.5).ceil().max(0.0) as usize).min(dem.height);
    let (w, h) = (c1.saturating_sub(c0), r1.saturating_sub(r0));
    // Ortho pixel index range covered by DEM cell edges [e, e + 1) along each axis.
    let span = |edge0: f64, edge1: f64, len: usize| -> Option<(usize, usize)> {
        let (a, b) = (edge0.floor(), edge1.ceil());
        (a >= 0.0 && b <= len as f64).then_some((a as usize, b as usize))
    };
    let x_edge = |c: usize| dt.edge_in(ot, c as f64, 0.0).0;
    let y_edge = |r: usize| dt.edge_in(ot, 0.0, r as f64).1;
    let mut mask = vec![0u8; w * h];
    for j in 0..h {
        let Some((ry0, ry1)) = span(y_edge(r0 + j), y_edge(r0 + j + 1), ortho.height) else {
            continue;
        };
        for i in 0..w {
            if !dem.get(c0 + i, r0 + j).is_finite() {
                continue;
            }
            let Some((rx0, rx1)) = span(x_edge(c0 + i), x_edge(c0 + i + 1), ortho.width) else {
                continue;
            };
            let all = (ry0..ry1).all(|r| {
                ortho.data[r * ortho.width + rx0..r * ortho.width + rx1]
                    .iter()
                    .all(|v| v.is_finite())
            });
            mask[j * w + i] = all as u8;
        }
    }
    (c0, r0, w, h, mask)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Direct definition: every pixel of the k × k window inside the raster and valid.
    fn brute_force(mask: &[u8], width: usize, height: usize, k: usize) -> Vec<u8> {
        let (before, after) = window_offsets(k);
        let mut out = vec![0u8; width * height];
        for r in 0..height {
            for c in 0..width {
                let inside = c >= before && r >= before && c + after < width && r + after < height;
                out[r * width + c] = (inside
                    && (r - before..=r + after)
                        .all(|rr| (c - before..=c + after).all(|cc| mask[rr * width + cc] != 0)))
                    as u8;
            }
        }
        out
    }

    /// Random masks that are mostly valid with holes (single pixels and blobs) — the hard case for erosion.
    fn masks() -> impl Strategy<Value = (usize, usize, usize, Vec<u8>)> {
        (1usize..40, 1usize..40, 1usize..12).prop_flat_map(|(w, h, k)| {
            let holes = prop::collection::vec((0..w, 0..h, 0usize..4), 0..6);
            let noise = prop::collection::vec(prop::bool::weighted(0.03), w * h);
            (Just(w), Just(h), Just(k), holes, noise).prop_map(|(w, h, k, holes, noise)| {
                let mut mask: Vec<u8> = noise.iter().map(|&n| (!n) as u8).collect();
                for (hc, hr, radius) in holes {
                    for r in hr.saturating_sub(radius)..(hr + radius + 1).min(h) {
                        for c in hc.saturating_sub(radius)..(hc + radius + 1).min(w) {
                            mask[r * w + c] = 0;
                        }
                    }
                }
                (w, h, k, mask)
            })
        })
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(600))]
        #[test]
        fn erosion_matches_brute_force_on_random_masks((w, h, k, mask) in masks()) {
            prop_assert_eq!(erode_square(&mask, w, h, k), brute_force(&mask, w, h, k));
        }

        #[test]
        fn runs_encode_the_mask_exactly((w, h, _k, mask) in masks()) {
            let runs = to_runs(&mask, w);
            let mut decoded = vec![0u8; w * h];
            for r in &runs {
                for c in r.start..r.start + r.len {
                    decoded[r.row as usize * w + c as usize] = 1;
                }
            }
            let binary: Vec<u8> = mask.iter().map(|&v| (v != 0) as u8).collect();
            prop_assert_eq!(decoded, binary);
            prop_assert_eq!(run_area_px(&runs), mask.iter().filter(|&&v| v != 0).count() as u64);
        }
    }

    #[test]
    fn a_full_raster_shrinks_by_the_window_and_edges_are_invalid() {
        let (w, h, k) = (10, 7, 4);
        let eroded = erode_square(&vec![1; w * h], w, h, k);
        // Valid centres need 2 pixels before and 1 after inside: columns 2..=8, rows 2..=5.
        assert_eq!(run_area_px(&to_runs(&eroded, w)), 7 * 4);
        assert_eq!((eroded[2 * w + 2], eroded[2 * w + 8]), (1, 1));
        assert_eq!(
            (eroded[w + 2], eroded[2 * w + 9], eroded[6 * w + 4]),
            (0, 0, 0)
        );
    }
}

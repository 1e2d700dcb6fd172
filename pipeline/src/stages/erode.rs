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

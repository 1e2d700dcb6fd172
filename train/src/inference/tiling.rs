//! How a DEM is cut into overlapping crops and how their outputs are blended back: crop placement, the blend
//! taper (a partition of unity over every DEM pixel), and the reflect padding at the borders.

use dataset::contract::schema::CROP_PX;

/// Default overlap between neighbouring crops, pixels (a quarter crop).
pub const DEFAULT_OVERLAP: usize = 32;

/// Start offsets of crops of `crop` pixels along an axis of `len` pixels (`len ≥ crop`), stride `crop − overlap`,
/// the last one flush with the end so every pixel is covered.
pub fn crop_origins(len: usize, crop: usize, overlap: usize) -> Vec<usize> {
    assert!(len >= crop && overlap < crop);
    let stride = crop - overlap;
    let mut origins: Vec<usize> = (0..)
        .map(|k| k * stride)
        .take_while(|&o| o + crop < len)
        .collect();
    origins.push(len - crop);
    origins
}

/// Where crops start along a DEM axis of `dem_len` pixels, in DEM pixels (negative = in the reflect padding):
/// the axis is padded by `overlap` on both sides (so border pixels get full weight) and at least to one crop.
pub fn crop_starts(dem_len: usize, overlap: usize) -> Vec<isize> {
    let padded = (dem_len + 2 * overlap).max(CROP_PX);
    crop_origins(padded, CROP_PX, overlap)
        .into_iter()
        .map(|o| o as isize - overlap as isize)
        .collect()
}

/// Blend weight of pixel `i` of a crop of `n` along one axis. With d = distance to the nearest crop edge and
/// m = overlap / 4: 0 for d < m (U-Net outputs next to a crop edge see zero padding, not terrain), a sin² ramp over
/// the next overlap − 2m pixels, 1 inside. Two crops overlapping by `overlap` then sum to exactly 1 (sin² + cos²),
/// and no crop's edge pixels ever reach the output.
pub fn taper(i: usize, n: usize, overlap: usize) -> f64 {
    let d = i.min(n - 1 - i);
    let margin = overlap / 4;
    let ramp = overlap - 2 * margin;
    if d < margin {
        0.0
    } else if d >= overlap - margin {
        1.0
    } else {
        let u = (d - margin) as f64 + 0.5;
        (std::f64::consts::FRAC_PI_2 * u / ramp as f64)
            .sin()
            .powi(2)
    }
}

/// numpy-style 'reflect' index (edge not repeated): −1 → 1, n → n − 2.
pub(super) fn reflect(i: isize, n: usize) -> usize {
    let n = n as isize;
    if n == 1 {
        return 0;
    }
    let period = 2 * (n - 1);
    let m = i.rem_euclid(period);
    (if m < n { m } else { period - m }) as usize
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crops_cover_every_dem_pixel_and_regular_overlaps_sum_to_one() {
        for (dem_len, overlap) in [
            (1, 32),
            (128, 0),
            (128, 32),
            (129, 32),
            (300, 32),
            (1000, 0),
            (1000, 48),
        ] {
            let len = (dem_len + 2 * overlap).max(128);
            let origins = crop_origins(len, 128, overlap);
            assert_eq!(origins[0], 0);
            assert_eq!(*origins.last().unwrap() + 128, len);
            let mut covered = vec![0.0; len];
            for o in &origins {
                for i in 0..128 {
                    covered[o + i] += taper(i, 128, overlap);
                }
            }
            let dem = &covered[overlap..overlap + dem_len];
            assert!(dem.iter().all(|&w| w > 0.0), "{dem_len} {overlap}");
            for pair in origins.windows(2) {
                assert!(
                    pair[1] - pair[0] <= 128 - overlap,
                    "stride {dem_len} {overlap}"
                );
            }
        }
        // 416 = 128 + 3 strides of 96: every DEM pixel's weights sum to exactly one (sin² + cos²).
        let origins = crop_origins(416, 128, 32);
        let mut covered = vec![0.0; 416];
        for o in &origins {
            for i in 0..128 {
                covered[o + i] += taper(i, 128, 32);
            }
        }
        assert!(covered[32..384].iter().all(|w| (w - 1.0).abs() < 1e-12));
        assert_eq!(taper(0, 128, 0), 1.0);
        assert_eq!(
            (taper(0, 128, 32), taper(7, 128, 32), taper(120, 128, 32)),
            (0.0, 0.0, 0.0)
        );
        let first = (std::f64::consts::FRAC_PI_2 * 0.5 / 16.0).sin().powi(2);
        assert!((taper(8, 128, 32) - first).abs() < 1e-15);
        assert_eq!((taper(24, 128, 32), taper(64, 128, 32)), (1.0, 1.0));
    }

    #[test]
    fn reflect_matches_numpy() {
        // numpy.pad([0,1,2,3], 2, 'reflect') = [2,1,0,1,2,3,2,1]
        let got: Vec<usize> = (-2..6).map(|i| reflect(i, 4)).collect();
        assert_eq!(got, vec![2, 1, 0, 1, 2, 3, 2, 1]);
        assert_eq!(reflect(-3, 1), 0);
    }
}

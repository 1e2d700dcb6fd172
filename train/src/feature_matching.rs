//! Feature-matching consistency between a ground-truth image and a rendering (the paper's Table 1 idea): detect
//! FAST-9 corners, describe them with 256-bit BRIEF (imageproc), keep reciprocal nearest neighbours in Hamming
//! distance, and measure how far each matched pair lies apart. Images are co-registered, so a correct match is
//! at 0 px: the share of matches within 1 / 3 / 5 px says whether the rendering reproduces the features a
//! navigation matcher would lock on. The paper used a learned matcher, which is not available here.

use dataset::contract::rng::keyed_rng;
use image::GrayImage;
use imageproc::binary_descriptors::brief::{brief, BriefDescriptor, TestPair};
use imageproc::binary_descriptors::BinaryDescriptor;
use imageproc::corners::{corners_fast9, Corner};
use imageproc::point::Point;
use rand::Rng;

/// FAST intensity threshold on the 8-bit stretched image.
pub const FAST_THRESHOLD: u8 = 20;
/// Most keypoints kept per image (strongest corners after non-maximum suppression).
pub const MAX_KEYPOINTS: usize = 300;
/// BRIEF needs its 31×31 patch (+1 for the box average) inside the image.
const BRIEF_MARGIN: u32 = 17;
/// Matches farther apart than this in Hamming distance are not matches (of 256 bits).
pub const MAX_HAMMING: u32 = 64;
const BRIEF_BITS: usize = 256;

/// The BRIEF test pairs: fixed by a keyed ChaCha stream (imageproc would draw them from thread_rng), Gaussian
/// around the patch centre with σ = 6.6 px as in Calonder et al.
pub fn test_pairs() -> Vec<TestPair> {
    let mut rng = keyed_rng(0, "brief-test-pairs", 0);
    let mut draw = || loop {
        // Box–Muller from two uniforms; rand_distr's Normal would do the same with another dependency path.
        let (u1, u2): (f64, f64) = (rng.random_range(f64::EPSILON..1.0), rng.random::<f64>());
        let v = 16.0 + 6.6 * (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos();
        if (0.0..31.0).contains(&v) {
            return v as u32;
        }
    };
    (0..BRIEF_BITS)
        .map(|_| TestPair {
            p0: Point::new(draw(), draw()),
            p1: Point::new(draw(), draw()),
        })
        .collect()
}

/// An image as 8 bits with the stretch `lo..hi` (shared by the images compared); invalid or non-finite pixels
/// become 0.
pub fn to_gray(values: &[f64], valid: &[bool], edge: usize, lo: f64, hi: f64) -> GrayImage {
    let span = (hi - lo).max(1e-12);
    GrayImage::from_fn(edge as u32, edge as u32, |x, y| {
        let k = y as usize * edge + x as usize;
        let v = if valid[k] && values[k].is_finite() {
            (((values[k] - lo) / span).clamp(0.0, 1.0) * 255.0).round() as u8
        } else {
            0
        };
        image::Luma([v])
    })
}

fn describe(image: &GrayImage, valid: &[bool], pairs: &[TestPair]) -> Vec<BriefDescriptor> {
    let (w, h) = image.dimensions();
    // A patch touching masked pixels would describe the mask's edge, identical in every rendering: skip it.
    let patch_valid = |c: &Corner| {
        let m = BRIEF_MARGIN as usize;
        let (x, y) = (c.x as usize, c.y as usize);
        (y - m..=y + m).all(|r| (x - m..=x + m).all(|k| valid[r * w as usize + k]))
    };
    let corners: Vec<Corner> = corners_fast9(image, FAST_THRESHOLD)
        .into_iter()
        .filter(|c| {
            c.x >= BRIEF_MARGIN
                && c.y >= BRIEF_MARGIN
                && c.x + BRIEF_MARGIN < w
                && c.y + BRIEF_MARGIN < h
        })
        .filter(patch_valid)
        .collect();
    let mut corners = imageproc::suppress::local_maxima(&corners, 2);
    // Strongest first; ties by position so the kept set never depends on detector order.
    corners.sort_by(|a, b| {
        b.score
            .total_cmp(&a.score)
            .then((a.y, a.x).cmp(&(b.y, b.x)))
    });
    corners.truncate(MAX_KEYPOINTS);
    let points: Vec<Point<u32>> = corners.iter().map(|c| Point::new(c.x, c.y)).collect();
    let pairs = pairs.to_vec();
    brief(image, &points, BRIEF_BITS, Some(&pairs))
        .map(|(descriptors, _)| descriptors)
        .unwrap_or_default()
}

/// Pixel distances of reciprocal nearest-neighbour matches between two images' descriptors.
fn reciprocal_match_distances(a: &[BriefDescriptor], b: &[BriefDescriptor]) -> Vec<f64> {
    let nearest = |d: &BriefDescriptor, pool: &[BriefDescriptor]| {
        pool.iter()
            .enumerate()
            .map(|(j, e)| (d.hamming_distance(e), j))
            .min()
    };
    a.iter()
        .enumerate()
        .filter_map(|(i, d)| {
            let (hamming, j) = nearest(d, b)?;
            let (_, back) = nearest(&b[j], a)?;
            (back == i && hamming <= MAX_HAMMING).then(|| {
                let (p, q) = (d.position(), b[j].position());
                ((p.x as f64 - q.x as f64).powi(2) + (p.y as f64 - q.y as f64).powi(2)).sqrt()
            })
        })
        .collect()
}

/// Match statistics accumulated over images.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct MatchStats {
    pub images: usize,
    pub matches: usize,
    pub within_1px: usize,
    pub within_3px: usize,
    pub within_5px: usize,
    pub error_sum_px: f64,
}

impl MatchStats {
    pub fn add_distances(&mut self, distances: &[f64]) {
        self.images += 1;
        self.matches += distances.len();
        for &d in distances {
            self.within_1px += usize::from(d <= 1.0);
            self.within_3px += usize::from(d <= 3.0);
            self.within_5px += usize::from(d <= 5.0);
            self.error_sum_px += d;
        }
    }

    /// Shares within 1 / 3 / 5 px and the mean error, over all matches (zeros when there are none).
    pub fn summary(&self) -> MatchSummary {
        let share = |n: usize| n as f64 / self.matches.max(1) as f64;
        MatchSummary {
            matches_per_image: self.matches as f64 / self.images.max(1) as f64,
            within_1px: share(self.within_1px),
            within_3px: share(self.within_3px),
            within_5px: share(self.within_5px),
            mean_error_px: self.error_sum_px / self.matches.max(1) as f64,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct MatchSummary {
    pub matches_per_image: f64,
    pub within_1px: f64,
    pub within_3px: f64,
    pub within_5px: f64,
    pub mean_error_px: f64,
}

/// Detects and describes the ground truth once, then matches any number of renderings against it.
pub struct FeatureMatcher {
    pairs: Vec<TestPair>,
}

impl Default for FeatureMatcher {
    fn default() -> Self {
        Self {
            pairs: test_pairs(),
        }
    }
}

impl FeatureMatcher {
    /// Distances of reciprocal matches between `truth` and `rendered` (edge², row-major), both stretched with the
    /// truth's 2–98 % range over valid pixels.
    pub fn match_distances(
        &self,
        truth: &[f64],
        rendered: &[f64],
        valid: &[bool],
        edge: usize,
    ) -> Vec<f64> {
        let mut values: Vec<f64> = truth
            .iter()
            .zip(valid)
            .filter(|(t, &ok)| ok && t.is_finite())
            .map(|(&t, _)| t)
            .collect();
        if values.len() < 2 {
            return Vec::new();
        }
        values.sort_by(f64::total_cmp);
        let n = values.len();
        let (lo, hi) = (values[n * 2 / 100], values[(n - 1) * 98 / 100]);
        let a = describe(&to_gray(truth, valid, edge, lo, hi), valid, &self.pairs);
        let b = describe(&to_gray(rendered, valid, edge, lo, hi), valid, &self.pairs);
        reciprocal_match_distances(&a, &b)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A textured test image: overlapping bright discs on a gradient.
    fn texture(shift_x: f64) -> Vec<f64> {
        (0..128 * 128)
            .map(|k| {
                let (x, y) = ((k % 128) as f64 - shift_x, (k / 128) as f64);
                let mut v = 0.2 + 0.001 * x;
                for (cx, cy, r) in [
                    (30.0, 40.0, 6.0),
                    (70.0, 35.0, 4.0),
                    (95.0, 80.0, 7.0),
                    (50.0, 90.0, 5.0),
                    (80.0, 60.0, 3.0),
                ] {
                    if (x - cx).powi(2) + (y - cy).powi(2) < r * r {
                        v += 0.5;
                    }
                }
                v + 0.05 * ((x * 0.9).sin() * (y * 1.3).cos())
            })
            .collect()
    }

    #[test]
    fn identical_images_match_at_zero_pixels_and_shifted_ones_at_the_shift() {
        let matcher = FeatureMatcher::default();
        let valid = vec![true; 128 * 128];
        let truth = texture(0.0);
        let same = matcher.match_distances(&truth, &truth, &valid, 128);
        assert!(same.len() >= 5, "too few features: {}", same.len());
        assert!(same.iter().all(|&d| d == 0.0), "{same:?}");
        let shifted = matcher.match_distances(&truth, &texture(4.0), &valid, 128);
        assert!(!shifted.is_empty());
        let mut stats = MatchStats::default();
        stats.add_distances(&shifted);
        let s = stats.summary();
        assert!(s.within_3px < 0.5 && s.within_5px > 0.5, "{s:?}");
        assert!((s.mean_error_px - 4.0).abs() < 1.0, "{s:?}");
    }

    #[test]
    fn masked_edges_never_make_matches() {
        // A flat rendering against a flat truth, both with a masked rectangle: the only corners are on the mask's
        // edge, identical in both; they must not count as matches.
        let matcher = FeatureMatcher::default();
        let valid: Vec<bool> = (0..128 * 128)
            .map(|k| !((40..80).contains(&(k % 128)) && (40..80).contains(&(k / 128))))
            .collect();
        let flat: Vec<f64> = (0..128 * 128)
            .map(|k| 0.3 + 0.001 * (k % 128) as f64)
            .collect();
        assert!(matcher
            .match_distances(&flat, &flat, &valid, 128)
            .is_empty());
    }

    #[test]
    fn test_pairs_are_fixed_and_inside_the_patch() {
        let (a, b) = (test_pairs(), test_pairs());
        assert_eq!(a, b);
        assert_eq!(a.len(), 256);
        assert!(a
            .iter()
            .all(|p| p.p0.x < 31 && p.p0.y < 31 && p.p1.x < 31 && p.p1.y < 31));
    }
}

//! Image metrics over the valid pixels of one crop: per-image SSE (the paper's "MSE"), per-pixel MSE, PSNR and
//! SSIM with data_range = that image's ground-truth range (docs/design.md, Trainer and evaluation).
//!
//! SSIM follows scikit-image's `structural_similarity` defaults: 7×7 uniform window, K1 = 0.01, K2 = 0.03, sample
//! covariance (N/(N−1)), mean over windows that lie inside the image (its `crop(S, 3)`); here additionally only
//! windows whose 49 pixels are all valid count, so masked pixels never enter a statistic.

/// Metrics of one rendered image against its ground truth.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ImageMetrics {
    pub valid_pixels: usize,
    /// Sum of squared errors over valid pixels (the paper's per-image "MSE").
    pub sse: f64,
    pub mse: f64,
    pub psnr_db: f64,
    /// `None` when no 7×7 window is fully valid.
    pub ssim: Option<f64>,
}

/// Metrics of many images: per-image means, plus the pixel MSE pooled over all valid pixels (the training loss).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct AggregateMetrics {
    /// Images with at least one valid pixel.
    pub images: usize,
    pub pixel_mse_pooled: f64,
    /// Mean of per-image pixel MSE.
    pub pixel_mse: f64,
    /// Mean of per-image SSE (the paper's "MSE").
    pub sse: f64,
    /// Mean over images with a finite PSNR (a perfect or constant image has none).
    pub psnr_db: f64,
    /// Mean over images with at least one fully valid 7×7 window.
    pub ssim: Option<f64>,
}

#[derive(Debug, Clone, Default)]
pub struct MetricsAccumulator {
    images: usize,
    pixels: usize,
    sse_sum: f64,
    mse_sum: f64,
    psnr_sum: f64,
    psnr_images: usize,
    ssim_sum: f64,
    ssim_images: usize,
}

impl MetricsAccumulator {
    /// Add one image (`edge²`, row-major); images without a valid pixel are skipped.
    pub fn add(&mut self, rendered: &[f64], truth: &[f64], valid: &[bool], edge: usize) {
        if let Some(m) = image_metrics(rendered, truth, valid, edge) {
            self.add_metrics(&m);
        }
    }

    /// Add one image's metrics, computed already (by [`image_metrics`]).
    pub fn add_metrics(&mut self, m: &ImageMetrics) {
        self.images += 1;
        self.pixels += m.valid_pixels;
        self.sse_sum += m.sse;
        self.mse_sum += m.mse;
        if m.psnr_db.is_finite() {
            self.psnr_sum += m.psnr_db;
            self.psnr_images += 1;
        }
        if let Some(s) = m.ssim {
            self.ssim_sum += s;
            self.ssim_images += 1;
        }
    }

    pub fn finish(&self) -> AggregateMetrics {
        let per_image = |sum: f64, n: usize| sum / n.max(1) as f64;
        AggregateMetrics {
            images: self.images,
            pixel_mse_pooled: per_image(self.sse_sum, self.pixels),
            pixel_mse: per_image(self.mse_sum, self.images),
            sse: per_image(self.sse_sum, self.images),
            psnr_db: per_image(self.psnr_sum, self.psnr_images),
            ssim: (self.ssim_images > 0).then(|| self.ssim_sum / self.ssim_images as f64),
        }
    }
}

pub const SSIM_WINDOW: usize = 7;
const K1: f64 = 0.01;
const K2: f64 = 0.03;

/// Metrics of `rendered` vs `truth` (both `edge²`, row-major) over pixels where `valid` is non-zero.
/// Returns `None` when no pixel is valid.
pub fn image_metrics(
    rendered: &[f64],
    truth: &[f64],
    valid: &[bool],
    edge: usize,
) -> Option<ImageMetrics> {
    assert!(
        rendered.len() == edge * edge && truth.len() == edge * edge && valid.len() == edge * edge
    );
    let pixels: Vec<usize> = (0..edge * edge).filter(|&k| valid[k]).collect();
    if pixels.is_empty() {
        return None;
    }
    let sse: f64 = pixels
        .iter()
        .map(|&k| (rendered[k] - truth[k]).powi(2))
        .sum();
    let mse = sse / pixels.len() as f64;
    let (lo, hi) = pixels
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &k| {
            (lo.min(truth[k]), hi.max(truth[k]))
        });
    let range = hi - lo;
    let psnr_db = if mse > 0.0 && range > 0.0 {
        10.0 * (range * range / mse).log10()
    } else {
        f64::INFINITY
    };
    Some(ImageMetrics {
        valid_pixels: pixels.len(),
        sse,
        mse,
        psnr_db,
        ssim: ssim(rendered, truth, valid, edge, range),
    })
}

/// Mean SSIM over fully valid 7×7 windows (scikit-image's formula with `data_range`).
pub fn ssim(x: &[f64], y: &[f64], valid: &[bool], edge: usize, data_range: f64) -> Option<f64> {
    let half = SSIM_WINDOW / 2;
    let n = (SSIM_WINDOW * SSIM_WINDOW) as f64;
    let cov_norm = n / (n - 1.0);
    let (c1, c2) = ((K1 * data_range).powi(2), (K2 * data_range).powi(2));
    let (mut total, mut count) = (0.0, 0usize);
    for r in half..edge.saturating_sub(half) {
        'window: for c in half..edge.saturating_sub(half) {
            let (mut sx, mut sy, mut sxx, mut syy, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
            for wr in r - half..=r + half {
                for wc in c - half..=c + half {
                    let k = wr * edge + wc;
                    if !valid[k] {
                        continue 'window;
                    }
                    let (a, b) = (x[k], y[k]);
                    sx += a;
                    sy += b;
                    sxx += a * a;
                    syy += b * b;
                    sxy += a * b;
                }
            }
            let (ux, uy) = (sx / n, sy / n);
            let vx = cov_norm * (sxx / n - ux * ux);
            let vy = cov_norm * (syy / n - uy * uy);
            let vxy = cov_norm * (sxy / n - ux * uy);
            total += ((2.0 * ux * uy + c1) * (2.0 * vxy + c2))
                / ((ux * ux + uy * uy + c1) * (vx + vy + c2));
            count += 1;
        }
    }
    (count > 0).then(|| total / count as f64)
}

/// An SSIM for tables: three decimals, or why there is none.
pub fn ssim_text(ssim: Option<f64>) -> String {
    ssim.map_or("n/a (no fully valid 7x7 window)".into(), |s| {
        format!("{s:.3}")
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identical_images_are_perfect_and_mse_psnr_match_hand_values() {
        let edge = 8;
        let truth: Vec<f64> = (0..64).map(|k| (k % 8) as f64 * 0.1).collect();
        let valid = vec![true; 64];
        let m = image_metrics(&truth, &truth, &valid, edge).unwrap();
        assert_eq!((m.sse, m.mse), (0.0, 0.0));
        assert!((m.ssim.unwrap() - 1.0).abs() < 1e-12);
        // Constant offset 0.05 on a 0..0.7 range: MSE 0.0025, PSNR = 10 log10(0.49 / 0.0025) = 22.92 dB.
        let shifted: Vec<f64> = truth.iter().map(|v| v + 0.05).collect();
        let m = image_metrics(&shifted, &truth, &valid, edge).unwrap();
        assert!((m.mse - 0.0025).abs() < 1e-12 && (m.sse - 0.16).abs() < 1e-12);
        assert!((m.psnr_db - 10.0 * (0.49f64 / 0.0025).log10()).abs() < 1e-9);
        assert!(image_metrics(&truth, &truth, &[false; 64], edge).is_none());
    }

    #[test]
    fn ssim_of_one_window_matches_the_formula_by_hand() {
        // A 7×7 image has exactly one window: x = ramp, y = 2x. ux = 3, uy = 6; vx = var·49/48, vxy = 2 vx, vy = 4 vx.
        let x: Vec<f64> = (0..49).map(|k| (k % 7) as f64).collect();
        let y: Vec<f64> = x.iter().map(|v| 2.0 * v).collect();
        let var = 4.0 * 49.0 / 48.0; // population variance of 0..6 is 4
        let (c1, c2) = ((0.01f64 * 12.0).powi(2), (0.03f64 * 12.0).powi(2));
        let expected = ((2.0 * 3.0 * 6.0 + c1) * (2.0 * 2.0 * var + c2))
            / ((9.0 + 36.0 + c1) * (var + 4.0 * var + c2));
        let got = ssim(&x, &y, &[true; 49], 7, 12.0).unwrap();
        assert!((got - expected).abs() < 1e-12, "{got} vs {expected}");
    }

    #[test]
    fn ssim_matches_scikit_image_on_fixed_arrays() {
        // Reference numbers from scikit-image 0.26.0 (computed once, not at test time):
        //   k = np.arange(400); x = (np.sin(0.37*k)*0.5 + (k%7)*0.01).reshape(20, 20)
        //   y = x + (0.1*np.cos(1.3*k)).reshape(20, 20); z = (0.3*np.cos(0.11*k) + 0.02*(k%5)).reshape(20, 20)
        //   structural_similarity(x, y, win_size=7, data_range=y.max()-y.min())  -> 0.9798124882640532
        //   structural_similarity(z, y, win_size=7, data_range=y.max()-y.min())  -> 0.02854049131098254
        let k = (0..400).map(|k| k as f64);
        let x: Vec<f64> = k
            .clone()
            .map(|k| (0.37 * k).sin() * 0.5 + (k % 7.0) * 0.01)
            .collect();
        let y: Vec<f64> = x
            .iter()
            .zip(k.clone())
            .map(|(x, k)| x + 0.1 * (1.3 * k).cos())
            .collect();
        let z: Vec<f64> = k
            .map(|k| 0.3 * (0.11 * k).cos() + 0.02 * (k % 5.0))
            .collect();
        let range = y.iter().cloned().fold(f64::NEG_INFINITY, f64::max)
            - y.iter().cloned().fold(f64::INFINITY, f64::min);
        let valid = [true; 400];
        let close = ssim(&x, &y, &valid, 20, range).unwrap();
        let far = ssim(&z, &y, &valid, 20, range).unwrap();
        assert!((close - 0.9798124882640532).abs() < 1e-12, "{close}");
        assert!((far - 0.02854049131098254).abs() < 1e-12, "{far}");
        // image_metrics uses the ground truth's own range.
        let m = image_metrics(&x, &y, &valid, 20).unwrap();
        assert_eq!(m.ssim, Some(close));
    }
}

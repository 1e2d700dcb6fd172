//! Stateless, seeded 2-D gradient noise and fractional Brownian motion (fBm): any cell can be evaluated
//! independently, so rasters fill in parallel and the result does not depend on the thread count.

/// Hermite smoothstep from `e0` (0) to `e1` (1); e0 > e1 gives a falling step.
pub fn smoothstep(e0: f64, e1: f64, x: f64) -> f64 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// 2-D gradient (Perlin-type) noise on a unit lattice, keyed by `key`; output roughly in [-1, 1].
#[inline]
pub fn gradient_noise(x: f64, y: f64, key: u64) -> f64 {
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = (x - x0, y - y0);
    let (ix, iy) = (x0 as i64, y0 as i64);
    let grad = |cx: i64, cy: i64, dx: f64, dy: f64| {
        // One of 16 evenly spaced unit gradients: no trig per lattice corner (it dominated world generation).
        let (gx, gy) = GRADIENTS[(hash3(cx as u64, cy as u64, key) >> 60) as usize];
        gx * dx + gy * dy
    };
    let fade = |t: f64| t * t * t * (t * (t * 6.0 - 15.0) + 10.0);
    let (u, v) = (fade(fx), fade(fy));
    let n00 = grad(ix, iy, fx, fy);
    let n10 = grad(ix + 1, iy, fx - 1.0, fy);
    let n01 = grad(ix, iy + 1, fx, fy - 1.0);
    let n11 = grad(ix + 1, iy + 1, fx - 1.0, fy - 1.0);
    let a = n00 + u * (n10 - n00);
    let b = n01 + u * (n11 - n01);
    (a + v * (b - a)) * std::f64::consts::SQRT_2
}

const GRADIENTS: [(f64, f64); 16] = {
    // cos/sin of k·22.5°, k = 0..15.
    const C: [f64; 5] = [
        1.0,
        0.923_879_532_511_286_7,
        std::f64::consts::FRAC_1_SQRT_2,
        0.382_683_432_365_089_8,
        0.0,
    ];
    let mut g = [(0.0, 0.0); 16];
    let mut k = 0;
    while k < 16 {
        let (q, r) = (k / 4, k % 4);
        let (c, s) = (C[r], C[4 - r]);
        g[k] = match q {
            0 => (c, s),
            1 => (-s, c),
            2 => (-c, -s),
            _ => (s, -c),
        };
        k += 1;
    }
    g
};

#[inline]
fn hash3(a: u64, b: u64, key: u64) -> u64 {
    // The splitmix64 finaliser over a combination of the lattice coordinates and the key.
    crate::rng::mix64(
        a.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ b.wrapping_mul(0xC2B2_AE3D_27D4_EB4F) ^ key,
    )
}

/// fBm parameters: octaves from `largest_wavelength_m` down to `smallest_wavelength_m`, amplitude ∝ λ^H.
#[derive(Debug, Clone, Copy)]
pub struct Fbm {
    pub key: u64,
    pub hurst: f64,
    /// Amplitude of the largest octave, metres (or whatever unit the caller wants).
    pub amplitude: f64,
    pub largest_wavelength_m: f64,
    pub smallest_wavelength_m: f64,
}

impl Fbm {
    /// Value at map point (x, y) in metres.
    pub fn at(&self, x: f64, y: f64) -> f64 {
        let mut wavelength = self.largest_wavelength_m;
        let mut amplitude = self.amplitude;
        let mut sum = 0.0;
        let mut octave = 0u64;
        let damping = 0.5f64.powf(self.hurst);
        while wavelength >= self.smallest_wavelength_m {
            // Each octave gets its own lattice key and a rotation so lattice axes don't line up across octaves.
            let (s, c) = (0.5 + octave as f64 * 1.3f64).sin_cos();
            let (u, v) = ((c * x - s * y) / wavelength, (s * x + c * y) / wavelength);
            sum += amplitude
                * gradient_noise(
                    u,
                    v,
                    self.key
                        .wrapping_add(octave.wrapping_mul(0x2545_F491_4F6C_DD1D)),
                );
            wavelength *= 0.5;
            amplitude *= damping;
            octave += 1;
        }
        sum
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn noise_is_continuous_and_bounded() {
        let mut max: f64 = 0.0;
        for i in 0..2000 {
            let (x, y) = (i as f64 * 0.137, i as f64 * 0.071);
            let v = gradient_noise(x, y, 42);
            max = max.max(v.abs());
            assert!((gradient_noise(x + 1e-7, y, 42) - v).abs() < 1e-5);
        }
        assert!(max <= 1.5 && max > 0.3, "{max}");
    }

    #[test]
    fn fbm_roughness_scales_with_hurst() {
        // Height differences over lag L grow like L^H: compare variograms at two lags.
        let fbm = Fbm {
            key: 3,
            hurst: 0.9,
            amplitude: 10.0,
            largest_wavelength_m: 4096.0,
            smallest_wavelength_m: 2.0,
        };
        let vario = |lag: f64| {
            let n = 4000;
            (0..n)
                .map(|i| {
                    let (x, y) = ((i * 37 % 4001) as f64 * 3.1, (i * 91 % 3989) as f64 * 2.7);
                    (fbm.at(x + lag, y) - fbm.at(x, y)).powi(2)
                })
                .sum::<f64>()
                / n as f64
        };
        let slope = (vario(64.0) / vario(16.0)).ln() / 4f64.ln() / 2.0;
        assert!(
            (slope - 0.9).abs() < 0.2,
            "variogram Hurst estimate {slope}"
        );
    }
}

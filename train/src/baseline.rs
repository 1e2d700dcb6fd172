//! The uniform-Hapke baseline the learned BRDF is compared with: one Moon-wide Hapke parameter set
//! ([`HapkeParams::lunar_typical`]) rendered with each sample's own geometry and lit fraction, then normalised per
//! image as the reference paper did — an affine map giving the rendering the ground truth's mean and range over
//! valid pixels. That normalisation **peeks at the ground truth**: it is the paper's baseline, not a fair one.

use dataset::contract::schema::Sample;
use dataset::science::geometry::{Cosines, PixelGeometry};
use dataset::science::hapke::{hapke_i_over_f, HFunction, HapkeParams};

/// I/F of the sample under uniform Hapke: lit fraction × Hapke (which carries the cos i factor itself).
pub fn hapke_render(sample: &Sample, params: &HapkeParams) -> Vec<f64> {
    hapke_from_geometry(&sample.pixel_geometry(), &sample.sun_lit, params)
}

/// [`hapke_render`] on precomputed geometry.
pub fn hapke_from_geometry(
    geometry: &[PixelGeometry],
    sun_lit: &[f32],
    params: &HapkeParams,
) -> Vec<f64> {
    lit_render(geometry, sun_lit, |c| {
        hapke_i_over_f(params, c.cos_i, c.cos_e, c.cos_g, HFunction::Hapke2002)
    })
}

/// I/F of a uniform reflectance model on precomputed geometry: lit fraction × `i_over_f(cosines)` per pixel.
pub fn lit_render(
    geometry: &[PixelGeometry],
    sun_lit: &[f32],
    i_over_f: impl Fn(&Cosines) -> f64,
) -> Vec<f64> {
    geometry
        .iter()
        .zip(sun_lit)
        .map(|(g, &lit)| lit as f64 * i_over_f(&g.cosines))
        .collect()
}

/// A sample's ground truth as f64 and its valid mask as bools (what every metric takes).
pub fn truth_and_valid(s: &Sample) -> (Vec<f64>, Vec<bool>) {
    (
        s.image.iter().map(|&v| v as f64).collect(),
        s.valid.iter().map(|&v| v != 0).collect(),
    )
}

/// The paper's per-image normalisation: `(x − mean_x) · range_t / range_x + mean_t` over valid pixels.
/// A constant rendering (range 0) is shifted to the truth's mean.
pub fn normalise_like_paper(rendered: &[f64], truth: &[f64], valid: &[bool]) -> Vec<f64> {
    let stats = |v: &[f64]| {
        let (mut sum, mut lo, mut hi, mut n) = (0.0, f64::INFINITY, f64::NEG_INFINITY, 0usize);
        for (&x, _) in v.iter().zip(valid).filter(|(_, &ok)| ok) {
            sum += x;
            lo = lo.min(x);
            hi = hi.max(x);
            n += 1;
        }
        (sum / n.max(1) as f64, hi - lo)
    };
    let ((mean_x, range_x), (mean_t, range_t)) = (stats(rendered), stats(truth));
    let scale = if range_x > 0.0 {
        range_t / range_x
    } else {
        0.0
    };
    rendered
        .iter()
        .map(|&x| (x - mean_x) * scale + mean_t)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_normalisation_matches_truth_mean_and_range_on_valid_pixels() {
        let rendered = [1.0, 2.0, 3.0, 100.0];
        let truth = [0.1, 0.3, 0.2, 0.0];
        let valid = [true, true, true, false];
        let out = normalise_like_paper(&rendered, &truth, &valid);
        // mean_x 2, range_x 2 → scale 0.1; mean_t 0.2: 1 → 0.1, 2 → 0.2, 3 → 0.3.
        for (got, want) in out.iter().zip([0.1, 0.2, 0.3]) {
            assert!((got - want).abs() < 1e-15, "{out:?}");
        }
    }

    #[test]
    fn uniform_hapke_of_a_sample_is_finite_and_zero_where_unlit() {
        let mut sample = crate::testing::synthetic_samples(1, 3).remove(0);
        sample.sun_lit[5] = 0.0;
        let r = hapke_render(&sample, &HapkeParams::lunar_typical());
        assert!(r.iter().all(|v| v.is_finite() && *v >= 0.0));
        assert_eq!(r[5], 0.0);
        assert!(
            r.iter().any(|&v| v > 0.01),
            "a 60° sun lights most of the crop"
        );
    }
}

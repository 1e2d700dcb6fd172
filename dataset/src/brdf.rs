//! The learnable cosine-polynomial BRDF family M1–M6 (scalar f64 reference).
//!
//! Convention (the reference renderer's): `f` returns the reflected fraction *including* the cos i factor, and the
//! image is `I = E · V_sun · f(p; geometry)`. Raw per-pixel parameters pass through LeakyReLU(0.01) inside `f`.
//! Terms are ordered (cos i, cos g, …) — the GeoTIFF band descriptions name them in this order.
//! A surface facing away from the sun (cos i ≤ 0) or from the camera (cos e ≤ 0) reflects nothing toward it: f = 0.

use crate::geometry::{Cosines, HalfDiffCosines, PixelGeometry};

/// Negative slope of the LeakyReLU applied to every raw parameter.
pub const LEAKY_SLOPE: f64 = 0.01;

#[inline]
pub fn leaky_relu(x: f64) -> f64 {
    if x >= 0.0 {
        x
    } else {
        LEAKY_SLOPE * x
    }
}

/// The raw parameter whose LeakyReLU is `activated` (parameter maps store activated values).
#[inline]
pub fn inverse_leaky_relu(activated: f64) -> f64 {
    if activated >= 0.0 {
        activated
    } else {
        activated / LEAKY_SLOPE
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BrdfModel {
    M1,
    M2,
    M3,
    M4,
    M5,
    M6,
}

impl BrdfModel {
    pub const ALL: [BrdfModel; 6] = [Self::M1, Self::M2, Self::M3, Self::M4, Self::M5, Self::M6];

    pub fn param_count(self) -> usize {
        self.term_names().len()
    }

    /// Name of the geometric term each parameter multiplies, in parameter order ("1" = constant).
    pub fn term_names(self) -> &'static [&'static str] {
        match self {
            Self::M1 => &["cos_i", "cos_g"],
            Self::M2 => &["cos_i", "cos_g", "1"],
            Self::M3 => &["cos_i", "cos_g", "cos_i*cos_g", "1"],
            Self::M4 => &["cos_i", "cos_g", "cos_i^2", "1"],
            Self::M5 => &["cos_i", "cos_g", "cos_g^2", "1"],
            Self::M6 => &["cos_theta_h", "cos_theta_d", "cos_phi_h", "cos_phi_d"],
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::M1 => "m1",
            Self::M2 => "m2",
            Self::M3 => "m3",
            Self::M4 => "m4",
            Self::M5 => "m5",
            Self::M6 => "m6",
        }
    }

    /// The geometric terms (the basis functions) for this geometry, in parameter order.
    pub fn terms(self, c: &Cosines, hd: &HalfDiffCosines) -> [f64; 4] {
        match self {
            Self::M1 => [c.cos_i, c.cos_g, 0.0, 0.0],
            Self::M2 => [c.cos_i, c.cos_g, 1.0, 0.0],
            Self::M3 => [c.cos_i, c.cos_g, c.cos_i * c.cos_g, 1.0],
            Self::M4 => [c.cos_i, c.cos_g, c.cos_i * c.cos_i, 1.0],
            Self::M5 => [c.cos_i, c.cos_g, c.cos_g * c.cos_g, 1.0],
            Self::M6 => [hd.cos_theta_h, hd.cos_theta_d, hd.cos_phi_h, hd.cos_phi_d],
        }
    }

    /// Reflected fraction f(p; geometry). `raw_params` has [`Self::param_count`] entries (before LeakyReLU).
    pub fn evaluate(self, raw_params: &[f64], c: &Cosines, hd: &HalfDiffCosines) -> f64 {
        debug_assert_eq!(raw_params.len(), self.param_count());
        if c.cos_i <= 0.0 || c.cos_e <= 0.0 {
            return 0.0;
        }
        let terms = self.terms(c, hd);
        raw_params
            .iter()
            .zip(terms)
            .map(|(&p, t)| leaky_relu(p) * t)
            .sum()
    }
}

impl std::str::FromStr for BrdfModel {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::ALL
            .into_iter()
            .find(|m| m.name().eq_ignore_ascii_case(s))
            .ok_or_else(|| format!("unknown BRDF model '{s}': use one of m1, m2, m3, m4, m5, m6"))
    }
}

/// Rendered pixel value `I = E · V_sun · f`.
pub fn render_pixel(
    model: BrdfModel,
    raw_params: &[f64],
    c: &Cosines,
    hd: &HalfDiffCosines,
    irradiance: f64,
    lit_fraction: f64,
) -> f64 {
    irradiance * lit_fraction * model.evaluate(raw_params, c, hd)
}

/// Render a whole crop: `planar_params[k * n + p]` is raw parameter k of pixel p (the network's channel-first
/// output), `geometry` and `lit_fraction` have one entry per pixel. The scalar reference of `train`'s renderer layer.
pub fn render_crop(
    model: BrdfModel,
    planar_params: &[f64],
    geometry: &[PixelGeometry],
    lit_fraction: &[f64],
    irradiance: f64,
) -> Vec<f64> {
    let n = geometry.len();
    assert_eq!(planar_params.len(), model.param_count() * n);
    assert_eq!(lit_fraction.len(), n);
    let mut raw = vec![0.0; model.param_count()];
    (0..n)
        .map(|p| {
            for (k, r) in raw.iter_mut().enumerate() {
                *r = planar_params[k * n + p];
            }
            let g = &geometry[p];
            render_pixel(
                model,
                &raw,
                &g.cosines,
                &g.half_diff,
                irradiance,
                lit_fraction[p],
            )
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inverse_leaky_relu_undoes_the_activation_on_both_branches() {
        // Exact on the identity branch; within the rounding of ×0.01 then ÷0.01 on the negative one.
        for raw in [-3.5, -1e-9, 0.0, 2e-7, 0.04] {
            let back = inverse_leaky_relu(leaky_relu(raw));
            assert!(
                (back - raw).abs() <= 2.0 * f64::EPSILON * raw.abs(),
                "{raw} -> {back}"
            );
        }
        assert_eq!(inverse_leaky_relu(0.04), 0.04);
    }
    use glam::DVec3;

    #[test]
    fn m2_matches_hand_value() {
        let (n, s, v) = (DVec3::Z, DVec3::new(0.6, 0.0, 0.8), DVec3::Z);
        let c = Cosines::new(n, s, v);
        let hd = HalfDiffCosines::new(n, s, v);
        // a·0.8 + b·0.8 + c with (a, b, c) = (0.5, -2 → -0.02, 0.1)
        let f = BrdfModel::M2.evaluate(&[0.5, -2.0, 0.1], &c, &hd);
        assert!((f - (0.5 * 0.8 - 0.02 * 0.8 + 0.1)).abs() < 1e-15);
    }

    #[test]
    fn backfacing_reflects_nothing() {
        let (n, s, v) = (DVec3::Z, DVec3::new(1.0, 0.0, -0.1).normalize(), DVec3::Z);
        let c = Cosines::new(n, s, v);
        let hd = HalfDiffCosines::new(n, s, v);
        for m in BrdfModel::ALL {
            assert_eq!(m.evaluate(&vec![1.0; m.param_count()], &c, &hd), 0.0);
        }
    }

    #[test]
    fn m6_at_nadir_is_finite_and_by_continuity() {
        let n = DVec3::Z;
        let c = Cosines::new(n, n, n);
        let hd = HalfDiffCosines::new(n, n, n);
        let f = BrdfModel::M6.evaluate(&[1.0, 1.0, 1.0, 1.0], &c, &hd);
        assert_eq!(f, 4.0);
    }

    use proptest::prelude::*;

    /// Unit vectors including the degenerate alignments: zenith, horizon, exact opposites, tiny offsets.
    fn hard_unit() -> impl Strategy<Value = DVec3> {
        prop_oneof![
            Just(DVec3::Z),
            Just(DVec3::X),
            Just(-DVec3::Z),
            Just(DVec3::new(1e-9, 0.0, 1.0).normalize()),
            Just(DVec3::new(1.0, 0.0, 1e-12).normalize()),
            (-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0).prop_filter_map("non-zero", |(x, y, z)| {
                let v = DVec3::new(x, y, z);
                (v.length() > 1e-3).then(|| v.normalize())
            }),
        ]
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(3000))]
        #[test]
        fn every_model_is_finite_on_hard_geometries(n in hard_unit(), s in hard_unit(), v in hard_unit(), p in prop::collection::vec(-10.0f64..10.0, 4)) {
            let c = Cosines::new(n, s, v);
            let hd = HalfDiffCosines::new(n, s, v);
            for cos in [hd.cos_theta_h, hd.cos_theta_d, hd.cos_phi_h, hd.cos_phi_d] {
                prop_assert!(cos.is_finite() && (-1.0..=1.0).contains(&cos), "{hd:?}");
            }
            for m in BrdfModel::ALL {
                let f = m.evaluate(&p[..m.param_count()], &c, &hd);
                prop_assert!(f.is_finite(), "{m:?} gives {f} at n={n:?} s={s:?} v={v:?}");
            }
        }
    }

    #[test]
    fn parse_model_names() {
        assert_eq!("M3".parse::<BrdfModel>().unwrap(), BrdfModel::M3);
        assert!("m7".parse::<BrdfModel>().unwrap_err().contains("m1"));
    }
}

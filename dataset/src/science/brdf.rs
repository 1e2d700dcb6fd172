//! The learnable BRDF families (scalar f64 reference): the paper's cosine polynomials M1–M6, and a
//! Lommel–Seeliger family L2–L4 that goes past the paper.
//!
//! Why L2–L4: M1–M6 are linear in cos i and cos g, but a regolith's single scattering goes as the Lommel–Seeliger
//! ratio LS = μ0/(μ0+μ) times a phase function (Hapke; Lunar-Lambert mixes LS with Lambert's μ0). No per-pixel map
//! of an M model can supply that 1/(μ0+μ) dependence on the *view*, because the maps cannot depend on the
//! geometry of one acquisition. L models keep the same shape as M (per-pixel coefficients of fixed terms, linear in
//! the parameters, so the same renderer layer and the same costs) with terms LS, LS·cos g, LS·cos² g and μ0.
//! And H1: one per-pixel scale on the Moon-wide Hapke shape ([`hapke_shape`]); its uniform fit is the honest
//! scaled-Hapke baseline, so its maps say exactly what the DEM adds to Hapke.
//!
//! Why H3: one scale cannot follow a material whose phase function or albedo differs from the Moon-wide one. Its
//! ratio to the Moon-wide I/F then changes with the acquisition's geometry (fresh crater material, w ≈ 0.6 and
//! b = 0.2: by a factor 1.4 between phase angles of 5° and 100° in a sketch without roughness), and a map that cannot see the geometry must
//! average it. H3 keeps Hapke's structure and its linearity in the parameters: single scattering under a
//! back-scattering and a less back-scattering double-HG lobe ([`H3_LOBES_B`]; any asymmetry between them is nearly
//! a positive mix of the two), and multiple scattering, each with the Moon-wide opposition surge, roughness and
//! Lommel–Seeliger ratio ([`hapke_decomposed`]).
//!
//! Convention (the reference renderer's): `f` returns the reflected fraction *including* the cos i factor, and the
//! image is `I = E · V_sun · f(p; geometry)`. Raw per-pixel parameters pass through LeakyReLU(0.01) inside `f`.
//! Terms are in [`BrdfModel::term_names`] order — the GeoTIFF band descriptions name them in this order.
//! A surface facing away from the sun (cos i ≤ 0) or from the camera (cos e ≤ 0) reflects nothing toward it: f = 0.

use glam::DVec3;

use crate::science::geometry::{Cosines, HalfDiffCosines, PixelGeometry};
use crate::science::hapke::{double_hg, hapke_i_over_f, hapke_parts, HFunction, HapkeParams};
use crate::science::least_squares::solve_small_system;

/// Negative slope of the LeakyReLU applied to every raw parameter.
pub const LEAKY_SLOPE: f64 = 0.01;

/// The metadata item of a parameter GeoTIFF naming its BRDF model (`BrdfModel::name`): `infer` writes it, `render`
/// reads it back.
pub const BRDF_MODEL_KEY: &str = "G2R_BRDF_MODEL";

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
    L2,
    L3,
    L4,
    H1,
    H3,
}

/// The Moon-wide Hapke I/F ([`HapkeParams::lunar_typical`], 2002 H-function): H1's one term. Depends only on the
/// three cosines, so the Burn layer can evaluate it elementwise with this very function.
#[inline]
pub fn hapke_shape(cos_i: f64, cos_e: f64, cos_g: f64) -> f64 {
    hapke_i_over_f(
        &HapkeParams::lunar_typical(),
        cos_i,
        cos_e,
        cos_g,
        HFunction::Hapke2002,
    )
}

/// Double-HG asymmetries b of H3's two single-scattering lobes, around the Moon-wide 0.25: the lunar range of
/// fitted b lies between them, and a mix of the two follows a lobe anywhere between to about 1 % (tested).
pub const H3_LOBES_B: [f64; 2] = [0.35, 0.15];

/// H3's terms: Moon-wide Hapke ([`HapkeParams::lunar_typical`]) split into single scattering under each of
/// [`H3_LOBES_B`] and multiple scattering ([`hapke_parts`]). Like [`hapke_shape`], a function of the cosines only.
#[inline]
pub fn hapke_decomposed(cos_i: f64, cos_e: f64, cos_g: f64) -> [f64; 3] {
    let p = HapkeParams::lunar_typical();
    let parts = hapke_parts(&p, cos_i, cos_e, cos_g, HFunction::Hapke2002);
    [
        parts.single_per_phase * double_hg(cos_g, H3_LOBES_B[0], p.c),
        parts.single_per_phase * double_hg(cos_g, H3_LOBES_B[1], p.c),
        parts.multiple,
    ]
}

/// Below this μ0 + μ the Lommel–Seeliger ratio's denominator is held (both grazing: the ratio is bounded by 1
/// anyway, and the floor keeps f32 and backward free of 0/0). The Burn layer uses the same floor.
pub const LS_DENOMINATOR_FLOOR: f64 = 1e-6;

/// Lommel–Seeliger ratio μ0/(μ0+μ) for a surface facing both sun and camera.
#[inline]
pub fn lommel_seeliger(cos_i: f64, cos_e: f64) -> f64 {
    cos_i.max(0.0) / (cos_i.max(0.0) + cos_e.max(0.0)).max(LS_DENOMINATOR_FLOOR)
}

impl BrdfModel {
    pub const ALL: [BrdfModel; 11] = [
        Self::M1,
        Self::M2,
        Self::M3,
        Self::M4,
        Self::M5,
        Self::M6,
        Self::L2,
        Self::L3,
        Self::L4,
        Self::H1,
        Self::H3,
    ];

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
            Self::L2 => &["ls", "cos_i"],
            Self::L3 => &["ls", "ls*cos_g", "cos_i"],
            Self::L4 => &["ls", "ls*cos_g", "ls*cos_g^2", "cos_i"],
            Self::H1 => &["hapke_moonwide"],
            Self::H3 => &["hapke_single_b0.35", "hapke_single_b0.15", "hapke_multiple"],
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
            Self::L2 => "l2",
            Self::L3 => "l3",
            Self::L4 => "l4",
            Self::H1 => "h1",
            Self::H3 => "h3",
        }
    }

    /// Whether [`Self::terms`] reads the half-angle cosines (M6 only), so callers may skip building them.
    pub fn uses_half_diff(self) -> bool {
        self == Self::M6
    }

    /// The terms where the surface faces both the sun and the camera; `None` where it faces away from either,
    /// where every model renders 0. The one place that rule lives (the scalar reference and the renderer layer).
    pub fn visible_terms(self, c: &Cosines, hd: &HalfDiffCosines) -> Option<[f64; 4]> {
        if c.cos_i <= 0.0 || c.cos_e <= 0.0 {
            return None;
        }
        Some(self.terms(c, hd))
    }

    /// [`Self::visible_terms`] of a pixel with unit `normal`, lit from `sun_dir` and seen along `view_dir`. The
    /// half/difference angles are computed only for the model that uses them (M6); the others get NaN there, so
    /// a model that read them would fail loudly.
    pub fn pixel_terms(self, normal: DVec3, sun_dir: DVec3, view_dir: DVec3) -> Option<[f64; 4]> {
        let c = Cosines::new(normal, sun_dir, view_dir);
        let hd = if self.uses_half_diff() {
            HalfDiffCosines::new(normal, sun_dir, view_dir)
        } else {
            HalfDiffCosines {
                cos_theta_h: f64::NAN,
                cos_theta_d: f64::NAN,
                cos_phi_h: f64::NAN,
                cos_phi_d: f64::NAN,
            }
        };
        self.visible_terms(&c, &hd)
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
            Self::H1 => [hapke_shape(c.cos_i, c.cos_e, c.cos_g), 0.0, 0.0, 0.0],
            Self::H3 => {
                let [single_back, single_less, multiple] =
                    hapke_decomposed(c.cos_i, c.cos_e, c.cos_g);
                [single_back, single_less, multiple, 0.0]
            }
            Self::L2 | Self::L3 | Self::L4 => {
                let ls = lommel_seeliger(c.cos_i, c.cos_e);
                match self {
                    Self::L2 => [ls, c.cos_i, 0.0, 0.0],
                    Self::L3 => [ls, ls * c.cos_g, c.cos_i, 0.0],
                    _ => [ls, ls * c.cos_g, ls * c.cos_g * c.cos_g, c.cos_i],
                }
            }
        }
    }

    /// Reflected fraction f(p; geometry). `raw_params` has [`Self::param_count`] entries (before LeakyReLU).
    pub fn evaluate(self, raw_params: &[f64], c: &Cosines, hd: &HalfDiffCosines) -> f64 {
        debug_assert_eq!(raw_params.len(), self.param_count());
        let Some(terms) = self.visible_terms(c, hd) else {
            return 0.0;
        };
        raw_params
            .iter()
            .zip(terms)
            .map(|(&p, t)| leaky_relu(p) * t)
            .sum()
    }
}

/// The geometries of lunar orbital images on a flat surface: incidence 20–80° (5° steps), emission 0–30°, the
/// camera's azimuth from the sun's 0–180° (30° steps). What a map that cannot see the geometry has to serve.
pub fn orbital_geometries() -> Vec<Cosines> {
    let mut out = Vec::new();
    for i_deg in (20..=80).step_by(5) {
        for e_deg in [0, 5, 10, 20, 30] {
            for az_deg in (0..=180).step_by(30) {
                let (i, e, az) = (
                    f64::from(i_deg).to_radians(),
                    f64::from(e_deg).to_radians(),
                    f64::from(az_deg).to_radians(),
                );
                out.push(Cosines {
                    cos_i: i.cos(),
                    cos_e: e.cos(),
                    cos_g: i.cos() * e.cos() + i.sin() * e.sin() * az.cos(),
                });
            }
        }
    }
    out
}

/// The best geometry-blind coefficients of `model` (activated values, one per term) for a material whose I/F is
/// `target` at each of `geometries`: least squares over them. Also returns the fit's RMS residual relative to the
/// target's RMS, the error that model's form leaves for that material whatever its maps hold. Not for M6, whose
/// half-angle terms these cosines do not carry.
pub fn best_coefficients(
    model: BrdfModel,
    geometries: &[Cosines],
    target: impl Fn(&Cosines) -> f64,
) -> (Vec<f64>, f64) {
    assert!(
        !model.uses_half_diff(),
        "best_coefficients: {} needs half-angle cosines",
        model.name()
    );
    let p = model.param_count();
    let no_half = HalfDiffCosines {
        cos_theta_h: f64::NAN,
        cos_theta_d: f64::NAN,
        cos_phi_h: f64::NAN,
        cos_phi_d: f64::NAN,
    };
    let rows: Vec<([f64; 4], f64)> = geometries
        .iter()
        .map(|c| (model.terms(c, &no_half), target(c)))
        .collect();
    let (mut ata, mut atb) = (vec![vec![0.0; p]; p], vec![0.0; p]);
    for (terms, t) in &rows {
        for i in 0..p {
            atb[i] += terms[i] * t;
            for j in 0..p {
                ata[i][j] += terms[i] * terms[j];
            }
        }
    }
    let x = solve_small_system(ata, atb);
    let (mut residual, mut norm) = (0.0, 0.0);
    for (terms, t) in &rows {
        let fit: f64 = terms.iter().zip(&x).map(|(a, b)| a * b).sum();
        residual += (fit - t).powi(2);
        norm += t * t;
    }
    let relative = if norm > 0.0 {
        (residual / norm).sqrt()
    } else {
        0.0
    };
    (x, relative)
}

impl std::str::FromStr for BrdfModel {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::ALL
            .into_iter()
            .find(|m| m.name().eq_ignore_ascii_case(s))
            .ok_or_else(|| {
                format!(
                    "unknown BRDF model '{s}': use one of {}",
                    Self::ALL.map(|m| m.name()).join(", ")
                )
            })
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
    fn lommel_seeliger_terms_match_hand_values() {
        // Sun 60° off the normal, camera at nadir: μ0 = 0.5, μ = 1, cos g = 0.5, LS = 1/3.
        let (n, s, v) = (DVec3::Z, DVec3::new(3f64.sqrt() / 2.0, 0.0, 0.5), DVec3::Z);
        let (c, hd) = (Cosines::new(n, s, v), HalfDiffCosines::new(n, s, v));
        let ls = 1.0 / 3.0;
        let t = BrdfModel::L4.terms(&c, &hd);
        for (got, want) in t.iter().zip([ls, ls * 0.5, ls * 0.25, 0.5]) {
            assert!((got - want).abs() < 1e-15, "{t:?}");
        }
        // L3 with (a, b, c) = (0.3, 0.2, 0.05): 0.3·LS + 0.2·LS·cos g + 0.05·μ0.
        let f = BrdfModel::L3.evaluate(&[0.3, 0.2, 0.05], &c, &hd);
        assert!((f - (0.3 * ls + 0.2 * ls * 0.5 + 0.05 * 0.5)).abs() < 1e-15);
    }

    #[test]
    fn lommel_seeliger_ratio_is_bounded_when_both_grazing() {
        // μ0 = μ = 1e-9: the true ratio is ½; below the floor the ratio shrinks toward 0 but never exceeds 1
        // or divides by zero.
        for (mu0, mu) in [
            (1e-9, 1e-9),
            (0.0, 0.0),
            (1e-300, 0.0),
            (1.0, 0.0),
            (0.3, 0.7),
        ] {
            let ls = lommel_seeliger(mu0, mu);
            assert!(
                ls.is_finite() && (0.0..=1.0).contains(&ls),
                "{mu0} {mu} → {ls}"
            );
        }
        assert!((lommel_seeliger(0.3, 0.7) - 0.3).abs() < 1e-15);
        assert_eq!(lommel_seeliger(1.0, 0.0), 1.0);
    }

    #[test]
    fn h1_is_a_scale_on_the_moonwide_hapke_i_over_f() {
        let p = HapkeParams::lunar_typical();
        for (n, s, v) in [
            (DVec3::Z, DVec3::new(0.6, 0.0, 0.8), DVec3::Z),
            (
                DVec3::new(0.1, -0.2, 1.0).normalize(),
                DVec3::new(-0.7, 0.3, 0.4).normalize(),
                DVec3::new(0.2, 0.1, 1.0).normalize(),
            ),
        ] {
            let (c, hd) = (Cosines::new(n, s, v), HalfDiffCosines::new(n, s, v));
            let hapke = hapke_i_over_f(&p, c.cos_i, c.cos_e, c.cos_g, HFunction::Hapke2002);
            assert!(hapke > 0.0);
            assert_eq!(BrdfModel::H1.evaluate(&[1.0], &c, &hd), hapke);
            assert!((BrdfModel::H1.evaluate(&[1.7], &c, &hd) - 1.7 * hapke).abs() < 1e-15);
        }
    }

    /// Why H3 exists: over the geometries of lunar orbital images (incidence 20–80°, emission 0–30°, every
    /// azimuth), the best single H1 scale misses a fresh, bright, less back-scattering material by several per cent
    /// (the ratio to the Moon-wide I/F moves with phase angle), while H3's best coefficients follow it, and follow
    /// any asymmetry between its two lobes to about 1 %. Materials like the Moon-wide one H1 already fits.
    #[test]
    fn h3_follows_materials_whose_phase_function_a_single_scale_cannot() {
        let geometries = orbital_geometries();
        let material = |w: f64, b: f64| {
            let p = HapkeParams {
                w,
                b,
                ..HapkeParams::lunar_typical()
            };
            move |c: &Cosines| hapke_i_over_f(&p, c.cos_i, c.cos_e, c.cos_g, HFunction::Hapke2002)
        };
        let error = |model, w, b| best_coefficients(model, &geometries, material(w, b)).1;
        // Fresh crater material of the synthetic worlds: w = 0.36 × 1.6, b = 0.25 − 0.05.
        let (h1_fresh, h3_fresh) = (
            error(BrdfModel::H1, 0.576, 0.2),
            error(BrdfModel::H3, 0.576, 0.2),
        );
        assert!(h1_fresh > 0.05, "H1 on fresh material: {h1_fresh}");
        assert!(h3_fresh < 0.01, "H3 on fresh material: {h3_fresh}");
        for (w, b) in [
            (0.24, 0.25),
            (0.36, 0.25),
            (0.5, 0.15),
            (0.3, 0.35),
            (0.7, 0.2),
        ] {
            let err = error(BrdfModel::H3, w, b);
            assert!(err < 0.012, "H3 on w = {w}, b = {b}: {err}");
        }
        // Where the material is the Moon-wide one up to its albedo, a single scale suffices.
        assert!(error(BrdfModel::H1, 0.32, 0.25) < 1e-12);
        assert!(error(BrdfModel::H1, 0.24, 0.25) < 0.015);
        // The fit itself: the Moon-wide material is H1 with coefficient 1.
        let (moonwide, _) = best_coefficients(BrdfModel::H1, &geometries, material(0.32, 0.25));
        assert!((moonwide[0] - 1.0).abs() < 1e-12, "{moonwide:?}");
    }

    #[test]
    fn parse_model_names() {
        assert_eq!("M3".parse::<BrdfModel>().unwrap(), BrdfModel::M3);
        assert!("m7".parse::<BrdfModel>().unwrap_err().contains("m1"));
        for m in BrdfModel::ALL {
            assert_eq!(m.name().parse::<BrdfModel>().unwrap(), m);
            assert_eq!(m.param_count(), m.term_names().len());
        }
    }
}

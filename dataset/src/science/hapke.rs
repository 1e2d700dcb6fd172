//! Hapke (2012 IMSA form) and Lunar-Lambert photometry, scalar f64 reference with every hazard guarded.
//!
//! Conventions:
//! - `hapke_reflectance` returns the bidirectional reflectance r (sr⁻¹); I/F = π·r ([`hapke_i_over_f`]).
//!   Like the M1–M6 models, it includes the cos i factor (through μ0e).
//! - Double Henyey–Greenstein: p(g) = (1+c)/2·HG(b, g) + (1−c)/2·HG(−b, g) with HG(b, g) = (1−b²)/(1−2b·cos g+b²)^{3/2},
//!   so c > 0 means back-scattering (the lunar case, c ≈ 0.3–0.9). Some codes use c' = (1+c)/2 instead.
//! - Porosity K = 1 unless set.
//!
//! Guards: inputs are cosines (clamped to [−1, 1]); i or e ≥ 90° → 0; cot at i or e = 0 is capped rather than
//! divided by sin = 0; θ̄ → 0 returns the smooth model; ψ is 0 when sin i·sin e = 0; tan(ψ/2) and tan(g/2) are never
//! formed (half-angle forms that stay finite at π); w is clamped to [0, 1]; |b| ≤ 1 − 1e-6.

use std::f64::consts::PI;

use crate::science::geometry::clamp_unit;

/// Which approximation of Chandrasekhar's H-function to use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum HFunction {
    /// H(x) = (1+2x)/(1+2γx), γ = √(1−w). Within ~4 % of the exact function.
    Hapke1981,
    /// H(x) ≈ [1 − w·x·(r0 + (1−2·r0·x)/2 · ln((1+x)/x))]⁻¹. Within ~1 %.
    Hapke2002,
}

/// Hapke parameters for one surface element.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct HapkeParams {
    /// Single-scattering albedo.
    pub w: f64,
    /// Double-HG asymmetry |b| < 1.
    pub b: f64,
    /// Double-HG back/forward partition (c > 0: back-scattering).
    pub c: f64,
    /// Shadow-hiding opposition amplitude B_S0.
    pub b_s0: f64,
    /// Shadow-hiding opposition width h_S.
    pub h_s: f64,
    /// Mean slope angle θ̄ of macroscopic roughness, radians.
    pub theta_bar_rad: f64,
    /// Porosity factor K (1 = ignore porosity).
    pub porosity_k: f64,
}

impl HapkeParams {
    /// Representative lunar highland/mare soil: each parameter inside the usual lunar range (w 0.2–0.5, b 0.2–0.3,
    /// c 0.3–0.9, B_S0 1.5–3, h_S 0.05–0.1); θ̄ from a Moon-wide fit.
    pub fn lunar_typical() -> Self {
        Self {
            w: 0.32,
            b: 0.25,
            c: 0.6,
            b_s0: 2.0,
            h_s: 0.07,
            theta_bar_rad: 23.657f64.to_radians(),
            porosity_k: 1.0,
        }
    }
}

const MAX_B: f64 = 1.0 - 1e-6;
const MIN_SIN: f64 = 1e-12;

/// Chandrasekhar H-function approximation for single-scattering albedo `w`.
pub fn h_function(x: f64, w: f64, form: HFunction) -> f64 {
    let w = w.clamp(0.0, 1.0);
    let x = x.max(0.0);
    let gamma = (1.0 - w).sqrt();
    match form {
        HFunction::Hapke1981 => (1.0 + 2.0 * x) / (1.0 + 2.0 * gamma * x),
        HFunction::Hapke2002 => {
            if x < 1e-12 {
                return 1.0; // H(0) = 1; x·ln(1/x) → 0
            }
            let r0 = (1.0 - gamma) / (1.0 + gamma);
            let bracket = 1.0 - w * x * (r0 + (1.0 - 2.0 * r0 * x) / 2.0 * ((1.0 + x) / x).ln());
            // For w ≤ 1 and x ≤ 1 the bracket stays ≥ 0.34; the floor only protects extrapolated x.
            1.0 / bracket.max(1e-6)
        }
    }
}

/// Double Henyey–Greenstein phase function at cos g.
pub fn double_hg(cos_g: f64, b: f64, c: f64) -> f64 {
    let b = b.clamp(-MAX_B, MAX_B);
    let cos_g = clamp_unit(cos_g);
    let one_minus_b2 = 1.0 - b * b;
    let back = one_minus_b2 / (1.0 - 2.0 * b * cos_g + b * b).max(1e-300).powf(1.5);
    let fwd = one_minus_b2 / (1.0 + 2.0 * b * cos_g + b * b).max(1e-300).powf(1.5);
    (1.0 + c) / 2.0 * back + (1.0 - c) / 2.0 * fwd
}

/// Shadow-hiding opposition B_S(g) = 1/(1 + tan(g/2)/h_S), in the half-angle form that is finite at g = π.
pub fn shoe(cos_g: f64, h_s: f64) -> f64 {
    let cos_g = clamp_unit(cos_g);
    let cos_half = ((1.0 + cos_g) / 2.0).sqrt();
    let sin_half = ((1.0 - cos_g) / 2.0).sqrt();
    let h_s = h_s.max(1e-12);
    h_s * cos_half / (h_s * cos_half + sin_half)
}

/// Effective cosines and shadowing of Hapke's macroscopic roughness correction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Roughness {
    pub mu0_eff: f64,
    pub mu_eff: f64,
    pub shadowing: f64,
}

/// Hapke (1984) macroscopic roughness: effective μ0e, μe and shadowing S(i, e, ψ), both branches (i ≤ e, i ≥ e).
///
/// Inputs are cos i, cos e, cos g; ψ (the azimuth between the incidence and emission planes) follows from
/// cos g = cos i cos e + sin i sin e cos ψ and is taken as 0 where sin i · sin e = 0 (ψ is undefined there, and
/// every term it multiplies vanishes).
pub fn roughness(cos_i: f64, cos_e: f64, cos_g: f64, theta_bar_rad: f64) -> Roughness {
    // Roughness is defined for i, e in [0°, 90°]; callers return 0 outside (backfacing).
    let (mu0, mu) = (cos_i.clamp(0.0, 1.0), cos_e.clamp(0.0, 1.0));
    // Physical mean slopes are < 45°; beyond 80° tan θ̄ explodes and the model has no meaning.
    let theta_bar_rad = if theta_bar_rad.is_finite() {
        theta_bar_rad.clamp(0.0, 80f64.to_radians())
    } else {
        0.0
    };
    if theta_bar_rad < 1e-6 {
        return Roughness {
            mu0_eff: mu0,
            mu_eff: mu,
            shadowing: 1.0,
        };
    }
    if mu0 == 0.0 || mu == 0.0 {
        // Exactly grazing: r = 0 whatever S is, and S itself is a 0/0 here; report no light rather than a NaN.
        return Roughness {
            mu0_eff: 0.0,
            mu_eff: 0.0,
            shadowing: 0.0,
        };
    }
    let sin_i = (1.0 - mu0 * mu0).max(0.0).sqrt();
    let sin_e = (1.0 - mu * mu).max(0.0).sqrt();
    let cos_psi = if sin_i * sin_e > MIN_SIN {
        clamp_unit((clamp_unit(cos_g) - mu0 * mu) / (sin_i * sin_e))
    } else {
        1.0
    };
    let psi = cos_psi.acos();
    let sin2_half_psi = (1.0 - cos_psi) / 2.0;
    // f(ψ) = exp(−2 tan(ψ/2)), with tan(ψ/2) = sin(ψ/2)/cos(ψ/2): the exponent → −∞ at ψ = π, f → 0.
    let cos_half_psi = ((1.0 + cos_psi) / 2.0).sqrt();
    let f_psi = if cos_half_psi < 1e-150 {
        0.0
    } else {
        (-2.0 * sin2_half_psi.sqrt() / cos_half_psi).exp()
    };

    let tan_tb = theta_bar_rad.tan();
    let cot_tb = 1.0 / tan_tb;
    let chi = 1.0 / (1.0 + PI * tan_tb * tan_tb).sqrt();
    // cot of i or e, capped at i, e → 0 instead of dividing by sin = 0 (E1, E2 → 0 either way).
    let cot = |cos_x: f64, sin_x: f64| (cos_x / sin_x.max(MIN_SIN)).min(1e12);
    let e1 = |cot_x: f64| (-2.0 / PI * cot_tb * cot_x).exp();
    let e2 = |cot_x: f64| (-1.0 / PI * cot_tb * cot_tb * cot_x * cot_x).exp();
    let (cot_i, cot_e) = (cot(mu0, sin_i), cot(mu, sin_e));
    let (e1_i, e2_i, e1_e, e2_e) = (e1(cot_i), e2(cot_i), e1(cot_e), e2(cot_e));
    let eta = |cos_x: f64, sin_x: f64, e1_x: f64, e2_x: f64| {
        chi * (cos_x + sin_x * tan_tb * e2_x / (2.0 - e1_x))
    };
    let eta0 = eta(mu0, sin_i, e1_i, e2_i);
    let eta_e = eta(mu, sin_e, e1_e, e2_e);

    let (mu0_eff, mu_eff, denominator_ratio) = if sin_i <= sin_e {
        // i ≤ e
        // Zero only when both are grazing and ψ = π, where every numerator vanishes too.
        let denom = (2.0 - e1_e - psi / PI * e1_i).max(MIN_SIN);
        let mu0_eff =
            chi * (mu0 + sin_i * tan_tb * (cos_psi * e2_e + sin2_half_psi * e2_i) / denom);
        let mu_eff = chi * (mu + sin_e * tan_tb * (e2_e - sin2_half_psi * e2_i) / denom);
        (mu0_eff, mu_eff, mu0 / eta0)
    } else {
        // i ≥ e
        let denom = (2.0 - e1_i - psi / PI * e1_e).max(MIN_SIN);
        let mu0_eff = chi * (mu0 + sin_i * tan_tb * (e2_i - sin2_half_psi * e2_e) / denom);
        let mu_eff = chi * (mu + sin_e * tan_tb * (cos_psi * e2_i + sin2_half_psi * e2_e) / denom);
        (mu0_eff, mu_eff, mu / eta_e)
    };
    // η ≥ χ·tan θ̄·E2/(2−E1) > 0 at grazing, and ≥ χ·cos x elsewhere: never zero for θ̄ > 0.
    let shadowing = (mu_eff / eta_e) * (mu0 / eta0) * chi
        / (1.0 - f_psi + f_psi * chi * denominator_ratio).max(f64::MIN_POSITIVE);
    Roughness {
        mu0_eff,
        mu_eff,
        shadowing,
    }
}

/// Hapke bidirectional reflectance r (sr⁻¹) from cos i, cos e, cos g.
pub fn hapke_reflectance(
    p: &HapkeParams,
    cos_i: f64,
    cos_e: f64,
    cos_g: f64,
    form: HFunction,
) -> f64 {
    let (mu0, mu) = (clamp_unit(cos_i), clamp_unit(cos_e));
    if mu0 <= 0.0 || mu <= 0.0 {
        return 0.0;
    }
    let w = p.w.clamp(0.0, 1.0);
    let k = p.porosity_k.max(1e-6);
    let rough = roughness(mu0, mu, cos_g, p.theta_bar_rad);
    let (mu0e, mue) = (rough.mu0_eff.max(0.0), rough.mu_eff.max(0.0));
    if mu0e + mue <= 0.0 {
        return 0.0;
    }
    let phase = double_hg(cos_g, p.b, p.c) * (1.0 + p.b_s0 * shoe(cos_g, p.h_s));
    let multiple = h_function(mu0e / k, w, form) * h_function(mue / k, w, form) - 1.0;
    let r = k * w / (4.0 * PI) * mu0e / (mu0e + mue) * (phase + multiple) * rough.shadowing;
    r.max(0.0)
}

/// Hapke's I/F split by scattering order: `single_per_phase · p(g)` is the single-scattering part for a phase
/// function p (opposition surge, roughness and the Lommel–Seeliger ratio included), `multiple` the
/// multiple-scattering part, so `hapke_i_over_f = single_per_phase · double_hg(cos g, b, c) + multiple` (tested).
/// The pieces of the H3 model ([`crate::science::brdf`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HapkeParts {
    pub single_per_phase: f64,
    pub multiple: f64,
}

pub fn hapke_parts(
    p: &HapkeParams,
    cos_i: f64,
    cos_e: f64,
    cos_g: f64,
    form: HFunction,
) -> HapkeParts {
    let none = HapkeParts {
        single_per_phase: 0.0,
        multiple: 0.0,
    };
    let (mu0, mu) = (clamp_unit(cos_i), clamp_unit(cos_e));
    if mu0 <= 0.0 || mu <= 0.0 {
        return none;
    }
    let w = p.w.clamp(0.0, 1.0);
    let k = p.porosity_k.max(1e-6);
    let rough = roughness(mu0, mu, cos_g, p.theta_bar_rad);
    let (mu0e, mue) = (rough.mu0_eff.max(0.0), rough.mu_eff.max(0.0));
    if mu0e + mue <= 0.0 {
        return none;
    }
    // π · r without the bracket: I/F = common · (p(g)·(1 + B_S) + M).
    let common = PI * k * w / (4.0 * PI) * mu0e / (mu0e + mue) * rough.shadowing;
    HapkeParts {
        single_per_phase: common * (1.0 + p.b_s0 * shoe(cos_g, p.h_s)),
        multiple: common * (h_function(mu0e / k, w, form) * h_function(mue / k, w, form) - 1.0),
    }
}

/// Hapke radiance factor I/F = π·r.
pub fn hapke_i_over_f(p: &HapkeParams, cos_i: f64, cos_e: f64, cos_g: f64, form: HFunction) -> f64 {
    PI * hapke_reflectance(p, cos_i, cos_e, cos_g, form)
}

/// McEwen's lunar limb-darkening weight L(g), g in degrees.
pub fn lunar_lambert_l(g_deg: f64) -> f64 {
    1.0 - 0.019 * g_deg + 2.42e-4 * g_deg * g_deg - 1.46e-6 * g_deg * g_deg * g_deg
}

/// Lunar-Lambert I/F = A·[2L(g)·μ0/(μ0+μ) + (1−L(g))·μ0].
pub fn lunar_lambert_i_over_f(albedo: f64, cos_i: f64, cos_e: f64, cos_g: f64) -> f64 {
    let (mu0, mu) = (clamp_unit(cos_i), clamp_unit(cos_e));
    if mu0 <= 0.0 || mu <= 0.0 {
        return 0.0;
    }
    let l = lunar_lambert_l(clamp_unit(cos_g).acos().to_degrees());
    // McEwen's L(g) polynomial turns negative past g ≈ 104°, where it was never fitted: reflect no negative light.
    (albedo * (2.0 * l * mu0 / (mu0 + mu) + (1.0 - l) * mu0)).max(0.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Exact H-function for isotropic scattering: iterate H(μ) = 1 / (1 − (ϖ/2)·μ·∫₀¹ H(μ')/(μ+μ') dμ') on
    /// Gauss–Legendre nodes (this form converges even at ϖ = 1, where the 1/H form oscillates). An independent
    /// reference: no approximation formula involved. Returns H as a function of μ via the same integral.
    fn chandrasekhar_h(w: f64) -> impl Fn(f64) -> f64 {
        let n = 48;
        let (nodes, weights) = gauss_legendre_01(n);
        let mut h = vec![1.0; n];
        let apply = move |h: &[f64], mu: f64| {
            let s: f64 = (0..n).map(|j| weights[j] * h[j] / (mu + nodes[j])).sum();
            1.0 / (1.0 - w / 2.0 * mu * s)
        };
        let (nodes2, _) = gauss_legendre_01(n);
        for _ in 0..400_000 {
            let next: Vec<f64> = nodes2.iter().map(|&m| apply(&h, m)).collect();
            let delta = next
                .iter()
                .zip(&h)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            h = next;
            if delta < 1e-15 {
                break;
            }
        }
        move |mu| apply(&h, mu)
    }

    fn gauss_legendre_01(n: usize) -> (Vec<f64>, Vec<f64>) {
        let (mut nodes, mut weights) = (vec![0.0; n], vec![0.0; n]);
        for i in 0..n {
            let mut x = (PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
            let mut dp = 0.0;
            for _ in 0..100 {
                let (mut p0, mut p1) = (1.0, x);
                for k in 2..=n {
                    let p2 = ((2 * k - 1) as f64 * x * p1 - (k - 1) as f64 * p0) / k as f64;
                    p0 = p1;
                    p1 = p2;
                }
                dp = n as f64 * (x * p1 - p0) / (x * x - 1.0);
                let dx = p1 / dp;
                x -= dx;
                if dx.abs() < 1e-15 {
                    break;
                }
            }
            nodes[i] = (1.0 - x) / 2.0;
            weights[i] = 1.0 / ((1.0 - x * x) * dp * dp);
        }
        (nodes, weights)
    }

    proptest! {
        /// The split recomposes the whole: single × p(g) + multiple is Hapke's I/F, for any material and geometry.
        #[test]
        fn hapke_parts_recompose_the_i_over_f(
            w in 0.02f64..0.95, b in 0.05f64..0.6, c in -0.5f64..1.0, theta in 0.0f64..40.0,
            cos_i in 0.01f64..1.0, cos_e in 0.01f64..1.0, t in 0.0f64..1.0,
        ) {
            let p = HapkeParams { w, b, c, theta_bar_rad: theta.to_radians(), ..HapkeParams::lunar_typical() };
            // A phase consistent with i and e: anywhere between the two azimuth extremes.
            let (si, se) = ((1.0 - cos_i * cos_i).sqrt(), (1.0 - cos_e * cos_e).sqrt());
            let cos_g = cos_i * cos_e + si * se * (1.0 - 2.0 * t);
            for form in [HFunction::Hapke1981, HFunction::Hapke2002] {
                let whole = hapke_i_over_f(&p, cos_i, cos_e, cos_g, form);
                let parts = hapke_parts(&p, cos_i, cos_e, cos_g, form);
                let recomposed = parts.single_per_phase * double_hg(cos_g, b, c) + parts.multiple;
                prop_assert!((whole - recomposed).abs() <= 1e-12 * whole.abs().max(1e-300), "{whole} vs {recomposed}");
                prop_assert!(parts.multiple >= 0.0 && parts.single_per_phase >= 0.0);
            }
        }
    }

    #[test]
    fn chandrasekhar_reference_reproduces_published_conservative_values() {
        // Chandrasekhar (1960), conservative isotropic scattering (ϖ = 1): H(0.5) = 2.0128, H(1) = 2.9078; and the
        // zeroth moment obeys ∫₀¹ H dμ = (2/ϖ)(1 − √(1−ϖ)) for any ϖ.
        let h = chandrasekhar_h(1.0);
        assert!((h(0.5) - 2.0128).abs() < 5e-4, "{}", h(0.5));
        assert!((h(1.0) - 2.9078).abs() < 5e-4, "{}", h(1.0));
        assert_eq!(h(0.0), 1.0);
        let (nodes, weights) = gauss_legendre_01(48);
        for w in [0.3f64, 0.9, 1.0] {
            let h = chandrasekhar_h(w);
            let moment: f64 = nodes.iter().zip(&weights).map(|(&m, &wt)| wt * h(m)).sum();
            let expected = 2.0 / w * (1.0 - (1.0 - w).sqrt());
            assert!(
                (moment - expected).abs() < 1e-4,
                "w={w}: {moment} vs {expected}"
            );
        }
    }

    #[test]
    fn h2002_within_one_percent_and_h1981_within_four_percent_of_exact() {
        for &w in &[0.1, 0.3, 0.5, 0.8, 0.95, 1.0] {
            let exact_h = chandrasekhar_h(w);
            for &x in &[0.0, 0.05, 0.2, 0.5, 0.8, 1.0] {
                let exact = exact_h(x);
                let h02 = h_function(x, w, HFunction::Hapke2002);
                let h81 = h_function(x, w, HFunction::Hapke1981);
                assert!(
                    (h02 / exact - 1.0).abs() < 0.01,
                    "2002 at w={w} x={x}: {h02} vs {exact}"
                );
                assert!(
                    (h81 / exact - 1.0).abs() < 0.04,
                    "1981 at w={w} x={x}: {h81} vs {exact}"
                );
                assert!(
                    (h02 / h81 - 1.0).abs() <= 0.04,
                    "2002 vs 1981 at w={w} x={x}"
                );
            }
        }
    }

    #[test]
    fn zero_roughness_reduces_to_the_smooth_model() {
        let c = roughness(0.7, 0.9, 0.5, 0.0);
        assert_eq!((c.mu0_eff, c.mu_eff, c.shadowing), (0.7, 0.9, 1.0));
        // And the rough model converges to it continuously.
        let r = roughness(0.7, 0.9, 0.5, 1e-4);
        assert!(
            (r.mu0_eff - 0.7).abs() < 1e-3
                && (r.mu_eff - 0.9).abs() < 1e-3
                && (r.shadowing - 1.0).abs() < 1e-3
        );
    }

    #[test]
    fn roughness_branches_agree_at_i_equals_e() {
        // The two branches are written separately; at i = e they must give the same answer from either side.
        let theta = 20f64.to_radians();
        let (ci, cg) = (40f64.to_radians().cos(), 0.3);
        let a = roughness(ci, ci + 1e-9, cg, theta);
        let b = roughness(ci + 1e-9, ci, cg, theta);
        assert!((a.shadowing - b.shadowing).abs() < 1e-6 && (a.mu0_eff - b.mu_eff).abs() < 1e-6);
    }

    #[test]
    fn lunar_lambert_with_l_one_is_lommel_seeliger() {
        // L(0) = 1: I/F = 2A·μ0/(μ0+μ).
        assert_eq!(lunar_lambert_l(0.0), 1.0);
        let (mu0, mu) = (0.6, 0.8);
        let f = lunar_lambert_i_over_f(0.3, mu0, mu, 1.0);
        assert!((f - 2.0 * 0.3 * mu0 / (mu0 + mu)).abs() < 1e-15);
    }

    #[test]
    fn hapke_isotropic_smooth_matches_closed_form() {
        // b = 0 (isotropic phase), no opposition, θ̄ = 0, H1981: r = w/4π · μ0/(μ0+μ) · H(μ0)H(μ).
        let p = HapkeParams {
            w: 0.4,
            b: 0.0,
            c: 0.0,
            b_s0: 0.0,
            h_s: 0.05,
            theta_bar_rad: 0.0,
            porosity_k: 1.0,
        };
        let (mu0, mu) = (0.5, 0.9);
        let g = 0.3; // irrelevant here: isotropic phase and no opposition effect
        let gamma = (1.0f64 - 0.4).sqrt();
        let h = |x: f64| (1.0 + 2.0 * x) / (1.0 + 2.0 * gamma * x);
        let expected = 0.4 / (4.0 * PI) * mu0 / (mu0 + mu) * h(mu0) * h(mu);
        let got = hapke_reflectance(&p, mu0, mu, g, HFunction::Hapke1981);
        assert!((got - expected).abs() < 1e-14, "{got} vs {expected}");
    }

    fn finite_everywhere(p: &HapkeParams, ci: f64, ce: f64, cg: f64) {
        for form in [HFunction::Hapke1981, HFunction::Hapke2002] {
            let r = hapke_reflectance(p, ci, ce, cg, form);
            assert!(
                r.is_finite() && r >= 0.0,
                "r = {r} at {p:?} cos i {ci} cos e {ce} cos g {cg}"
            );
        }
        let ll = lunar_lambert_i_over_f(p.w, ci, ce, cg);
        assert!(ll.is_finite() && ll >= 0.0);
        let rough = roughness(ci, ce, cg, p.theta_bar_rad);
        assert!(
            rough.mu0_eff.is_finite() && rough.mu_eff.is_finite() && rough.shadowing.is_finite()
        );
    }

    /// Cosines of the hazards: exact 0 and 1, a hair outside [−1, 1], and near-grazing values.
    fn hazard_cos() -> impl Strategy<Value = f64> {
        prop_oneof![
            Just(0.0),
            Just(1.0),
            Just(-1.0),
            Just(1.0 + 1e-12),
            Just(-1.0 - 1e-12),
            Just(1e-300),
            Just(1e-9),
            Just(1.0 - 1e-15),
            -1.0f64..=1.0,
        ]
    }

    fn hazard_params() -> impl Strategy<Value = HapkeParams> {
        (
            prop_oneof![
                Just(1.0),
                Just(1.0 - 1e-15),
                Just(1.2),
                Just(0.0),
                0.0f64..1.0
            ],
            prop_oneof![Just(1.0), Just(-1.0), Just(0.999_999_9), -1.0f64..1.0],
            prop_oneof![Just(1.0), Just(-1.0), -1.0f64..1.0],
            0.0f64..4.0,
            prop_oneof![Just(0.0), Just(1e-9), 0.0f64..0.2],
            prop_oneof![
                Just(0.0),
                Just(1e-9),
                Just(1e-7),
                Just(std::f64::consts::FRAC_PI_2),
                0.0f64..1.0
            ],
        )
            .prop_map(|(w, b, c, b_s0, h_s, theta_bar_rad)| HapkeParams {
                w,
                b,
                c,
                b_s0,
                h_s,
                theta_bar_rad,
                porosity_k: 1.0,
            })
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(4000))]
        #[test]
        fn hapke_never_nan_or_inf_on_hard_cases(p in hazard_params(), ci in hazard_cos(), ce in hazard_cos(), cg in hazard_cos()) {
            finite_everywhere(&p, ci, ce, cg);
        }

        #[test]
        fn hapke_never_nan_on_physical_geometries(p in hazard_params(), i in 0.0f64..=90.0, e in 0.0f64..=90.0, psi in 0.0f64..=180.0) {
            // Physically consistent (i, e, ψ) including i = e = 0, ψ = π (g = i + e) and grazing 90°.
            let (i, e, psi) = (i.to_radians(), e.to_radians(), psi.to_radians());
            let cg = i.cos() * e.cos() + i.sin() * e.sin() * psi.cos();
            finite_everywhere(&p, i.cos(), e.cos(), cg);
        }
    }

    #[test]
    fn typical_lunar_i_over_f_is_plausible() {
        // Flat terrain, sun at i = 45°, nadir view: lunar highland I/F at this geometry is of order 0.1.
        let p = HapkeParams::lunar_typical();
        let ci = 45f64.to_radians().cos();
        let v = hapke_i_over_f(&p, ci, 1.0, ci, HFunction::Hapke2002);
        assert!((0.04..0.25).contains(&v), "{v}");
    }
}

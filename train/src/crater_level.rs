//! The crater level: each crop's brightness level inside a large catalogued crater's frame, fitted beside a
//! trained H1 run and applied to its maps in `eval` and `infer`.
//!
//! Why it exists (docs/crater-diagnosis.md): on a complex crater's wall the unit under the crop (mare or highland,
//! 1.66× apart in brightness there) is in the DEM only as the crop's height against the crater's own profile.
//! A ridge regression on that one number reads the unit on held-out wall crops (R² 0.74, AUC 1.0), but the U-Net,
//! trained on every crop at once, renders one wall brightness between the units: it fits the training tiles'
//! walls and does not carry that to held-out ones. A regression of a few coefficients, fitted on the wall's crops
//! alone, does carry. So the network keeps its pattern inside each crop and this model sets the crop's level.
//!
//! - **Fitted on train crops, with no network:** the target is the log of each crop's best uniform H1 scale
//!   (least squares of the ground truth on the Moon-wide Hapke rendering, [`best_uniform_scale`]); the features are
//!   a logistic step in the crop's height against the crater's profile (centre and width chosen on a grid), the
//!   crop's mean slope and its normalised radius ρ. One regression for each band of ρ ([`BANDS`]: the melt floor,
//!   terraced wall, rim and ejecta of a complex crater).
//! - **Chosen on the validation split:** for each band, how far the network's level moves toward the regression's
//!   (`weight`, in log space; 0 keeps the network's), by the summed squared error of the run's renderings of the
//!   band's validation crops. The bands are disjoint, so each band's choice is its own.
//! - **Applied** by scaling every pixel's H1 scale in a crop by `(predicted / network)^weight`, where `network` is
//!   the crop's mean scale in the network's maps: in `eval` read off its rendering ([`rendered_scale`]), in
//!   `infer` the mean of its scale band. Crops in a band of weight 0, beyond the bands, or without a crater frame
//!   are left as the network made them, and counted.
//!
//! This module holds the model (and the regression's fit, which needs no network); [`crate::crater_level_fit`]
//! the passes over a dataset that fit it and choose its weights with the run's network.

use std::path::Path;

use anyhow::{bail, Context, Result};
use dataset::contract::crater_frame::CraterPosition;
use dataset::contract::schema::Sample;
use dataset::science::brdf::BrdfModel;
use dataset::science::least_squares::solve_small_system;

use crate::data::mean_slope_deg;

/// The file a run directory keeps its crater level in; `eval` and `infer` load it with the run.
pub const CRATER_LEVEL_FILE: &str = "crater_level.json";
/// Bumped when the file's meaning changes; older files are refused with the command that rewrites them.
pub const CRATER_LEVEL_VERSION: u32 = 1;

/// The disjoint bands of ρ, each with its own regression and weight: a complex crater's melt floor (ρ < 0.45),
/// terraced wall (to 1), rim (to 1.5) and ejecta (to 3 radii), the classes `eval` groups crops by.
pub const BANDS: [(f64, f64); 4] = [(0.0, 0.45), (0.45, 1.0), (1.0, 1.5), (1.5, 3.0)];
/// How far a crop's level moves from the network's toward the regression's, in log space; 0 keeps the network's.
pub const CANDIDATE_WEIGHTS: [f64; 5] = [0.0, 0.25, 0.5, 0.75, 1.0];
/// Grid of the logistic step's centre (m against the profile) and width (m).
const STEP_CENTRES_M: std::ops::RangeInclusive<i32> = -12..=12; // × 25 m: −300 … 300 m
const STEP_CENTRE_SPACING_M: f64 = 25.0;
const STEP_WIDTHS_M: [f64; 5] = [10.0, 25.0, 50.0, 100.0, 200.0];
/// Slopes enter as mean slope / this, so the coefficients are of one order.
const SLOPE_UNIT_DEG: f64 = 30.0;

/// ln(best uniform H1 scale) of a crop as a function of where it lies in its crater's frame.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LevelRegression {
    /// The band of normalised radius it was fitted on and applies to: `rho_min ≤ ρ < rho_max`.
    pub rho_min: f64,
    pub rho_max: f64,
    /// The logistic step in height against the crater's profile: centre and width, metres.
    pub step_centre_m: f64,
    pub step_width_m: f64,
    /// Coefficients of [1, step, mean slope / 30°, ρ].
    pub coefficients: [f64; 4],
    /// Train crops it was fitted on, and its RMS residual there (natural log of the scale).
    pub train_crops: usize,
    pub train_rms_log: f64,
}

impl LevelRegression {
    pub fn covers(&self, rho: f64) -> bool {
        rho >= self.rho_min && rho < self.rho_max
    }

    fn features(&self, at: &CraterPosition, slope_deg: f64) -> [f64; 4] {
        features(at, slope_deg, self.step_centre_m, self.step_width_m)
    }

    /// The crop's predicted best uniform H1 scale.
    pub fn scale(&self, at: &CraterPosition, slope_deg: f64) -> f64 {
        let x = self.features(at, slope_deg);
        x.iter()
            .zip(&self.coefficients)
            .map(|(x, c)| x * c)
            .sum::<f64>()
            .exp()
    }
}

fn features(at: &CraterPosition, slope_deg: f64, centre_m: f64, width_m: f64) -> [f64; 4] {
    let step = 1.0 / (1.0 + (-(at.relative_height_m - centre_m) / width_m).exp());
    [1.0, step, slope_deg / SLOPE_UNIT_DEG, at.rho]
}

/// One candidate of the validation choice and its score.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CandidateScore {
    pub rho_min: f64,
    pub rho_max: f64,
    pub weight: f64,
    /// Validation crops in the band.
    pub crops_in_band: usize,
    /// The band's summed squared error with this weight over the network's there.
    pub band_sse_ratio: f64,
    /// The whole validation split's, with only this band changed, over the network's.
    pub val_sse_ratio: f64,
}

/// One band's regression and the weight chosen for it (0: the band keeps the network's level).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct BandLevel {
    pub regression: LevelRegression,
    pub weight: f64,
    /// The band's validation SSE with each crop at its own best factor (which peeks at the ground truth) over the
    /// network's: how much of the band's error is the crops' level at all.
    pub val_level_oracle_sse_ratio: f64,
}

impl BandLevel {
    /// The factor on the H1 scales of a crop at `at` in this band: `(predicted / network_scale)^weight`; 1 at
    /// weight 0 or when the network's scale is not positive (no level to move).
    pub fn factor(&self, at: &CraterPosition, slope_deg: f64, network_scale: f64) -> f64 {
        if self.weight > 0.0 && network_scale > 0.0 {
            (self.regression.scale(at, slope_deg) / network_scale).powf(self.weight)
        } else {
            1.0
        }
    }
}

/// A run's crater level: each band's regression and chosen weight, with the table they were chosen from.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CraterLevel {
    pub version: u32,
    /// Disjoint bands of ρ, in order.
    pub bands: Vec<BandLevel>,
    /// Validation crops scored, and those with a crater frame.
    pub val_crops: usize,
    pub val_crops_framed: usize,
    /// The whole validation split's summed squared error with the chosen weights over the network's alone.
    pub val_sse_ratio: f64,
    /// Every candidate, band by band; each band's chosen weight has its lowest `band_sse_ratio`.
    pub candidates: Vec<CandidateScore>,
}

/// A band and its weight, as `eval` reports which levels it applied.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct BandWeight {
    pub rho_min: f64,
    pub rho_max: f64,
    pub weight: f64,
}

impl CraterLevel {
    /// A level from given bands, with no validation record (for tests and hand-made levels).
    pub fn from_bands(bands: Vec<BandLevel>) -> Self {
        Self {
            version: CRATER_LEVEL_VERSION,
            bands,
            val_crops: 0,
            val_crops_framed: 0,
            val_sse_ratio: 1.0,
            candidates: Vec::new(),
        }
    }

    /// Each band's weight.
    pub fn weights(&self) -> Vec<BandWeight> {
        self.bands
            .iter()
            .map(|b| BandWeight {
                rho_min: b.regression.rho_min,
                rho_max: b.regression.rho_max,
                weight: b.weight,
            })
            .collect()
    }

    /// The band that sets the level of a crop at `at` (one with a positive weight), if any.
    fn band<'a>(
        &'a self,
        at: Option<&'a CraterPosition>,
    ) -> Option<(&'a BandLevel, &'a CraterPosition)> {
        let at = at?;
        self.bands
            .iter()
            .find(|b| b.weight > 0.0 && b.regression.covers(at.rho))
            .map(|b| (b, at))
    }

    /// The factor a crop's H1 scales are multiplied by: `(predicted / network_scale)^weight` of its band, else 1
    /// (also when the crop has no frame or the network's scale is not positive).
    pub fn factor(&self, at: Option<&CraterPosition>, slope_deg: f64, network_scale: f64) -> f64 {
        self.band(at)
            .map_or(1.0, |(band, at)| band.factor(at, slope_deg, network_scale))
    }

    /// Whether a crop at `at` is one the level applies to (it lies in a band with a positive weight).
    pub fn applies(&self, at: Option<&CraterPosition>) -> bool {
        self.band(at).is_some()
    }

    /// A sample's learned rendering with the level applied (`hapke`: its Moon-wide Hapke rendering). Returns
    /// whether the level applied to the crop.
    pub fn apply_to_rendering(&self, sample: &Sample, learned: &mut [f64], hapke: &[f64]) -> bool {
        if !self.applies(sample.crater.as_ref()) {
            return false;
        }
        let network = rendered_scale(learned, hapke).unwrap_or(0.0);
        let k = self.factor(sample.crater.as_ref(), mean_slope_deg(sample), network);
        learned.iter_mut().for_each(|x| *x *= k);
        true
    }
}

/// Load a run directory's crater level, if it keeps one; refuses a file of another version or a run whose BRDF
/// model is not H1 (the level is a factor on H1's one scale).
pub fn load(run: &Path, model: BrdfModel) -> Result<Option<CraterLevel>> {
    let path = run.join(CRATER_LEVEL_FILE);
    if !path.exists() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(&path)
        .with_context(|| format!("{}: cannot read", path.display()))?;
    let level: CraterLevel = serde_json::from_str(&text).with_context(|| {
        format!(
            "{}: not a crater level file: rewrite it with `g2r-train crater-level --run {}`",
            path.display(),
            run.display()
        )
    })?;
    if level.version != CRATER_LEVEL_VERSION {
        bail!(
            "{}: crater level version {} (this build reads {CRATER_LEVEL_VERSION}): rewrite it with `g2r-train crater-level --run {}`",
            path.display(),
            level.version,
            run.display()
        );
    }
    if model != BrdfModel::H1 {
        bail!(
            "{}: a crater level scales H1's one scale, but the run's model is {}: remove the file",
            path.display(),
            model.name()
        );
    }
    Ok(Some(level))
}

/// The crop's mean H1 scale as its rendering shows it: the mean of rendering / Moon-wide Hapke over the pixels
/// where Hapke is positive (lit, facing sun and camera); `None` when there are none.
pub fn rendered_scale(rendered: &[f64], hapke: &[f64]) -> Option<f64> {
    let (sum, n) = rendered
        .iter()
        .zip(hapke)
        .filter(|(r, &h)| h > 1e-12 && r.is_finite())
        .fold((0.0, 0usize), |(s, n), (r, h)| (s + r / h, n + 1));
    (n > 0).then(|| sum / n as f64)
}

/// The crop's best uniform H1 scale: least squares of the ground truth on its Moon-wide Hapke rendering over valid
/// pixels (Σ h·t / Σ h²); `None` when Hapke is zero on every valid pixel or the scale is not positive.
pub fn best_uniform_scale(hapke: &[f64], truth: &[f64], valid: &[bool]) -> Option<f64> {
    let mut fit = crate::uniform_fit::ScaleFit::default();
    fit.add(hapke, truth, valid);
    let s = fit.scale();
    (s > 0.0).then_some(s)
}

/// One train crop of the fit: where it lies, how steep it is, and ln of its best uniform H1 scale.
#[derive(Debug, Clone, Copy)]
pub(crate) struct TrainCrop {
    pub at: CraterPosition,
    pub slope_deg: f64,
    pub log_scale: f64,
}

/// Fit the regression of one band on the train crops in it: the step's centre and width on a grid, the four
/// coefficients by least squares at each; the pair with the smallest residual wins.
pub(crate) fn fit_band(crops: &[TrainCrop], band: (f64, f64)) -> Option<LevelRegression> {
    let inside: Vec<&TrainCrop> = crops
        .iter()
        .filter(|c| c.at.rho >= band.0 && c.at.rho < band.1)
        .collect();
    if inside.len() < 16 {
        return None;
    }
    let mut best: Option<LevelRegression> = None;
    for centre in STEP_CENTRES_M.map(|i| i as f64 * STEP_CENTRE_SPACING_M) {
        for width in STEP_WIDTHS_M {
            let (mut ata, mut atb) = (vec![vec![0.0; 4]; 4], vec![0.0; 4]);
            for c in &inside {
                let x = features(&c.at, c.slope_deg, centre, width);
                for i in 0..4 {
                    atb[i] += x[i] * c.log_scale;
                    for j in 0..4 {
                        ata[i][j] += x[i] * x[j];
                    }
                }
            }
            // A whisker of ridge keeps a step that is flat over the band (all crops on one side) solvable.
            for (i, row) in ata.iter_mut().enumerate() {
                row[i] += 1e-9 * inside.len() as f64;
            }
            let beta = solve_small_system(ata, atb);
            let coefficients = [beta[0], beta[1], beta[2], beta[3]];
            let residual: f64 = inside
                .iter()
                .map(|c| {
                    let x = features(&c.at, c.slope_deg, centre, width);
                    let fit: f64 = x.iter().zip(&coefficients).map(|(x, b)| x * b).sum();
                    (fit - c.log_scale).powi(2)
                })
                .sum();
            let rms = (residual / inside.len() as f64).sqrt();
            if rms.is_finite() && best.as_ref().is_none_or(|b| rms < b.train_rms_log) {
                best = Some(LevelRegression {
                    rho_min: band.0,
                    rho_max: band.1,
                    step_centre_m: centre,
                    step_width_m: width,
                    coefficients,
                    train_crops: inside.len(),
                    train_rms_log: rms,
                });
            }
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::baseline::hapke_render;
    use dataset::science::hapke::HapkeParams;

    fn at(rho: f64, h: f64) -> CraterPosition {
        CraterPosition {
            rho,
            relative_height_m: h,
        }
    }

    /// Crops drawn from a known law are fitted back: a step of 0.5 in ln(scale) at +50 m against the
    /// profile, slope and ρ terms, inside the band; crops outside it are not fitted on.
    #[test]
    fn a_band_recovers_the_law_its_crops_follow() {
        let law = |a: &CraterPosition, slope: f64| {
            let step = 1.0 / (1.0 + (-(a.relative_height_m - 50.0) / 25.0).exp());
            -1.2 + 0.5 * step + 0.2 * slope / 30.0 - 0.1 * a.rho
        };
        let mut crops = Vec::new();
        for i in 0..400 {
            let a = at(
                0.45 + 0.55 * (i % 20) as f64 / 20.0,
                -200.0 + (i / 20) as f64 * 20.0,
            );
            let slope = 10.0 + (i % 7) as f64 * 3.0;
            crops.push(TrainCrop {
                at: a,
                slope_deg: slope,
                log_scale: law(&a, slope),
            });
        }
        // Outside the band, a law that would spoil the fit if it were used.
        crops.push(TrainCrop {
            at: at(2.0, 0.0),
            slope_deg: 5.0,
            log_scale: 9.0,
        });
        let r = fit_band(&crops, (0.45, 1.0)).expect("enough crops");
        assert_eq!(r.train_crops, 400);
        assert_eq!((r.step_centre_m, r.step_width_m), (50.0, 25.0));
        for (got, want) in r.coefficients.iter().zip([-1.2, 0.5, 0.2, -0.1]) {
            assert!((got - want).abs() < 1e-6, "{:?}", r.coefficients);
        }
        assert!(r.train_rms_log < 1e-6);
        let probe = at(0.7, 80.0);
        assert!((r.scale(&probe, 20.0).ln() - law(&probe, 20.0)).abs() < 1e-6);
        assert!(fit_band(&crops, (1.0, 1.5)).is_none(), "no crops there");
    }

    /// The factor moves the network's level the chosen fraction of the way (in log space) toward the prediction,
    /// only in the band, and sets it exactly at weight 1.
    #[test]
    fn the_factor_moves_the_level_by_its_weight_inside_the_band_only() {
        let level = |weight| crate::testing::constant_crater_level(0.45, 1.0, 0.4, weight);
        let wall = at(0.7, 30.0);
        assert!((level(1.0).factor(Some(&wall), 25.0, 0.5) * 0.5 - 0.4).abs() < 1e-12);
        assert_eq!(
            level(0.0).factor(Some(&wall), 25.0, 0.5),
            1.0,
            "weight 0 keeps the network's"
        );
        assert!(!level(0.0).applies(Some(&wall)));
        let level = level(0.5);
        let k = level.factor(Some(&wall), 25.0, 0.5);
        assert!((k - (0.8f64).sqrt()).abs() < 1e-12);
        assert_eq!(level.factor(Some(&at(1.2, 30.0)), 25.0, 0.5), 1.0);
        assert_eq!(level.factor(None, 25.0, 0.5), 1.0);
        assert_eq!(
            level.factor(Some(&wall), 25.0, 0.0),
            1.0,
            "no level to move"
        );
    }

    /// `eval`'s path: a crop in the band gets the regression's level at weight 1, whatever the network's was; a
    /// crop without a crater frame is left alone.
    #[test]
    fn applied_to_a_rendering_the_level_is_the_regressions() {
        let level = crate::testing::constant_crater_level(0.45, 1.0, 0.4, 1.0);
        let mut sample = crate::testing::synthetic_samples(1, 3).remove(0);
        let hapke = hapke_render(&sample, &HapkeParams::lunar_typical());
        let network: Vec<f64> = hapke.iter().map(|h| 0.6 * h).collect();
        let mut rendered = network.clone();
        assert!(!level.apply_to_rendering(&sample, &mut rendered, &hapke));
        assert_eq!(rendered, network, "no frame, no level");
        sample.crater = Some(at(0.7, 20.0));
        assert!(level.apply_to_rendering(&sample, &mut rendered, &hapke));
        let shown = rendered_scale(&rendered, &hapke).unwrap();
        assert!((shown - 0.4).abs() < 1e-12, "{shown}");
    }
}

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
//!   a logistic step in the crop's height against the crater's profile, the crop's mean slope and its normalised
//!   radius ρ. One regression for each zone of ρ.
//! - **Zones and steps from the data, not the world generator:** the zones are grown on the train crops
//!   ([`grow_zones`]): one zone over the frame's reach, then, step by step, the split (at a sixteenth of a zone's
//!   crops' ρ) that lowers the train residual most, up to [`MAX_ZONES`]. The step's centre is tried at quantiles of
//!   the zone's heights against the profile and its width at fractions of their interquartile range, so a crater
//!   ten times deeper gives the same fit with its heights ten times larger (tested).
//! - **Chosen on the validation split:** how many zones to keep, and for each zone how far the network's level
//!   moves toward the regression's (`weight`, in log space; 0 keeps the network's), by the summed squared error of
//!   the run's renderings of the validation crops. With the world's terrain classes (`crater-level --world`) the
//!   weights are also held so that no kind of ground (class and unit) gets a larger validation error than the
//!   network's alone.
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
use rayon::prelude::*;

use crate::data::mean_slope_deg;

/// The file a run directory keeps its crater level in; `eval` and `infer` load it with the run.
pub const CRATER_LEVEL_FILE: &str = "crater_level.json";
/// Bumped when the file's meaning changes; older files are refused with the command that rewrites them.
pub const CRATER_LEVEL_VERSION: u32 = 1;

/// How far a crop's level moves from the network's toward the regression's, in log space; 0 keeps the network's.
pub const CANDIDATE_WEIGHTS: [f64; 5] = [0.0, 0.25, 0.5, 0.75, 1.0];
/// The most zones of ρ the fit grows; how many it keeps is chosen on validation.
pub const MAX_ZONES: usize = 8;
/// The fewest train crops a zone is fitted on: a split leaving fewer on either side is not tried.
pub const MIN_ZONE_TRAIN_CROPS: usize = 64;
/// A zone is split only at its crops' ρ sixteenths.
const SPLIT_QUANTILES: usize = 16;
/// The step's centre is tried at the zone's height twentieths (5 % to 95 %), its width at these fractions of the
/// heights' interquartile range.
const STEP_CENTRE_QUANTILES: usize = 20;
const STEP_WIDTH_IQR_FRACTIONS: [f64; 5] = [0.0625, 0.125, 0.25, 0.5, 1.0];
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

    /// Its summed squared residual on the train crops it was fitted on.
    fn train_sse(&self) -> f64 {
        self.train_rms_log.powi(2) * self.train_crops as f64
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
    /// Every candidate of the kept zones, zone by zone: without a ground guard each zone's chosen weight has its
    /// lowest `band_sse_ratio`.
    pub candidates: Vec<CandidateScore>,
    /// Each partition the fit grew (1, 2, … zones), scored on validation with its own chosen weights; the kept one
    /// has the lowest ratio (the fewest zones on a tie). Empty in files written before zones were grown.
    #[serde(default)]
    pub zone_counts: Vec<ZoneCountScore>,
    /// With the world's terrain classes (`crater-level --world`): each kind of ground's validation error with the
    /// chosen level over the network's alone, which the choice holds at or below 1. Empty without them.
    #[serde(default)]
    pub ground_guard: Vec<GroundScore>,
}

/// One partition of ρ into zones, as the validation choice scored it.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ZoneCountScore {
    pub zones: usize,
    /// The zones' inner edges in ρ, in order (the outer ones are 0 and the frame's reach).
    pub edges: Vec<f64>,
    /// The validation split's summed squared error with this partition's chosen weights over the network's.
    pub val_sse_ratio: f64,
    /// Whether holding every kind of ground at or below the network's error changed the weights.
    pub guard_bound: bool,
}

/// One kind of ground's validation error under the chosen level.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct GroundScore {
    /// Class and unit (`rim, highland`), as `eval` labels them; `unknown` off the world's class map.
    pub ground: String,
    pub val_crops: usize,
    /// Its summed squared error with the chosen level over the network's alone (at most 1).
    pub val_sse_ratio: f64,
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
            zone_counts: Vec::new(),
            ground_guard: Vec::new(),
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

/// Fit the regression of one zone of ρ on the train crops in it: the step's centre and width on a grid drawn
/// from the zone's own heights, the four coefficients by least squares at each; the pair with the smallest
/// residual wins. `None` with fewer than [`MIN_ZONE_TRAIN_CROPS`] crops in the zone.
pub(crate) fn fit_zone(crops: &[TrainCrop], zone: (f64, f64)) -> Option<LevelRegression> {
    let inside: Vec<&TrainCrop> = crops
        .iter()
        .filter(|c| c.at.rho >= zone.0 && c.at.rho < zone.1)
        .collect();
    if inside.len() < MIN_ZONE_TRAIN_CROPS {
        return None;
    }
    let mut heights: Vec<f64> = inside.iter().map(|c| c.at.relative_height_m).collect();
    heights.sort_by(f64::total_cmp);
    let quantile = |q: f64| heights[((heights.len() - 1) as f64 * q).round() as usize];
    // Heights that do not spread (all crops at one height) make the step constant over the zone whatever its
    // width; the ridge below keeps that solvable, so any positive width serves.
    let iqr = (quantile(0.75) - quantile(0.25)).max(f64::MIN_POSITIVE);
    let mut best: Option<LevelRegression> = None;
    for k in 1..STEP_CENTRE_QUANTILES {
        let centre = quantile(k as f64 / STEP_CENTRE_QUANTILES as f64);
        for fraction in STEP_WIDTH_IQR_FRACTIONS {
            let width = fraction * iqr;
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
            // A whisker of ridge keeps a step that is flat over the zone (all crops on one side) solvable.
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
                    rho_min: zone.0,
                    rho_max: zone.1,
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

/// The places a zone may be split: midway between neighbouring crops at each sixteenth of its crops' ρ, where
/// both sides keep [`MIN_ZONE_TRAIN_CROPS`].
fn split_points(crops: &[TrainCrop], zone: &LevelRegression) -> Vec<f64> {
    let mut rho: Vec<f64> = crops
        .iter()
        .map(|c| c.at.rho)
        .filter(|&r| zone.covers(r))
        .collect();
    rho.sort_by(f64::total_cmp);
    let mut points: Vec<f64> = (1..SPLIT_QUANTILES)
        .map(|k| k * rho.len() / SPLIT_QUANTILES)
        .filter(|&i| i >= MIN_ZONE_TRAIN_CROPS && rho.len() - i >= MIN_ZONE_TRAIN_CROPS)
        .filter(|&i| rho[i - 1] < rho[i])
        .map(|i| 0.5 * (rho[i - 1] + rho[i]))
        .collect();
    points.dedup();
    points
}

/// Zones of ρ grown on the train crops within `reach` radii: one zone first, then at each step the split of one
/// zone into two regressions that lowers the summed train residual most, until `max_zones` or no split helps.
/// Returns every partition on the way (1, 2, … zones), each a list of disjoint zones covering `[0, reach)` in
/// order; empty when fewer than [`MIN_ZONE_TRAIN_CROPS`] crops lie within reach.
pub(crate) fn grow_zones(
    crops: &[TrainCrop],
    reach: f64,
    max_zones: usize,
) -> Vec<Vec<LevelRegression>> {
    let Some(whole) = fit_zone(crops, (0.0, reach)) else {
        return Vec::new();
    };
    let mut partitions = vec![vec![whole]];
    while let Some(current) = partitions.last().filter(|p| p.len() < max_zones) {
        let tries: Vec<(usize, f64)> = current
            .iter()
            .enumerate()
            .flat_map(|(i, zone)| split_points(crops, zone).into_iter().map(move |s| (i, s)))
            .collect();
        let splits: Vec<(usize, f64, LevelRegression, LevelRegression)> = tries
            .par_iter()
            .filter_map(|&(i, at)| {
                let zone = &current[i];
                let below = fit_zone(crops, (zone.rho_min, at))?;
                let above = fit_zone(crops, (at, zone.rho_max))?;
                let gain = zone.train_sse() - below.train_sse() - above.train_sse();
                (gain > 0.0).then_some((i, gain, below, above))
            })
            .collect();
        // The largest gain; on a tie the first in zone and ρ order, so the result does not depend on threads.
        let Some((i, _, below, above)) =
            splits
                .into_iter()
                .reduce(|best, s| if s.1 > best.1 { s } else { best })
        else {
            break;
        };
        let mut next = current.clone();
        next.splice(i..=i, [below, above]);
        partitions.push(next);
    }
    partitions
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
            relief_to_diameter: None,
        }
    }

    /// 400 crops in a zone: ρ over 0.45–1, heights against the profile from −200 to 180 m, slopes 10–28°.
    fn zone_crops(law: impl Fn(&CraterPosition, f64) -> f64, height_scale: f64) -> Vec<TrainCrop> {
        (0..400)
            .map(|i| {
                let a = at(
                    0.45 + 0.55 * (i % 20) as f64 / 20.0,
                    height_scale * (-200.0 + (i / 20) as f64 * 20.0),
                );
                let slope = 10.0 + (i % 7) as f64 * 3.0;
                TrainCrop {
                    at: a,
                    slope_deg: slope,
                    log_scale: law(&a, slope),
                }
            })
            .collect()
    }

    /// Crops drawn from a known law are fitted back, with the step's centre and width found on the grid the
    /// crops' own heights give (their median, a quarter of their interquartile range, computed here from the
    /// heights); crops outside the zone are not fitted on.
    #[test]
    fn a_zone_recovers_the_law_its_crops_follow_on_a_grid_from_their_heights() {
        let mut heights: Vec<f64> = zone_crops(|_, _| 0.0, 1.0)
            .iter()
            .map(|c| c.at.relative_height_m)
            .collect();
        heights.sort_by(f64::total_cmp);
        let pick = |q: f64| heights[(399.0 * q).round() as usize];
        let (centre, width) = (pick(0.5), (pick(0.75) - pick(0.25)) / 4.0);
        assert_eq!(
            (centre, width),
            (0.0, 45.0),
            "median 0 m, IQR 180 m: the crops' own"
        );
        let law = |a: &CraterPosition, slope: f64| {
            let step = 1.0 / (1.0 + (-(a.relative_height_m - centre) / width).exp());
            -1.2 + 0.5 * step + 0.2 * slope / 30.0 - 0.1 * a.rho
        };
        let mut crops = zone_crops(law, 1.0);
        // Outside the zone, a law that would spoil the fit if it were used.
        crops.push(TrainCrop {
            at: at(2.0, 0.0),
            slope_deg: 5.0,
            log_scale: 9.0,
        });
        let r = fit_zone(&crops, (0.45, 1.0)).expect("enough crops");
        assert_eq!(r.train_crops, 400);
        assert_eq!((r.step_centre_m, r.step_width_m), (centre, width));
        for (got, want) in r.coefficients.iter().zip([-1.2, 0.5, 0.2, -0.1]) {
            assert!((got - want).abs() < 1e-6, "{:?}", r.coefficients);
        }
        assert!(r.train_rms_log < 1e-6);
        let probe = at(0.7, 80.0);
        assert!((r.scale(&probe, 20.0).ln() - law(&probe, 20.0)).abs() < 1e-6);
        assert!(fit_zone(&crops, (1.0, 1.5)).is_none(), "no crops there");
    }

    /// No depth in metres is built in: a crater ten times deeper, whose crops follow the same law of their
    /// heights over ten, is fitted with the same coefficients and a step ten times wider, ten times further out.
    #[test]
    fn a_deeper_crater_gives_the_same_fit_with_its_heights_scaled() {
        let law = |scale: f64| {
            move |a: &CraterPosition, slope: f64| {
                let step = 1.0 / (1.0 + (-(a.relative_height_m / scale - 37.0) / 60.0).exp());
                -1.0 + 0.4 * step + 0.1 * slope / 30.0 + 0.2 * a.rho
            }
        };
        let shallow = fit_zone(&zone_crops(law(1.0), 1.0), (0.45, 1.0)).unwrap();
        let deep = fit_zone(&zone_crops(law(10.0), 10.0), (0.45, 1.0)).unwrap();
        assert!(
            shallow.train_rms_log > 1e-4,
            "the law is off the grid: a real fit"
        );
        assert!((deep.step_centre_m - 10.0 * shallow.step_centre_m).abs() < 1e-9);
        assert!((deep.step_width_m - 10.0 * shallow.step_width_m).abs() < 1e-9);
        for (d, s) in deep.coefficients.iter().zip(&shallow.coefficients) {
            assert!(
                (d - s).abs() < 1e-9,
                "{:?} vs {:?}",
                deep.coefficients,
                shallow.coefficients
            );
        }
        assert!((deep.train_rms_log - shallow.train_rms_log).abs() < 1e-12);
    }

    /// Where the level changes with ρ, the zones grow there: a large change at 1.5 radii splits first, a small
    /// one at 0.75 second (both fall on the sixteenths of the crops of the zone they split), and the third
    /// partition has those edges and no residual. Every partition covers the reach without gaps, keeps the minimum
    /// crops per zone, and fits the train crops no worse than the one before.
    #[test]
    fn zones_grow_where_the_level_changes_with_the_radius() {
        let n = 1600;
        let crops: Vec<TrainCrop> = (0..n)
            .map(|i| {
                let rho = 3.0 * (i as f64 + 0.5) / n as f64;
                let level = if rho < 0.75 {
                    -1.0
                } else if rho < 1.5 {
                    -0.9
                } else {
                    -2.0
                };
                TrainCrop {
                    at: at(rho, -100.0 + (i % 41) as f64 * 5.0),
                    slope_deg: 5.0 + (i % 13) as f64,
                    log_scale: level,
                }
            })
            .collect();
        let partitions = grow_zones(&crops, 3.0, MAX_ZONES);
        assert!(partitions.len() >= 3, "{} partitions", partitions.len());
        let mut last_sse = f64::INFINITY;
        for (k, zones) in partitions.iter().enumerate() {
            assert_eq!(zones.len(), k + 1);
            assert_eq!(zones[0].rho_min, 0.0);
            assert_eq!(zones.last().unwrap().rho_max, 3.0);
            for pair in zones.windows(2) {
                assert_eq!(pair[0].rho_max, pair[1].rho_min, "no gap, no overlap");
            }
            assert!(zones.iter().all(|z| z.train_crops >= MIN_ZONE_TRAIN_CROPS));
            assert_eq!(zones.iter().map(|z| z.train_crops).sum::<usize>(), n);
            let sse: f64 = zones.iter().map(LevelRegression::train_sse).sum();
            assert!(sse <= last_sse, "partition {k}: {sse} after {last_sse}");
            last_sse = sse;
        }
        let three = &partitions[2];
        let edges: Vec<f64> = three[1..].iter().map(|z| z.rho_min).collect();
        assert!(
            (edges[0] - 0.75).abs() < 1e-12 && (edges[1] - 1.5).abs() < 1e-12,
            "{edges:?}"
        );
        assert_eq!(
            partitions[1][1].rho_min, edges[1],
            "the large change splits first"
        );
        assert!(three.iter().all(|z| z.train_rms_log < 1e-4), "{three:?}");
        assert!(grow_zones(&crops[..MIN_ZONE_TRAIN_CROPS - 1], 3.0, MAX_ZONES).is_empty());
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

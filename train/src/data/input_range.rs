//! The range a run's per-crop inputs spanned over its train crops (`input_range.json`), and how many crops of the
//! data a run is applied to fall outside it. Outside, the network extrapolates: a crater deeper for its size than
//! any it trained on, or a context window mostly off a small DEM, can be rendered far from the truth (the demo
//! world, docs/experiments.md, forty-fourth session). `eval` and `infer` count such crops and say so, rather than
//! render them silently.

use std::collections::BTreeMap;

use anyhow::{bail, Result};
use dataset::contract::crater_frame::CraterPosition;
use dataset::contract::schema::{Sample, Split};

use super::{
    crop_interior_m, crop_mean, for_each_sample_group, framed, InputNormalisation, SampleSource,
};

/// Train crops, spread over the split, whose inputs make a run's range: enough that a crop of the training data
/// itself falls outside it about once in 2,000 per side, few enough to read in seconds at the start of a fit.
pub const INPUT_RANGE_SAMPLES: usize = 4096;

/// The file a run keeps its range in.
pub const INPUT_RANGE_FILE: &str = "input_range.json";

/// Closed interval of one input over train crops.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Interval {
    pub min: f64,
    pub max: f64,
}

impl Interval {
    fn point(v: f64) -> Self {
        Self { min: v, max: v }
    }

    fn widen(&mut self, v: f64) {
        self.min = self.min.min(v);
        self.max = self.max.max(v);
    }
}

/// One crop's scalar inputs a range is kept for, each where the crop has it. Names are what
/// [`Self::named`] calls them in `input_range.json` and in reports.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct CropInputs {
    /// Std of the crop's finite heights, metres: the relief plane is heights over one fixed std, so a rougher
    /// crop (a steeper site, or a finer DEM) feeds the network larger values than any it saw.
    pub height_std_m: Option<f64>,
    /// Share of the context window's cells with no DEM (past a small DEM's edge).
    pub context_off_dem: Option<f64>,
    /// The crop's height against its framing crater's profile, metres (framed crops only).
    pub crater_relative_height_m: Option<f64>,
    /// The framing crater's relief over its diameter (framed crops only).
    pub crater_relief_to_diameter: Option<f64>,
}

impl CropInputs {
    /// From a crop's `heights_m` (its `CROP_PX²` interior), its context window's heights, when the run cut one,
    /// and its crater position (taken as framed only within the profile's reach, as the frame input takes it).
    pub fn of(
        heights_m: &[f64],
        context_m: Option<&[f32]>,
        crater: Option<&CraterPosition>,
    ) -> Self {
        let finite: Vec<f64> = heights_m
            .iter()
            .copied()
            .filter(|z| z.is_finite())
            .collect();
        let height_std_m = (!finite.is_empty()).then(|| {
            let mean = crop_mean(&finite);
            (finite.iter().map(|z| (z - mean).powi(2)).sum::<f64>() / finite.len() as f64).sqrt()
        });
        let context_off_dem = context_m
            .filter(|c| !c.is_empty())
            .map(|c| c.iter().filter(|z| !z.is_finite()).count() as f64 / c.len() as f64);
        let crater = framed(crater);
        Self {
            height_std_m,
            context_off_dem,
            crater_relative_height_m: crater.map(|c| c.relative_height_m),
            crater_relief_to_diameter: crater.and_then(|c| c.relief_to_diameter),
        }
    }

    /// A published sample's inputs, as `fit` and `eval` feed them.
    pub fn of_sample(sample: &Sample) -> Self {
        Self::of(
            &crop_interior_m(sample),
            sample.context.as_ref().map(|c| c.heights_m.as_slice()),
            sample.crater.as_ref(),
        )
    }

    /// Each input by its name, in a fixed order.
    pub fn named(&self) -> [(&'static str, Option<f64>); 4] {
        [
            ("crop_height_std_m", self.height_std_m),
            ("context_off_dem", self.context_off_dem),
            ("crater_relative_height_m", self.crater_relative_height_m),
            ("crater_relief_to_diameter", self.crater_relief_to_diameter),
        ]
    }
}

/// A run's range: each input's interval over the train crops that had it (`input_range.json`). An input no train
/// crop had (no context window, no catalogue) has no interval, and is not checked.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct InputRange {
    /// Train crops the range was measured over (spread over the split of every training publication).
    pub crops: usize,
    /// The publications whose train split it spans, in the run's pool order.
    pub datasets: Vec<String>,
    pub inputs: BTreeMap<String, Interval>,
}

impl InputRange {
    /// Over up to `max` train crops of `source`, spread over its split (every training member of a pool).
    pub fn of_source(source: &dyn SampleSource, datasets: Vec<String>, max: usize) -> Result<Self> {
        let mut range = Self {
            crops: 0,
            datasets,
            inputs: BTreeMap::new(),
        };
        for_each_sample_group(source, Split::Train, Some(max), "input range", |group| {
            for sample in group {
                range.widen(&CropInputs::of_sample(sample));
            }
        })?;
        if range.crops == 0 {
            bail!(
                "{}: the train split has no crops to measure the inputs' range on",
                source.describe()
            );
        }
        Ok(range)
    }

    fn widen(&mut self, crop: &CropInputs) {
        self.crops += 1;
        for (name, value) in crop.named() {
            if let Some(v) = value {
                self.inputs
                    .entry(name.to_string())
                    .and_modify(|i| i.widen(v))
                    .or_insert(Interval::point(v));
            }
        }
    }

    /// A crater position with its relief over diameter clamped into the training range (`--clamp-crater-relief`):
    /// a crater fresher than any trained on is fed as the freshest one, not extrapolated from.
    pub fn clamp_crater_relief(&self, crater: &CraterPosition) -> CraterPosition {
        let interval = self.inputs.get("crater_relief_to_diameter");
        CraterPosition {
            relief_to_diameter: match (crater.relief_to_diameter, interval) {
                (Some(r), Some(i)) => Some(r.clamp(i.min, i.max)),
                (r, _) => r,
            },
            ..*crater
        }
    }

    /// The range a run's crater relief is clamped into (`--clamp-crater-relief`): refused for a run that keeps no
    /// range, or feeds no relief.
    pub fn for_clamping<'a>(
        range: Option<&'a Self>,
        input: &InputNormalisation,
    ) -> Result<&'a Self> {
        let Some(range) = range else {
            bail!(
                "the run keeps no input range ({INPUT_RANGE_FILE}) to clamp the crater relief into: measure it with \
                 `g2r-train input-range`, or drop --clamp-crater-relief"
            );
        };
        if input.crater_relief().is_none() {
            bail!("the run has no crater relief input to clamp (trained without --crater-relief-input): drop --clamp-crater-relief");
        }
        Ok(range)
    }

    /// An empty count of crops against this range.
    pub fn check(&self) -> RangeCheck<'_> {
        RangeCheck {
            range: self,
            crops: 0,
            outside_any: 0,
            inputs: BTreeMap::new(),
        }
    }
}

/// Crops counted against a run's [`InputRange`], input by input.
pub struct RangeCheck<'a> {
    range: &'a InputRange,
    crops: usize,
    outside_any: usize,
    inputs: BTreeMap<&'static str, InputCount>,
}

/// One input's count: how many crops had it, how many fell below and above the training interval, and the
/// interval they spanned.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct InputCount {
    pub training: Interval,
    pub seen: Interval,
    pub crops: usize,
    pub below: usize,
    pub above: usize,
}

impl RangeCheck<'_> {
    /// Count one crop; whether it has any input outside the training range.
    pub fn add(&mut self, crop: &CropInputs) -> bool {
        self.crops += 1;
        let mut outside = false;
        for (name, value) in crop.named() {
            let (Some(v), Some(&training)) = (value, self.range.inputs.get(name)) else {
                continue;
            };
            let count = self.inputs.entry(name).or_insert(InputCount {
                training,
                seen: Interval::point(v),
                crops: 0,
                below: 0,
                above: 0,
            });
            count.seen.widen(v);
            count.crops += 1;
            count.below += usize::from(v < training.min);
            count.above += usize::from(v > training.max);
            outside |= v < training.min || v > training.max;
        }
        self.outside_any += usize::from(outside);
        outside
    }

    pub fn finish(self) -> RangeReport {
        RangeReport {
            crops: self.crops,
            outside_any: self.outside_any,
            measured_on_crops: self.range.crops,
            inputs: self
                .inputs
                .into_iter()
                .map(|(name, count)| (name.to_string(), count))
                .collect(),
        }
    }
}

/// How many crops lay outside a run's training range (`metrics.json`'s `inputs_outside_training_range`).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct RangeReport {
    /// Crops counted.
    pub crops: usize,
    /// Of them, those with at least one input outside its training interval.
    pub outside_any: usize,
    /// Train crops the run's range was measured over.
    pub measured_on_crops: usize,
    pub inputs: BTreeMap<String, InputCount>,
}

impl RangeReport {
    /// One line for a log or a report: how many crops lay outside, and which inputs took them there.
    pub fn summary(&self) -> String {
        let outside: Vec<String> = self
            .inputs
            .iter()
            .filter(|(_, c)| c.below + c.above > 0)
            .map(|(name, c)| {
                format!(
                    "{name} {} below and {} above [{:.4}, {:.4}] (seen {:.4} to {:.4})",
                    c.below, c.above, c.training.min, c.training.max, c.seen.min, c.seen.max
                )
            })
            .collect();
        if outside.is_empty() {
            format!(
                "all {} crops lie within the run's training range of inputs",
                self.crops
            )
        } else {
            format!(
                "{} of {} crops have an input outside the run's training range, where the network extrapolates: {}",
                self.outside_any,
                self.crops,
                outside.join("; ")
            )
        }
    }

    /// Log the summary, a warning when any crop lay outside; for a run that keeps no range (`None`), that its
    /// crops were not counted.
    pub fn log(report: Option<&Self>) {
        match report {
            Some(r) if r.outside_any > 0 => tracing::warn!("{}", r.summary()),
            Some(r) => tracing::info!("{}", r.summary()),
            None => tracing::info!(
                "the run keeps no input range ({INPUT_RANGE_FILE}): crops outside its training inputs are not \
                 counted (`g2r-train input-range` measures one)"
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dataset::contract::crater_frame::PROFILE_RHO_MAX;

    fn crater(rho: f64, relief: f64) -> CraterPosition {
        CraterPosition {
            rho,
            relative_height_m: -10.0,
            relief_to_diameter: Some(relief),
        }
    }

    #[test]
    fn a_crops_inputs_are_its_height_std_off_dem_share_and_frame_within_reach() {
        // Heights 0 and 2 alternating (std exactly 1), one hole; a window a quarter off the DEM.
        let mut heights: Vec<f64> = (0..16).map(|k| 2.0 * (k % 2) as f64).collect();
        heights.push(f64::NAN);
        let mut window = vec![5.0f32; 12];
        window.extend([f32::NAN; 4]);
        let inputs = CropInputs::of(&heights, Some(&window), Some(&crater(1.0, 0.08)));
        assert_eq!(inputs.height_std_m, Some(1.0));
        assert_eq!(inputs.context_off_dem, Some(0.25));
        assert_eq!(inputs.crater_relative_height_m, Some(-10.0));
        assert_eq!(inputs.crater_relief_to_diameter, Some(0.08));
        // Past the profile's reach the crop is unframed, as the frame input feeds it.
        let far = CropInputs::of(&heights, None, Some(&crater(PROFILE_RHO_MAX + 0.1, 0.08)));
        assert_eq!(far.crater_relief_to_diameter, None);
        assert_eq!(far.crater_relative_height_m, None);
        assert_eq!(far.context_off_dem, None);
    }

    fn range_of(reliefs: &[f64]) -> InputRange {
        let mut range = InputRange {
            crops: 0,
            datasets: vec!["d".into()],
            inputs: BTreeMap::new(),
        };
        for &r in reliefs {
            range.widen(&CropInputs {
                crater_relief_to_diameter: Some(r),
                height_std_m: Some(10.0 * r),
                ..CropInputs::default()
            });
        }
        range
    }

    #[test]
    fn the_range_spans_the_train_crops_and_a_check_counts_each_side_and_each_crop_once() {
        let range = range_of(&[0.05, 0.12, 0.08]);
        assert_eq!(range.crops, 3);
        assert_eq!(
            range.inputs["crater_relief_to_diameter"],
            Interval {
                min: 0.05,
                max: 0.12
            }
        );
        let mut check = range.check();
        // Inside, on both edges, one below and one above on both inputs, and one with no inputs at all.
        for r in [0.07, 0.05, 0.12, 0.01, 0.15] {
            check.add(&CropInputs {
                crater_relief_to_diameter: Some(r),
                height_std_m: Some(10.0 * r),
                ..CropInputs::default()
            });
        }
        check.add(&CropInputs::default());
        let report = check.finish();
        assert_eq!((report.crops, report.outside_any), (6, 2));
        let relief = report.inputs["crater_relief_to_diameter"];
        assert_eq!((relief.crops, relief.below, relief.above), (5, 1, 1));
        assert_eq!(
            relief.seen,
            Interval {
                min: 0.01,
                max: 0.15
            }
        );
        assert!(
            report.summary().starts_with("2 of 6 crops"),
            "{}",
            report.summary()
        );
        // An input no train crop had is not checked.
        assert!(!report.inputs.contains_key("context_off_dem"));
    }

    #[test]
    fn clamping_moves_only_a_relief_outside_the_range_onto_its_edge() {
        let range = range_of(&[0.05, 0.12]);
        let clamped = |r| {
            range
                .clamp_crater_relief(&crater(0.5, r))
                .relief_to_diameter
        };
        assert_eq!(clamped(0.15), Some(0.12));
        assert_eq!(clamped(0.01), Some(0.05));
        assert_eq!(clamped(0.07), Some(0.07));
        let unmeasured = CraterPosition {
            relief_to_diameter: None,
            ..crater(0.5, 0.0)
        };
        assert_eq!(
            range.clamp_crater_relief(&unmeasured).relief_to_diameter,
            None
        );
    }
}

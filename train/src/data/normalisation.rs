//! How a crop's heights become the network's input planes (relief, elevation, context), fitted on the train
//! split and saved with a run so evaluation and inference feed the network what training did.

use anyhow::{bail, Result};
use dataset::contract::crater_frame::{CraterPosition, PROFILE_RHO_MAX};
use dataset::contract::schema::{Sample, CONTEXT_PX};

use super::{crop_interior_m, SampleSource};

/// How a crop's heights become the network's input planes; saved with a run (`normalisation.json`) so that
/// evaluation and inference on a new DEM feed the network exactly what training did.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct InputNormalisation {
    /// Train-split DEM std: the relief plane is (height − crop mean) / this (docs/design.md, Data contract).
    pub dem_std_m: f64,
    /// Absolute-elevation plane, (height − mean) / std over train crops, when the run uses one. The relief plane
    /// hides where a crop sits (crater floor, mare plain or rim), and at the crop scale that explains much of the
    /// albedo (`--elevation-input`); runs written before it existed have none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub elevation: Option<ElevationNormalisation>,
    /// Context input, when the run uses one (`--context-input`): the sample's wide coarse DEM window
    /// (`dataset::contract::context`) relative to the crop's mean height, so the network sees whether the crop lies in a
    /// crater, on its wall or on a plain kilometres across.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub context: Option<ContextNormalisation>,
}

/// The context window's cell size (the one the training data was cut with; inference cuts the same) and the std
/// its heights relative to the crop mean are divided by.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ContextNormalisation {
    pub gsd_m: f64,
    pub std_m: f64,
    /// Also feed the window's absolute heights, normalised as the elevation plane is (`--context-absolute`).
    /// Relative heights show where the crop lies in the terrain; absolute ones show how high that terrain
    /// stands, which on a crater wall is what tells the unit under it (docs/crater-diagnosis.md). Runs written
    /// before it existed have none.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub absolute: bool,
    /// Also feed the crop's height relative to its crater's median profile (`--crater-input`; the sample's
    /// `crater_relative_height_m`, `dataset::contract::crater_frame`) as a constant plane, over this RMS of it
    /// over train crops. On a complex crater's wall that height tells the unit under the crop, which neither the
    /// crop's own level nor the window's shape does (docs/crater-diagnosis.md). Runs written before it existed
    /// have none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crater_rms_m: Option<f64>,
    /// Feed the crater input as a frame (`--crater-frame-input`): the height against the profile as above, the
    /// crop's normalised radius ρ over the profile's reach, and a plane that is 1 where the crop is framed
    /// ([`framed`]). An unframed crop (no catalogue, its crater missed by the catalogue, or past the reach) is fed
    /// 0, 1 and 0: the network learns to do without a frame, and one model runs on a site with a catalogue or
    /// without. Runs written before it existed have none.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub crater_frame: bool,
    /// Feed the framing crater's relief over its diameter (the sample's `crater_relief_to_diameter`,
    /// `dataset::contract::crater_frame::RELIEF_CREST_RHO_MAX`) as one more frame plane, standardised by these
    /// train statistics, 0 where the crop is not framed (`--crater-relief-input`). A crater's wall and ejecta are
    /// as bright as the crater is fresh, and a fresh crater is deep for its size: the relief says which crater
    /// of a field is the young one, where the crop's own window sees only part of it. Runs written before it
    /// existed have none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crater_relief: Option<ReliefNormalisation>,
    /// Feed the window's highland fraction from the site's unit map (the sample's `context_highland`) as a plane,
    /// 2·fraction − 1 where mapped and 0 where not, and a plane that is 1 where mapped (`--unit-input`). A crater
    /// wall is bright fresh material of the ground it cuts, highland or mare, and with heights relative to the
    /// crop no crop tells which: a unit map does, as a catalogue tells where the crater is. A sample without a
    /// map is fed as unmapped everywhere. Runs written before it existed have none.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub units: bool,
}

/// Mean and std of the framing craters' relief over diameter over framed train crops (each crop counts once,
/// so a crater counts as often as it frames crops).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ReliefNormalisation {
    pub mean: f64,
    pub std: f64,
}

/// A crop's crater frame when it has one within the profile's reach ([`PROFILE_RHO_MAX`] radii): past it the
/// crater is not the crop's terrain, and the frame input treats the crop as it treats one with no catalogue.
pub fn framed(crater: Option<&CraterPosition>) -> Option<&CraterPosition> {
    crater.filter(|c| c.rho < PROFILE_RHO_MAX)
}

/// Planes of the relative context input: relative height, then a mask (1 where the cell has DEM). An absolute
/// context and a crater-relative height add their planes between the two, in that order.
pub const CONTEXT_CHANNELS: usize = 2;

/// Which optional planes a context input carries beside its [`CONTEXT_CHANNELS`]. [`Self::count`] is the one place
/// they are counted: the network's width (`FitConfig::net_config`) and the batches'
/// ([`InputNormalisation::context_channels`]) both come from it, so the two cannot drift.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ContextPlanes {
    /// Absolute height (`--context-absolute`).
    pub absolute: bool,
    /// Height relative to the framing crater's profile (`--crater-input`).
    pub crater: bool,
    /// The crater frame's two planes, ρ and its mask (`--crater-frame-input`).
    pub crater_frame: bool,
    /// The framing crater's relief over diameter (`--crater-relief-input`).
    pub crater_relief: bool,
    /// The unit map's two planes, highland fraction and mapped mask (`--unit-input`).
    pub units: bool,
}

impl ContextPlanes {
    pub fn count(self) -> usize {
        CONTEXT_CHANNELS
            + usize::from(self.absolute)
            + usize::from(self.crater)
            + 2 * usize::from(self.crater_frame)
            + usize::from(self.crater_relief)
            + 2 * usize::from(self.units)
    }
}

impl ContextNormalisation {
    /// From train samples' context windows: their common cell size, and the pooled std of every finite cell's
    /// height relative to its crop's mean.
    pub fn of_samples<'a>(samples: impl IntoIterator<Item = &'a Sample>) -> Result<Self> {
        let (mut gsd_m, mut n, mut sum_sq) = (None::<f64>, 0usize, 0f64);
        for s in samples {
            let Some(context) = &s.context else {
                bail!(
                    "sample {} has no context window: the dataset predates schema 1.2; re-run `g2r-pipeline run` to publish one with context_dem",
                    s.sample_id
                );
            };
            match gsd_m {
                Some(g) if g != context.gsd_m => bail!(
                    "samples' context windows have different cell sizes ({g} m and {} m at {})",
                    context.gsd_m,
                    s.sample_id
                ),
                _ => gsd_m = Some(context.gsd_m),
            }
            let mean = crop_mean(&crop_interior_m(s));
            for &z in context.heights_m.iter().filter(|z| z.is_finite()) {
                n += 1;
                sum_sq += (z as f64 - mean).powi(2);
            }
        }
        let (Some(gsd_m), true) = (gsd_m, n >= 2) else {
            bail!("no finite context heights to normalise the context input with");
        };
        let std_m = (sum_sq / n as f64).sqrt();
        if std_m <= 0.0 {
            bail!("every context window is flat at its crop's height: the context input would divide by zero");
        }
        Ok(Self {
            gsd_m,
            std_m,
            absolute: false,
            crater_rms_m: None,
            crater_frame: false,
            crater_relief: None,
            units: false,
        })
    }

    /// Refuse a `--unit-input` run whose train crops carry no unit map at all: it would learn nothing from the
    /// planes and read a map at inference as something it never saw.
    pub fn check_units_mapped<'a>(samples: impl IntoIterator<Item = &'a Sample>) -> Result<()> {
        let mapped = samples
            .into_iter()
            .any(|s| s.context.as_ref().is_some_and(|c| c.highland.is_some()));
        if !mapped {
            bail!("no train crop carries a unit map's highland fraction: publish the dataset with inputs.unit_map in the pipeline manifest (schema 1.6), or train without --unit-input");
        }
        Ok(())
    }

    /// Statistics of the [`framed`] train crops' crater relief over diameter, for `--crater-relief-input`. A
    /// framed crop without one (a shard older than schema 1.4) is refused.
    pub fn crater_relief_of_samples<'a>(
        samples: impl IntoIterator<Item = &'a Sample>,
    ) -> Result<ReliefNormalisation> {
        let mut reliefs = Vec::new();
        for s in samples {
            let Some(crater) = framed(s.crater.as_ref()) else {
                continue;
            };
            let Some(relief) = crater.relief_to_diameter else {
                bail!(
                    "sample {} has a crater frame without its crater's relief: re-run `g2r-pipeline run` to publish schema 1.4, or train without --crater-relief-input",
                    s.sample_id
                );
            };
            reliefs.push(relief);
        }
        let (n, mean, std) = count_mean_std(reliefs);
        if n < 2 {
            bail!("fewer than two framed train crops: no crater relief to normalise the relief input with");
        }
        if !(std > 0.0 && std.is_finite()) {
            bail!("every framed train crop's crater has the same relief: the relief input would divide by zero");
        }
        Ok(ReliefNormalisation { mean, std })
    }

    /// The RMS of train samples' crater-relative heights, for `--crater-input`: over every sample, each of
    /// which must have a frame; with `frame_input`, over the [`framed`] ones (a catalogue's simulated errors
    /// leave some samples with no frame in reach, or none at all).
    pub fn crater_rms_of_samples<'a>(
        samples: impl IntoIterator<Item = &'a Sample>,
        frame_input: bool,
    ) -> Result<f64> {
        let (mut n, mut sum_sq) = (0usize, 0f64);
        for s in samples {
            let crater = match (&s.crater, frame_input) {
                (Some(crater), false) => crater,
                (crater, true) => match framed(crater.as_ref()) {
                    Some(crater) => crater,
                    None => continue,
                },
                (None, false) => bail!(
                    "sample {} has no crater frame: publish the dataset with inputs.crater_catalogue in the pipeline manifest (schema 1.3), or train without --crater-input",
                    s.sample_id
                ),
            };
            n += 1;
            sum_sq += crater.relative_height_m.powi(2);
        }
        let rms = (sum_sq / n.max(1) as f64).sqrt();
        if !(rms > 0.0 && rms.is_finite()) {
            bail!("no train crop stands off its crater's profile: the crater input would divide by zero");
        }
        Ok(rms)
    }
}

/// Mean of the finite heights (0 when there are none): the level every input plane and the crater input take a
/// crop's height from.
pub fn crop_mean(heights_m: &[f64]) -> f64 {
    let finite = heights_m.iter().filter(|z| z.is_finite());
    let count = finite.clone().count();
    finite.sum::<f64>() / count.max(1) as f64
}

/// Count, mean and population std of `values`, in one pass (sums of values and of their squares).
fn count_mean_std(values: impl IntoIterator<Item = f64>) -> (usize, f64, f64) {
    let (mut n, mut sum, mut sum_sq) = (0usize, 0f64, 0f64);
    for v in values {
        n += 1;
        sum += v;
        sum_sq += v * v;
    }
    let mean = sum / n.max(1) as f64;
    (
        n,
        mean,
        (sum_sq / n.max(1) as f64 - mean * mean).max(0.0).sqrt(),
    )
}

/// Mean and std of absolute heights over train crops' pixels.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ElevationNormalisation {
    pub mean_m: f64,
    pub std_m: f64,
}

impl ElevationNormalisation {
    /// Pooled mean and std of the crops' heights (`crops` of `CROP_PX²` each; non-finite heights skipped).
    pub fn of_crops<'a>(crops: impl IntoIterator<Item = &'a [f64]>) -> Result<Self> {
        // Heights are ~−1e3 m with ~1e2 m spread: the one-pass form loses ~1e-10 relative here, far below need.
        let (n, mean_m, std_m) = count_mean_std(
            crops
                .into_iter()
                .flat_map(|crop| crop.iter().copied().filter(|z| z.is_finite())),
        );
        if n < 2 {
            bail!("no finite heights to normalise the elevation input with");
        }
        if std_m <= 0.0 {
            bail!("train crops all have the same height: the elevation input would divide by zero");
        }
        Ok(Self { mean_m, std_m })
    }
}

impl InputNormalisation {
    /// Relief only (the paper's input).
    pub fn relief(dem_std_m: f64) -> Self {
        Self {
            dem_std_m,
            elevation: None,
            context: None,
        }
    }

    pub fn channels(&self) -> usize {
        1 + usize::from(self.elevation.is_some())
    }

    /// Refuse a dataset that cannot feed this input: a context input needs schema 1.2 or later (`context_dem`),
    /// a crater input 1.3 (`crater_relative_height_m`).
    pub fn check_dataset(&self, source: &dyn SampleSource) -> Result<()> {
        let version = &source.manifest().schema_version;
        let minor = version
            .split('.')
            .nth(1)
            .and_then(|m| m.parse::<u32>().ok());
        if self.context.is_some() && minor.is_none_or(|m| m < 2) {
            bail!(
                "{}: dataset schema {version} has no context windows, but the run feeds one (--context-input): re-run `g2r-pipeline run` to publish schema 1.2",
                source.describe()
            );
        }
        if self.crater_rms_m().is_some() && minor.is_none_or(|m| m < 3) {
            bail!(
                "{}: dataset schema {version} has no crater frames, but the run feeds one (--crater-input): re-run `g2r-pipeline run` with inputs.crater_catalogue to publish schema 1.3",
                source.describe()
            );
        }
        if self.crater_relief().is_some() && minor.is_none_or(|m| m < 4) {
            bail!(
                "{}: dataset schema {version} has no crater relief, but the run feeds it (--crater-relief-input): re-run `g2r-pipeline run` with inputs.crater_catalogue to publish schema 1.4",
                source.describe()
            );
        }
        if self.units() && minor.is_none_or(|m| m < 6) {
            bail!(
                "{}: dataset schema {version} has no unit map planes, but the run feeds them (--unit-input): re-run `g2r-pipeline run` with inputs.unit_map to publish schema 1.6",
                source.describe()
            );
        }
        Ok(())
    }

    /// Context planes per sample (0 without a context input).
    pub fn context_channels(&self) -> usize {
        self.context.map_or(0, |c| {
            ContextPlanes {
                absolute: c.absolute,
                crater: c.crater_rms_m.is_some(),
                crater_frame: c.crater_rms_m.is_some() && c.crater_frame,
                crater_relief: self.crater_relief().is_some(),
                units: c.units,
            }
            .count()
        })
    }

    /// Whether the run feeds the unit map's planes ([`ContextNormalisation::units`]).
    pub fn units(&self) -> bool {
        self.context.is_some_and(|c| c.units)
    }

    /// The relief plane's statistics, when the run feeds one (only as part of a crater frame).
    pub fn crater_relief(&self) -> Option<ReliefNormalisation> {
        self.context
            .filter(|c| c.crater_rms_m.is_some() && c.crater_frame)
            .and_then(|c| c.crater_relief)
    }

    /// The crater input's scale, when the run feeds one.
    pub fn crater_rms_m(&self) -> Option<f64> {
        self.context.and_then(|c| c.crater_rms_m)
    }

    /// Whether the run feeds its crater input as a frame, which a crop without one can be fed too
    /// ([`ContextNormalisation::crater_frame`]).
    pub fn crater_frame_input(&self) -> bool {
        self.context
            .is_some_and(|c| c.crater_rms_m.is_some() && c.crater_frame)
    }

    /// Append one crop's planes (`CROP_PX²` heights, row-major, metres) channel after channel. A non-finite height
    /// (a DEM hole at inference) is fed as the crop's mean height in every plane: a function of the crop alone,
    /// so the same terrain gives the same input whatever the DEM's extent.
    pub fn push_planes(&self, heights_m: &[f64], out: &mut Vec<f64>) {
        let mean = crop_mean(heights_m);
        let filled = |z: f64| if z.is_finite() { z } else { mean };
        out.extend(
            heights_m
                .iter()
                .map(|&z| (filled(z) - mean) / self.dem_std_m),
        );
        if let Some(e) = self.elevation {
            out.extend(heights_m.iter().map(|&z| (filled(z) - e.mean_m) / e.std_m));
        }
    }

    /// Append one crop's context planes (`CONTEXT_PX²` each): the window's heights minus the crop's mean height
    /// (`heights_m`, as in [`Self::push_planes`]) over the context std, 0 where a cell has no DEM; with an
    /// absolute context, the window's heights normalised as the elevation plane, 0 where no DEM; with a crater
    /// input, the crop's crater-relative height over its train RMS in every cell (as a frame, then ρ over the
    /// reach and the framed plane, 0, 1 and 0 when not [`framed`]); with a unit input, the cells' highland
    /// fraction `highland` as 2·fraction − 1 and where it is mapped, 0 and 0 where not (or without a map); then the
    /// mask. Panics when the run has no context input, or feeds the crater height alone and `crater` is `None`
    /// (checked when a run starts).
    pub fn push_context(
        &self,
        heights_m: &[f64],
        context_m: &[f32],
        crater: Option<&CraterPosition>,
        highland: Option<&[f32]>,
        out: &mut Vec<f64>,
    ) {
        let c = self
            .context
            .expect("push_context on a run without context input");
        assert_eq!(
            context_m.len(),
            CONTEXT_PX * CONTEXT_PX,
            "context window size"
        );
        let mean = crop_mean(heights_m);
        out.extend(context_m.iter().map(|&z| {
            if z.is_finite() {
                (z as f64 - mean) / c.std_m
            } else {
                0.0
            }
        }));
        if c.absolute {
            let e = self
                .elevation
                .expect("an absolute context is normalised as the elevation plane (checked when a run starts)");
            out.extend(context_m.iter().map(|&z| {
                if z.is_finite() {
                    (z as f64 - e.mean_m) / e.std_m
                } else {
                    0.0
                }
            }));
        }
        match (c.crater_rms_m, c.crater_frame) {
            (None, _) => {}
            (Some(rms), false) => {
                let crater = crater.expect(
                    "a crater input needs every sample's crater frame (checked when a run starts)",
                );
                out.extend(std::iter::repeat_n(
                    crater.relative_height_m / rms,
                    context_m.len(),
                ));
            }
            (Some(rms), true) => {
                let at = framed(crater);
                let (height, rho, framed) = match at {
                    Some(at) => (at.relative_height_m / rms, at.rho / PROFILE_RHO_MAX, 1.0),
                    None => (0.0, 1.0, 0.0),
                };
                for value in [height, rho, framed] {
                    out.extend(std::iter::repeat_n(value, context_m.len()));
                }
                if let Some(r) = self.crater_relief() {
                    let relief = at.map_or(0.0, |at| {
                        let relief = at.relief_to_diameter.expect(
                            "a relief input needs every frame's relief (schema 1.4, checked when a run starts)",
                        );
                        (relief - r.mean) / r.std
                    });
                    out.extend(std::iter::repeat_n(relief, context_m.len()));
                }
            }
        }
        if c.units {
            let cells = context_m.len();
            let highland = highland.inspect(|h| assert_eq!(h.len(), cells, "unit window size"));
            let at = |k: usize| highland.map(|h| h[k]).filter(|f| f.is_finite());
            out.extend((0..cells).map(|k| at(k).map_or(0.0, |f| 2.0 * f64::from(f) - 1.0)));
            out.extend((0..cells).map(|k| f64::from(u8::from(at(k).is_some()))));
        }
        out.extend(context_m.iter().map(|z| f64::from(u8::from(z.is_finite()))));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A context input of 512 m cells and 4 m std with no optional plane; tests switch on the ones they need.
    fn plain_context() -> ContextNormalisation {
        ContextNormalisation {
            gsd_m: 512.0,
            std_m: 4.0,
            absolute: false,
            crater_rms_m: None,
            crater_frame: false,
            crater_relief: None,
            units: false,
        }
    }
    use dataset::contract::schema::{CONTEXT_PX, DEM_PX};

    #[test]
    fn planes_are_relief_then_elevation_and_a_hole_is_fed_at_the_crop_mean() {
        let input = InputNormalisation {
            dem_std_m: 2.0,
            elevation: Some(ElevationNormalisation {
                mean_m: 10.0,
                std_m: 4.0,
            }),
            context: None,
        };
        // Crop mean over the finite heights: (10 + 12 + 20) / 3 = 14.
        let mut out = Vec::new();
        input.push_planes(&[10.0, 12.0, f64::NAN, 20.0], &mut out);
        assert_eq!(out, vec![-2.0, -1.0, 0.0, 3.0, 0.0, 0.5, 1.0, 2.5]);
        assert_eq!(input.channels(), 2);

        let mut relief = Vec::new();
        InputNormalisation::relief(2.0).push_planes(&[10.0, 12.0, f64::NAN, 20.0], &mut relief);
        assert_eq!(relief, out[..4]);
        assert_eq!(InputNormalisation::relief(2.0).channels(), 1);
    }

    #[test]
    fn elevation_statistics_pool_every_finite_height_of_every_crop() {
        // Heights 1, 2, 3, 5: mean 2.75, population variance (3.0625 + 0.5625 + 0.0625 + 5.0625) / 4 = 2.1875.
        let crops = [vec![1.0, 2.0, f64::NAN, 3.0], vec![5.0, f64::INFINITY]];
        let e = ElevationNormalisation::of_crops(crops.iter().map(Vec::as_slice)).unwrap();
        assert_eq!(e.mean_m, 2.75);
        assert!((e.std_m - 2.1875f64.sqrt()).abs() < 1e-15);
        // Lunar-scale heights keep their precision in the one-pass form.
        let far = [vec![-1201.0, -1199.0]];
        let e = ElevationNormalisation::of_crops(far.iter().map(Vec::as_slice)).unwrap();
        assert_eq!((e.mean_m, e.std_m), (-1200.0, 1.0));

        let flat = [vec![3.0, 3.0]];
        let err = ElevationNormalisation::of_crops(flat.iter().map(Vec::as_slice)).unwrap_err();
        assert!(err.to_string().contains("same height"), "{err}");
        let empty: [Vec<f64>; 0] = [];
        assert!(ElevationNormalisation::of_crops(empty.iter().map(Vec::as_slice)).is_err());
    }

    /// A sample whose crop heights are all `crop_m` and whose context is `context_m` (cells beyond those given
    /// are NaN: off the DEM).
    fn sample_with_context(crop_m: f32, context_m: &[f32], gsd_m: f64) -> Sample {
        let mut s = dataset::testing::synthetic_sample(0);
        s.dem_m = vec![crop_m; DEM_PX * DEM_PX];
        let mut heights_m = vec![f32::NAN; CONTEXT_PX * CONTEXT_PX];
        heights_m[..context_m.len()].copy_from_slice(context_m);
        s.context = Some(dataset::contract::schema::ContextWindow {
            gsd_m,
            heights_m,
            highland: None,
        });
        s
    }

    /// A context window whose first three cells are −1190, −1210 and −1202 m; the rest are holes.
    fn context_window() -> Vec<f32> {
        let mut context = vec![f32::NAN; CONTEXT_PX * CONTEXT_PX];
        context[..3].copy_from_slice(&[-1190.0, -1210.0, -1202.0]);
        context
    }

    /// The context planes `input` makes of [`context_window`] around a crop of −1200, a hole and −1204 m; and the
    /// cells per plane.
    fn context_planes(input: &InputNormalisation) -> (Vec<f64>, usize) {
        let mut out = Vec::new();
        input.push_context(
            &[-1200.0, f64::NAN, -1204.0],
            &context_window(),
            None,
            None,
            &mut out,
        );
        (out, CONTEXT_PX * CONTEXT_PX)
    }

    #[test]
    fn a_crater_input_feeds_the_crops_relative_height_over_its_rms_before_the_mask() {
        let input = InputNormalisation {
            context: Some(ContextNormalisation {
                crater_rms_m: Some(50.0),
                ..plain_context()
            }),
            ..InputNormalisation::relief(2.0)
        };
        let crater = CraterPosition {
            rho: 0.7,
            relative_height_m: -125.0,
            relief_to_diameter: None,
        };
        let mut out = Vec::new();
        input.push_context(
            &[-1200.0, f64::NAN, -1204.0],
            &context_window(),
            Some(&crater),
            None,
            &mut out,
        );
        let n = CONTEXT_PX * CONTEXT_PX;
        assert_eq!((out.len(), input.context_channels()), (3 * n, 3));
        // The relative plane as without it, then −125 / 50 in every cell, then the mask.
        assert_eq!(out[..3], [3.0, -2.0, 0.0]);
        assert!(out[n..2 * n].iter().all(|&v| v == -2.5));
        assert_eq!(out[2 * n..2 * n + 4], [1.0, 1.0, 1.0, 0.0]);
        let json = serde_json::to_string(&input.context).unwrap();
        assert!(json.contains(r#""crater_rms_m":50.0"#), "{json}");
        // Runs written before the crater input read as having none.
        let old: Option<ContextNormalisation> =
            serde_json::from_str(r#"{"gsd_m":512.0,"std_m":4.0}"#).unwrap();
        assert_eq!(old.unwrap().crater_rms_m, None);
    }

    #[test]
    fn the_crater_rms_is_over_train_samples_and_a_sample_without_a_frame_is_refused() {
        // dataset::testing's sample i stands 10 i − 40 m off its crater's profile: −30, −20 and −10 m.
        let mut samples: Vec<Sample> = (1..=3).map(dataset::testing::synthetic_sample).collect();
        let rms = ContextNormalisation::crater_rms_of_samples(&samples, false).unwrap();
        assert!((rms - (1400.0f64 / 3.0).sqrt()).abs() < 1e-12, "{rms}");
        samples[1].crater = None;
        let err = ContextNormalisation::crater_rms_of_samples(&samples, false)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains(&samples[1].sample_id) && err.contains("inputs.crater_catalogue"),
            "{err}"
        );
    }

    #[test]
    fn a_crater_frame_input_feeds_height_radius_and_framed_and_an_unframed_crop_as_none() {
        let input = InputNormalisation {
            context: Some(ContextNormalisation {
                crater_rms_m: Some(50.0),
                crater_frame: true,
                ..plain_context()
            }),
            ..InputNormalisation::relief(2.0)
        };
        assert!(input.crater_frame_input());
        let n = CONTEXT_PX * CONTEXT_PX;
        assert_eq!(input.context_channels(), 5);
        let planes = |crater: Option<CraterPosition>| {
            let mut out = Vec::new();
            input.push_context(
                &[-1200.0, f64::NAN, -1204.0],
                &context_window(),
                crater.as_ref(),
                None,
                &mut out,
            );
            assert_eq!(out.len(), 5 * n);
            // Each crater plane is one value in every cell.
            (1..4)
                .map(|k| {
                    assert!(out[k * n..(k + 1) * n].iter().all(|&v| v == out[k * n]));
                    out[k * n]
                })
                .collect::<Vec<f64>>()
        };
        let at = |rho: f64| CraterPosition {
            rho,
            relative_height_m: -125.0,
            relief_to_diameter: None,
        };
        // Height over its RMS, ρ over the reach of 3 radii, framed.
        assert_eq!(planes(Some(at(0.75))), [-2.5, 0.25, 1.0]);
        // Past the reach, and with no frame at all: the same unframed input.
        assert_eq!(planes(Some(at(PROFILE_RHO_MAX))), [0.0, 1.0, 0.0]);
        assert_eq!(planes(None), [0.0, 1.0, 0.0]);
        // The RMS of a frame input is over the framed samples alone; the height alone needs every one framed.
        let mut samples: Vec<Sample> = (1..=3).map(dataset::testing::synthetic_sample).collect();
        samples[0].crater = None;
        samples[1].crater.as_mut().unwrap().rho = 4.0;
        let rms = ContextNormalisation::crater_rms_of_samples(&samples, true).unwrap();
        assert_eq!(rms, samples[2].crater.unwrap().relative_height_m.abs());
        assert!(ContextNormalisation::crater_rms_of_samples(&samples, false).is_err());
        let json = serde_json::to_string(&input.context).unwrap();
        assert!(json.contains(r#""crater_frame":true"#), "{json}");
        // Runs written before the frame input read as feeding the height alone.
        let old: Option<ContextNormalisation> =
            serde_json::from_str(r#"{"gsd_m":512.0,"std_m":4.0,"crater_rms_m":50.0}"#).unwrap();
        assert!(!old.unwrap().crater_frame);
    }

    #[test]
    fn a_relief_input_feeds_the_standardised_relief_after_the_frame_and_zero_unframed() {
        // Framed train crops' reliefs 0.05, 0.07 and 0.09 (one crop unframed, one past the reach): mean 0.07,
        // population std √(0.0008 / 3).
        let mut samples: Vec<Sample> = (1..=5).map(dataset::testing::synthetic_sample).collect();
        for (s, relief) in samples.iter_mut().zip([0.05, 0.07, 0.09, 0.5, 0.5]) {
            s.crater.as_mut().unwrap().relief_to_diameter = Some(relief);
        }
        samples[3].crater.as_mut().unwrap().rho = 4.0;
        samples[4].crater = None;
        let r = ContextNormalisation::crater_relief_of_samples(&samples).unwrap();
        assert!((r.mean - 0.07).abs() < 1e-15, "{r:?}");
        assert!((r.std - (0.0008f64 / 3.0).sqrt()).abs() < 1e-15, "{r:?}");
        // A framed crop whose shard predates the relief is refused, not fed as some value.
        samples[0].crater.as_mut().unwrap().relief_to_diameter = None;
        let err = ContextNormalisation::crater_relief_of_samples(&samples).unwrap_err();
        assert!(err.to_string().contains("schema 1.4"), "{err}");

        let input = InputNormalisation {
            context: Some(ContextNormalisation {
                crater_rms_m: Some(50.0),
                crater_frame: true,
                crater_relief: Some(ReliefNormalisation {
                    mean: 0.07,
                    std: 0.01,
                }),
                ..plain_context()
            }),
            ..InputNormalisation::relief(2.0)
        };
        let n = CONTEXT_PX * CONTEXT_PX;
        assert_eq!(input.context_channels(), 6);
        let planes = |crater: Option<CraterPosition>| {
            let mut out = Vec::new();
            input.push_context(
                &[-1200.0],
                &context_window(),
                crater.as_ref(),
                None,
                &mut out,
            );
            assert_eq!(out.len(), 6 * n);
            (1..5).map(|k| out[k * n]).collect::<Vec<f64>>()
        };
        let at = CraterPosition {
            rho: 0.75,
            relative_height_m: -125.0,
            relief_to_diameter: Some(0.095),
        };
        let framed = planes(Some(at));
        assert_eq!(framed[..3], [-2.5, 0.25, 1.0]);
        assert!((framed[3] - 2.5).abs() < 1e-12, "{framed:?}");
        assert_eq!(planes(None), [0.0, 1.0, 0.0, 0.0]);
        // Without the frame input the relief is not fed, whatever the file holds.
        let mut height_only = input;
        height_only.context.as_mut().unwrap().crater_frame = false;
        assert!(height_only.crater_relief().is_none());
        let json = serde_json::to_string(&input.context).unwrap();
        let back: Option<ContextNormalisation> = serde_json::from_str(&json).unwrap();
        assert_eq!(back, input.context);
    }

    #[test]
    fn context_planes_are_height_above_the_crop_mean_then_the_mask() {
        let input = InputNormalisation {
            context: Some(plain_context()),
            ..InputNormalisation::relief(2.0)
        };
        // Crop mean over the finite heights: (−1200 − 1204) / 2 = −1202.
        let (out, n) = context_planes(&input);
        assert_eq!(out.len(), 2 * n);
        assert_eq!(out[..4], [3.0, -2.0, 0.0, 0.0]);
        assert!(out[3..n].iter().all(|&v| v == 0.0), "holes are fed as 0");
        assert_eq!(out[n..n + 4], [1.0, 1.0, 1.0, 0.0]);
        assert_eq!(out[n..].iter().sum::<f64>(), 3.0);
        assert_eq!((input.channels(), input.context_channels()), (1, 2));
        assert_eq!(InputNormalisation::relief(2.0).context_channels(), 0);
        // Written without the absolute flag, as runs before it were (their normalisation.json stays the same).
        let json = serde_json::to_string(&input.context).unwrap();
        assert_eq!(json, r#"{"gsd_m":512.0,"std_m":4.0}"#);
        assert_eq!(
            serde_json::from_str::<Option<ContextNormalisation>>(&json).unwrap(),
            input.context
        );
    }

    #[test]
    fn an_absolute_context_adds_the_window_normalised_as_the_elevation_plane() {
        let input = InputNormalisation {
            elevation: Some(ElevationNormalisation {
                mean_m: -1200.0,
                std_m: 5.0,
            }),
            context: Some(ContextNormalisation {
                absolute: true,
                ..plain_context()
            }),
            ..InputNormalisation::relief(2.0)
        };
        let (out, n) = context_planes(&input);
        assert_eq!(out.len(), 3 * n);
        assert_eq!(input.context_channels(), 3);
        // Relative plane as without the flag; then (z + 1200) / 5; then the mask.
        assert_eq!(out[..3], [3.0, -2.0, 0.0]);
        assert_eq!(out[n..n + 4], [2.0, -2.0, -0.4, 0.0]);
        assert!(
            out[n + 3..2 * n].iter().all(|&v| v == 0.0),
            "holes are fed as 0"
        );
        assert_eq!(out[2 * n..2 * n + 4], [1.0, 1.0, 1.0, 0.0]);
        // The same terrain raised by 50 m: the relative plane is unchanged, the absolute one moves by 50 / 5.
        let raised: Vec<f32> = context_window().iter().map(|z| z + 50.0).collect();
        let mut moved = Vec::new();
        input.push_context(
            &[-1150.0, f64::NAN, -1154.0],
            &raised,
            None,
            None,
            &mut moved,
        );
        assert_eq!(moved[..n], out[..n]);
        assert_eq!(moved[n..n + 3], [12.0, 8.0, 9.6]);
        let json = serde_json::to_string(&input.context).unwrap();
        assert!(json.contains(r#""absolute":true"#), "{json}");
    }

    #[test]
    fn context_statistics_pool_cells_relative_to_their_own_crop() {
        // Crop at −1000 with cells −1003, −997; crop at −2000 with cell −1996: deviations −3, 3, 4 → std √(34/3).
        let samples = [
            sample_with_context(-1000.0, &[-1003.0, -997.0], 512.0),
            sample_with_context(-2000.0, &[-1996.0], 512.0),
        ];
        let c = ContextNormalisation::of_samples(&samples).unwrap();
        assert_eq!(c.gsd_m, 512.0);
        assert!(
            (c.std_m - (34.0f64 / 3.0).sqrt()).abs() < 1e-12,
            "{}",
            c.std_m
        );

        let mixed = [
            samples[0].clone(),
            sample_with_context(-1000.0, &[-990.0], 256.0),
        ];
        let err = ContextNormalisation::of_samples(&mixed).unwrap_err();
        assert!(err.to_string().contains("cell sizes"), "{err}");
        let mut old = samples[0].clone();
        old.context = None;
        let err = ContextNormalisation::of_samples(&[old]).unwrap_err();
        assert!(err.to_string().contains("schema 1.2"), "{err}");
        let flat = [sample_with_context(-1000.0, &[-1000.0, -1000.0], 512.0)];
        assert!(ContextNormalisation::of_samples(&flat).is_err());
    }

    /// The unit planes: 2·fraction − 1 and 1 where the map has the cell, 0 and 0 where it has not or there is no
    /// map, between the crater planes and the mask; and a run whose train crops have no map is refused.
    #[test]
    fn the_unit_map_is_fed_as_a_signed_fraction_and_where_it_is_mapped() {
        let input = InputNormalisation {
            context: Some(ContextNormalisation {
                units: true,
                ..plain_context()
            }),
            ..InputNormalisation::relief(2.0)
        };
        let n = CONTEXT_PX * CONTEXT_PX;
        assert_eq!(input.context_channels(), CONTEXT_CHANNELS + 2);
        let mut highland = vec![f32::NAN; n];
        highland[..3].copy_from_slice(&[1.0, 0.0, 0.25]);
        let planes = |highland: Option<&[f32]>| {
            let mut out = Vec::new();
            input.push_context(&[-1200.0], &context_window(), None, highland, &mut out);
            assert_eq!(out.len(), 4 * n);
            out
        };
        let mapped = planes(Some(&highland));
        assert_eq!(mapped[n..n + 4], [1.0, -1.0, -0.5, 0.0]);
        assert_eq!(mapped[2 * n..2 * n + 4], [1.0, 1.0, 1.0, 0.0]);
        // The DEM mask stays last: the window's first three cells have DEM.
        assert_eq!(mapped[3 * n..3 * n + 4], [1.0, 1.0, 1.0, 0.0]);
        let unmapped = planes(None);
        assert!(unmapped[n..3 * n].iter().all(|&v| v == 0.0));
        assert_eq!(unmapped[..n], mapped[..n]);
        assert_eq!(unmapped[3 * n..], mapped[3 * n..]);

        let mut sample = sample_with_context(-1200.0, &context_window()[..3], 512.0);
        sample.context.as_mut().unwrap().highland = None;
        let err = ContextNormalisation::check_units_mapped([&sample]).unwrap_err();
        assert!(err.to_string().contains("inputs.unit_map"), "{err}");
        sample.context.as_mut().unwrap().highland = Some(highland);
        ContextNormalisation::check_units_mapped([&sample]).unwrap();
    }
}

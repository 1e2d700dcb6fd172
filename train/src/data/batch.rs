//! Samples to one host batch (network input planes, renderer geometry, targets), and the per-crop statistics the
//! epoch planner weighs rows by.

use anyhow::Result;
use dataset::contract::schema::{Sample, Split, DEM_PX};
use rayon::prelude::*;

use super::{for_each_sample_group, InputNormalisation, SampleSource};

/// One batch on the host, f64 (the device's float type decides the precision on upload). Rasters are
/// `N × edge²` row-major, north row first.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct HostBatch {
    pub sample_ids: Vec<String>,
    /// Network input `N × C × 128²` ([`InputNormalisation::push_planes`]): interior heights minus the crop mean over
    /// the train-split std, then (when the run uses it) absolute elevation.
    pub net_input: Vec<f64>,
    /// Input planes per sample (`C`).
    pub input_channels: usize,
    /// Context input `N × C' × 32²` ([`InputNormalisation::push_context`]); empty when the run has none.
    pub context_input: Vec<f64>,
    /// Context planes per sample (`C'`; 0 without a context input).
    pub context_channels: usize,
    /// `N × 130²` heights relative to each crop's ENU origin (with apron), metres.
    pub relative_heights_m: Vec<f64>,
    pub image: Vec<f64>,
    pub valid: Vec<f64>,
    pub lit: Vec<f64>,
    pub sun_dir_enu: Vec<f64>,
    pub camera_pos_enu_m: Vec<f64>,
    pub map_to_en: Vec<f64>,
    pub gsd_m: Vec<f64>,
    pub origin_height_m: Vec<f64>,
}

impl HostBatch {
    pub fn len(&self) -> usize {
        self.sample_ids.len()
    }

    pub fn is_empty(&self) -> bool {
        self.sample_ids.is_empty()
    }

    /// Assemble a batch, with the network input normalised as `input` says (docs/design.md, Data contract).
    pub fn from_samples(samples: &[Sample], input: &InputNormalisation) -> Self {
        let mut b = HostBatch {
            input_channels: input.channels(),
            context_channels: input.context_channels(),
            ..HostBatch::default()
        };
        for s in samples {
            b.sample_ids.push(s.sample_id.clone());
            let crop = crop_interior_m(s);
            input.push_planes(&crop, &mut b.net_input);
            if input.context.is_some() {
                let context = s.context.as_ref().unwrap_or_else(|| {
                    panic!(
                        "sample {} has no context window, but the run feeds one (checked when a run starts)",
                        s.sample_id
                    )
                });
                input.push_context(
                    &crop,
                    &context.heights_m,
                    s.crater.as_ref(),
                    context.highland.as_deref(),
                    &mut b.context_input,
                );
            }
            b.relative_heights_m
                .extend(s.dem_m.iter().map(|&h| h as f64 - s.enu_origin_height_m));
            b.image.extend(s.image.iter().map(|&v| v as f64));
            b.valid.extend(s.valid.iter().map(|&v| f64::from(v != 0)));
            b.lit.extend(s.sun_lit.iter().map(|&v| v as f64));
            b.sun_dir_enu.extend(s.sun_dir_enu);
            b.camera_pos_enu_m.extend(s.camera_pos_enu_m);
            b.map_to_en.extend(s.map_to_en);
            b.gsd_m.push(s.gsd_m);
            b.origin_height_m.push(s.enu_origin_height_m);
        }
        b
    }
}

/// A sample's interior heights (the `128²` crop inside the one-pixel apron), row-major, metres.
pub fn crop_interior_m(sample: &Sample) -> Vec<f64> {
    dataset::contract::schema::crop_interior(&sample.dem_m).collect()
}

/// Mean slope of the crop's delivered DEM in degrees: the tilt of [`dataset::science::geometry::plane_normal`] from central
/// differences over the crop's own cells (the apron gives their neighbours), on the map grid (the slope's size
/// does not depend on which way rows run).
pub fn mean_slope_deg(sample: &Sample) -> f64 {
    grid_mean_slope_deg(
        |c, r| sample.dem_m[r * DEM_PX + c] as f64,
        DEM_PX,
        sample.gsd_m,
    )
}

/// [`mean_slope_deg`] of any `n × n` height grid (`height(col, row)`, cells of `gsd` m): the mean over its
/// interior cells of the central-difference slope; cells whose stencil touches a non-finite height (a DEM hole)
/// are left out of the mean.
pub fn grid_mean_slope_deg(height: impl Fn(usize, usize) -> f64, n: usize, gsd: f64) -> f64 {
    let (mut sum, mut count) = (0.0, 0usize);
    for r in 1..n - 1 {
        for c in 1..n - 1 {
            let dx = (height(c + 1, r) - height(c - 1, r)) / (2.0 * gsd);
            let dy = (height(c, r + 1) - height(c, r - 1)) / (2.0 * gsd);
            if !(dx.is_finite() && dy.is_finite()) {
                continue;
            }
            sum += dataset::science::geometry::plane_normal(dx, dy)
                .z
                .clamp(-1.0, 1.0)
                .acos();
            count += 1;
        }
    }
    (sum / count.max(1) as f64).to_degrees()
}

/// Crops at least this steep (mean slope of the delivered DEM, [`mean_slope_deg`]) are the ones a steep-weighted
/// epoch draws more often: on tycho-full they are 28 % of the test crops and hold the complex crater's walls.
pub const STEEP_SLOPE_DEG: f64 = 20.0;

/// Each row's draw weight for a steep-weighted epoch ([`dataset::contract::planner::plan_weighted_epoch`]), in the split's
/// row-group order, then row order: `steep_weight` for a crop whose mean slope is at least [`STEEP_SLOPE_DEG`],
/// 1 otherwise. The slope is the delivered DEM's, so the weighting needs no truth. One pass over the split.
pub fn steep_row_weights(
    source: &dyn SampleSource,
    split: Split,
    steep_weight: f64,
) -> Result<Vec<f64>> {
    let mut weights = Vec::new();
    for_each_sample_group(source, split, None, "steep weights", |samples| {
        weights.extend(
            samples
                .par_iter()
                .map(|s| {
                    if mean_slope_deg(s) >= STEEP_SLOPE_DEG {
                        steep_weight
                    } else {
                        1.0
                    }
                })
                .collect::<Vec<f64>>(),
        );
    })?;
    Ok(weights)
}

//! Fitting a run's [`crate::crater_level`] (`crater-level`, `fit --crater-level`), beside the run it scores: the
//! passes over a dataset: each band's regression fitted on the train split (no network), then
//! every band's weight chosen on the validation split with the run's network, from each crop's sufficient
//! statistics.

use anyhow::{bail, Result};
use dataset::contract::crater_frame::CraterPosition;
use dataset::contract::schema::{Split, CROP_PX};
use dataset::science::brdf::BrdfModel;
use dataset::science::hapke::HapkeParams;
use rayon::prelude::*;

use crate::baseline::{hapke_render, truth_and_valid};
use crate::crater_level::{
    best_uniform_scale, fit_band, rendered_scale, BandLevel, CandidateScore, CraterLevel,
    LevelRegression, TrainCrop, BANDS, CANDIDATE_WEIGHTS, CRATER_LEVEL_VERSION,
};
use crate::data::{for_each_sample_group, mean_slope_deg, SampleSource};
use crate::kernels::TrainOps;
use crate::prediction::predict_ensemble;
use crate::run_dir::TrainedRun;

/// One validation crop's sufficient statistics: for a factor k on the learned rendering L, its squared error is
/// k²·ll − 2k·lg + gg.
#[derive(Debug, Clone, Copy)]
struct ValCrop {
    at: Option<CraterPosition>,
    slope_deg: f64,
    network_scale: f64,
    ll: f64,
    lg: f64,
    gg: f64,
}

impl ValCrop {
    fn sse(&self, k: f64) -> f64 {
        k * k * self.ll - 2.0 * k * self.lg + self.gg
    }

    /// The factor that minimises the crop's error (lg / ll): it peeks at the ground truth.
    fn best_factor(&self) -> f64 {
        if self.ll > 0.0 {
            self.lg / self.ll
        } else {
            1.0
        }
    }
}

/// How many crops `crater-level` reads.
#[derive(Debug, Clone, Copy)]
pub struct CraterLevelOptions {
    /// Train crops read (spread evenly over the split; only those within 3 radii of a crater are fitted on).
    pub train_samples: Option<usize>,
    /// Validation crops the choice is scored on (spread evenly; default all).
    pub val_samples: Option<usize>,
    pub batch_size: usize,
}

/// What `crater-level` did: the chosen level, and what it read.
#[derive(Debug, Clone)]
pub struct CraterLevelFit {
    pub level: CraterLevel,
    pub train_crops_read: usize,
    pub train_crops_framed: usize,
}

/// Fit each band's regression on the train split (no network), score every candidate on the validation split
/// with the run's network, and return the best (lowest validation SSE). Refuses a dataset without crater frames
/// and a run that is not H1.
pub fn fit_crater_level<B: TrainOps>(
    run: &TrainedRun<B>,
    source: &dyn SampleSource,
    options: &CraterLevelOptions,
    device: &B::Device,
) -> Result<CraterLevelFit> {
    if run.config.model != BrdfModel::H1 {
        bail!(
            "a crater level scales H1's one scale, but the run's model is {}: fit it beside an H1 run",
            run.config.model.name()
        );
    }
    run.input.check_dataset(source)?;
    match &source.manifest().crater_frame {
        Some(frame) => tracing::info!(
            catalogue = %frame.catalogue,
            blake3 = %frame.catalogue_blake3,
            min_diameter_m = frame.min_diameter_m,
            "the dataset's crater frames (its manifest)"
        ),
        None => tracing::info!(
            "the dataset's manifest names no crater catalogue (published before it did, or without one): the samples' own frames decide"
        ),
    }
    let params = HapkeParams::lunar_typical();
    let reach = BANDS.iter().map(|b| b.1).fold(0.0, f64::max);
    let (mut read, mut framed, mut train) = (0usize, 0usize, Vec::<TrainCrop>::new());
    for_each_sample_group(
        source,
        Split::Train,
        options.train_samples,
        "crater-level fit",
        |group| {
            read += group.len();
            let crops: Vec<Option<TrainCrop>> = group
                .par_iter()
                .map(|s| {
                    let at = s.crater?;
                    if at.rho >= reach {
                        return None;
                    }
                    let (truth, valid) = truth_and_valid(s);
                    let scale = best_uniform_scale(&hapke_render(s, &params), &truth, &valid)?;
                    Some(TrainCrop {
                        at,
                        slope_deg: mean_slope_deg(s),
                        log_scale: scale.ln(),
                    })
                })
                .collect();
            framed += group.iter().filter(|s| s.crater.is_some()).count();
            train.extend(crops.into_iter().flatten());
        },
    )?;
    if framed == 0 {
        bail!(
            "{}: no train crop has a crater frame: publish the dataset with inputs.crater_catalogue in its pipeline manifest (schema 1.3)",
            source.describe()
        );
    }
    let regressions: Vec<LevelRegression> = BANDS
        .iter()
        .filter_map(|&band| fit_band(&train, band))
        .collect();
    if regressions.is_empty() {
        bail!(
            "{}: no band of crater radii holds 16 train crops within {reach} radii of a catalogued crater: nothing to fit a crater level on",
            source.describe()
        );
    }

    let runs = std::slice::from_ref(run);
    let mut val = Vec::<ValCrop>::new();
    for_each_sample_group(
        source,
        Split::Val,
        options.val_samples,
        "crater-level choice",
        |group| {
            for chunk in group.chunks(options.batch_size.max(1)) {
                let learned = predict_ensemble(runs, chunk, false, device);
                let px = CROP_PX * CROP_PX;
                let crops: Vec<ValCrop> = chunk
                    .par_iter()
                    .enumerate()
                    .map(|(i, s)| {
                        let l = &learned[i * px..(i + 1) * px];
                        let hapke = hapke_render(s, &params);
                        let (truth, valid) = truth_and_valid(s);
                        let (mut ll, mut lg, mut gg) = (0.0, 0.0, 0.0);
                        for ((&x, &t), &ok) in l.iter().zip(&truth).zip(&valid) {
                            if ok && x.is_finite() {
                                ll += x * x;
                                lg += x * t;
                                gg += t * t;
                            }
                        }
                        ValCrop {
                            at: s.crater,
                            slope_deg: mean_slope_deg(s),
                            network_scale: rendered_scale(l, &hapke).unwrap_or(0.0),
                            ll,
                            lg,
                            gg,
                        }
                    })
                    .collect();
                val.extend(crops);
            }
        },
    )?;
    if val.is_empty() {
        bail!(
            "{}: the val split is empty: nothing to choose the crater level on",
            source.describe()
        );
    }
    // The bands are disjoint, so each crop's error depends on its own band's weight only: each band's weight is
    // chosen on its own crops, and the split's error is the network's plus each band's change.
    let network_sse: f64 = val.iter().map(|c| c.sse(1.0)).sum();
    let (mut bands, mut candidates, mut chosen_sse) = (Vec::new(), Vec::new(), network_sse);
    for regression in regressions {
        let inside: Vec<&ValCrop> = val
            .iter()
            .filter(|c| c.at.is_some_and(|at| regression.covers(at.rho)))
            .collect();
        let band_network: f64 = inside.iter().map(|c| c.sse(1.0)).sum();
        let level_oracle: f64 = inside.iter().map(|c| c.sse(c.best_factor())).sum();
        let mut best = (f64::INFINITY, 0.0);
        for weight in CANDIDATE_WEIGHTS {
            let band = BandLevel {
                regression: regression.clone(),
                weight,
                val_level_oracle_sse_ratio: f64::NAN,
            };
            let sse: f64 = inside
                .iter()
                .map(|c| {
                    let at = c.at.as_ref().expect("inside a band");
                    c.sse(band.factor(at, c.slope_deg, c.network_scale))
                })
                .sum();
            candidates.push(CandidateScore {
                rho_min: regression.rho_min,
                rho_max: regression.rho_max,
                weight,
                crops_in_band: inside.len(),
                band_sse_ratio: if band_network > 0.0 {
                    sse / band_network
                } else {
                    1.0
                },
                val_sse_ratio: (network_sse - band_network + sse) / network_sse,
            });
            // Ties keep the smaller weight (weight 0 first): the network's level unless moving it helps.
            if sse < best.0 {
                best = (sse, weight);
            }
        }
        chosen_sse += best.0 - band_network;
        bands.push(BandLevel {
            regression,
            weight: best.1,
            val_level_oracle_sse_ratio: if band_network > 0.0 {
                level_oracle / band_network
            } else {
                1.0
            },
        });
    }
    let level = CraterLevel {
        version: CRATER_LEVEL_VERSION,
        bands,
        val_crops: val.len(),
        val_crops_framed: val.iter().filter(|c| c.at.is_some()).count(),
        val_sse_ratio: chosen_sse / network_sse,
        candidates,
    };
    Ok(CraterLevelFit {
        level,
        train_crops_read: read,
        train_crops_framed: framed,
    })
}

/// The fit's Markdown: each band's regression and chosen weight, then every candidate's validation score.
pub fn markdown(fit: &CraterLevelFit) -> String {
    let level = &fit.level;
    let mut text = format!(
        "# Crater level\n\nTrain crops read: {} ({} with a crater frame). Chosen on {} validation crops ({} \
         framed): the split's summed squared error is **{:.4}** × the network's alone.\n\n\
         ln(scale) = c0 + c1·step + c2·slope/30° + c3·ρ, step = logistic((height against the profile − centre) / width)\n\n\
         | ρ band | train crops | RMS residual (ln) | c0 | c1 | c2 | c3 | step centre, width (m) | chosen weight | \
         band SSE with each crop's best level (peeks) / network's |\n\
         |---|---|---|---|---|---|---|---|---|---|\n",
        fit.train_crops_read,
        fit.train_crops_framed,
        level.val_crops,
        level.val_crops_framed,
        level.val_sse_ratio,
    );
    for band in &level.bands {
        let r = &band.regression;
        text.push_str(&format!(
            "| {}–{} | {} | {:.3} | {:.4} | {:.4} | {:.4} | {:.4} | {:.0}, {:.0} | {} | {:.4} |\n",
            r.rho_min,
            r.rho_max,
            r.train_crops,
            r.train_rms_log,
            r.coefficients[0],
            r.coefficients[1],
            r.coefficients[2],
            r.coefficients[3],
            r.step_centre_m,
            r.step_width_m,
            band.weight,
            band.val_level_oracle_sse_ratio
        ));
    }
    text.push_str(
        "\n| ρ band | weight | val crops in band | band SSE / network's | val SSE / network's |\n|---|---|---|---|---|\n",
    );
    for c in &level.candidates {
        text.push_str(&format!(
            "| {}–{} | {} | {} | {:.4} | {:.4} |\n",
            c.rho_min, c.rho_max, c.weight, c.crops_in_band, c.band_sse_ratio, c.val_sse_ratio
        ));
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The scale an H1 rendering shows is its per-pixel scale's mean over the pixels Hapke lights; the best uniform
    /// scale of a truth that is Hapke times a constant is that constant; the validation SSE of a scaled rendering
    /// is the direct sum.
    #[test]
    fn scales_and_the_sufficient_statistics_agree_with_direct_sums() {
        let hapke = [0.1, 0.2, 0.0, 0.4];
        let scales = [0.5, 0.7, 9.0, 0.9];
        let rendered: Vec<f64> = hapke.iter().zip(&scales).map(|(h, m)| h * m).collect();
        let shown = rendered_scale(&rendered, &hapke).unwrap();
        assert!(
            (shown - (0.5 + 0.7 + 0.9) / 3.0).abs() < 1e-12,
            "the dark pixel shows nothing"
        );
        let truth: Vec<f64> = hapke.iter().map(|h| 0.37 * h).collect();
        let s = best_uniform_scale(&hapke, &truth, &[true; 4]).unwrap();
        assert!((s - 0.37).abs() < 1e-12);
        assert!(best_uniform_scale(&[0.0; 4], &truth, &[true; 4]).is_none());
        let (ll, lg, gg) = rendered
            .iter()
            .zip(&truth)
            .fold((0.0, 0.0, 0.0), |(a, b, c), (l, g)| {
                (a + l * l, b + l * g, c + g * g)
            });
        let crop = ValCrop {
            at: None,
            slope_deg: 0.0,
            network_scale: shown,
            ll,
            lg,
            gg,
        };
        let k = 1.3;
        let direct: f64 = rendered
            .iter()
            .zip(&truth)
            .map(|(l, g)| (k * l - g).powi(2))
            .sum();
        assert!((crop.sse(k) - direct).abs() < 1e-15);
    }
}

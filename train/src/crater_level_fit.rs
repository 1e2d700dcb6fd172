//! Fitting a run's [`crate::crater_level`] (`crater-level`, `fit --crater-level`), beside the run it scores: the
//! passes over a dataset: zones of ρ grown and their regressions fitted on the train split (no network), then how
//! many zones to keep and every zone's weight chosen on the validation split with the run's network, from each
//! crop's sufficient statistics.

use std::collections::BTreeMap;

use anyhow::{bail, Result};
use dataset::contract::crater_frame::{CraterPosition, PROFILE_RHO_MAX};
use dataset::contract::schema::{Split, CROP_PX};
use dataset::science::brdf::BrdfModel;
use dataset::science::hapke::HapkeParams;
use rayon::prelude::*;

use crate::baseline::{hapke_render, truth_and_valid};
use crate::crater_level::{
    best_uniform_scale, grow_zones, rendered_scale, BandLevel, CandidateScore, CraterLevel,
    GroundScore, LevelRegression, TrainCrop, ZoneCountScore, CANDIDATE_WEIGHTS,
    CRATER_LEVEL_VERSION, MAX_ZONES, MIN_ZONE_TRAIN_CROPS,
};
use crate::data::{for_each_sample_group, mean_slope_deg, SampleSource};
use crate::evaluation::TerrainMap;
use crate::kernels::TrainOps;
use crate::prediction::predict_ensemble;
use crate::run_dir::TrainedRun;

/// One validation crop's sufficient statistics: for a factor k on the learned rendering L, its squared error is
/// k²·ll − 2k·lg + gg.
#[derive(Debug, Clone)]
struct ValCrop {
    at: Option<CraterPosition>,
    /// Its kind of ground (class and unit) from the world's terrain classes, when the fit has them.
    ground: Option<String>,
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

/// Grow the zones and fit their regressions on the train split (no network), score every partition and weight on
/// the validation split with the run's network, and return the best (lowest validation SSE). With `terrain` (the
/// world's classes) no kind of ground may end above the network's validation error. Refuses a dataset without
/// crater frames and a run that is not H1.
pub fn fit_crater_level<B: TrainOps>(
    run: &TrainedRun<B>,
    source: &dyn SampleSource,
    options: &CraterLevelOptions,
    terrain: Option<&TerrainMap>,
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
    // The frame's own reach: past it a crop's position is clamped to the profile's end.
    let reach = PROFILE_RHO_MAX;
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
    let partitions = grow_zones(&train, reach, MAX_ZONES);
    if partitions.is_empty() {
        bail!(
            "{}: fewer than {MIN_ZONE_TRAIN_CROPS} train crops lie within {reach} radii of a catalogued crater: nothing to fit a crater level on",
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
                            ground: terrain.map(|t| {
                                t.ground_at(s.center_x_m, s.center_y_m)
                                    .map_or_else(|| "unknown".to_string(), |g| g.label())
                            }),
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
    let network_sse: f64 = val.iter().map(|c| c.sse(1.0)).sum();
    let guarded = terrain.is_some();
    let mut best: Option<(usize, WeightChoice)> = None;
    let mut zone_counts = Vec::new();
    for (k, zones) in partitions.iter().enumerate() {
        let choice = choose_weights(zones, &val);
        zone_counts.push(ZoneCountScore {
            zones: zones.len(),
            edges: zones[1..].iter().map(|z| z.rho_min).collect(),
            val_sse_ratio: choice.sse / network_sse,
            guard_bound: guarded && choice.guard_bound,
        });
        // Fewer zones first, so a tie keeps the smaller partition.
        if best.as_ref().is_none_or(|(_, b)| choice.sse < b.sse) {
            best = Some((k, choice));
        }
    }
    let (kept, choice) = best.expect("at least one partition");
    let zones = &partitions[kept];
    let mut candidates = Vec::new();
    let mut bands = Vec::new();
    for (z, regression) in zones.iter().enumerate() {
        let inside: Vec<&ValCrop> = val
            .iter()
            .filter(|c| c.at.is_some_and(|at| regression.covers(at.rho)))
            .collect();
        let band_network: f64 = inside.iter().map(|c| c.sse(1.0)).sum();
        let ratio = |sse: f64| {
            if band_network > 0.0 {
                sse / band_network
            } else {
                1.0
            }
        };
        for (w, &weight) in CANDIDATE_WEIGHTS.iter().enumerate() {
            let sse: f64 = choice.zone_sse[z][w].iter().sum();
            candidates.push(CandidateScore {
                rho_min: regression.rho_min,
                rho_max: regression.rho_max,
                weight,
                crops_in_band: inside.len(),
                band_sse_ratio: ratio(sse),
                val_sse_ratio: (network_sse - band_network + sse) / network_sse,
            });
        }
        let level_oracle: f64 = inside.iter().map(|c| c.sse(c.best_factor())).sum();
        bands.push(BandLevel {
            regression: regression.clone(),
            weight: CANDIDATE_WEIGHTS[choice.weights[z]],
            val_level_oracle_sse_ratio: ratio(level_oracle),
        });
    }
    let ground_guard = if guarded {
        ground_scores(&CraterLevel::from_bands(bands.clone()), &val)
    } else {
        Vec::new()
    };
    let level = CraterLevel {
        version: CRATER_LEVEL_VERSION,
        bands,
        val_crops: val.len(),
        val_crops_framed: val.iter().filter(|c| c.at.is_some()).count(),
        val_sse_ratio: choice.sse / network_sse,
        candidates,
        zone_counts,
        ground_guard,
    };
    Ok(CraterLevelFit {
        level,
        train_crops_read: read,
        train_crops_framed: framed,
    })
}

/// The weights chosen for one partition: an index into [`CANDIDATE_WEIGHTS`] per zone, the validation split's
/// summed squared error with them, and each zone's error per weight and kind of ground (for the candidate table).
struct WeightChoice {
    weights: Vec<usize>,
    sse: f64,
    /// `zone_sse[zone][weight][ground]`: the zone's validation crops of that ground, at that weight.
    zone_sse: Vec<Vec<Vec<f64>>>,
    /// Whether keeping every kind of ground at or below the network's error changed the weights.
    guard_bound: bool,
}

/// Choose each zone's weight by the validation split's summed squared error, holding every kind of ground the
/// crops carry (all one kind without the world's classes) at or below the network's error there. The zones are
/// disjoint, so each zone's best weight alone is the answer when it keeps every ground; otherwise every
/// combination is tried (at most 5⁸), and the best that keeps them wins. Weight 0 everywhere is the network and
/// always keeps them, so there is always an answer. Ties keep the smaller weights.
fn choose_weights(zones: &[LevelRegression], val: &[ValCrop]) -> WeightChoice {
    let mut grounds = BTreeMap::<Option<&str>, usize>::new();
    for c in val {
        let next = grounds.len();
        grounds.entry(c.ground.as_deref()).or_insert(next);
    }
    // Each zone at each candidate weight, built once.
    let levels: Vec<Vec<BandLevel>> = zones
        .iter()
        .map(|zone| {
            CANDIDATE_WEIGHTS
                .iter()
                .map(|&weight| BandLevel {
                    regression: zone.clone(),
                    weight,
                    val_level_oracle_sse_ratio: f64::NAN,
                })
                .collect()
        })
        .collect();
    let mut zone_sse = vec![vec![vec![0.0; grounds.len()]; CANDIDATE_WEIGHTS.len()]; zones.len()];
    let mut outside = 0.0;
    for c in val {
        let g = grounds[&c.ground.as_deref()];
        let zone =
            c.at.as_ref()
                .and_then(|at| zones.iter().position(|z| z.covers(at.rho)).map(|z| (z, at)));
        let Some((z, at)) = zone else {
            outside += c.sse(1.0);
            continue;
        };
        for (w, level) in levels[z].iter().enumerate() {
            zone_sse[z][w][g] += c.sse(level.factor(at, c.slope_deg, c.network_scale));
        }
    }
    let total = |weights: &[usize]| -> f64 {
        outside
            + weights
                .iter()
                .enumerate()
                .map(|(z, &w)| zone_sse[z][w].iter().sum::<f64>())
                .sum::<f64>()
    };
    // A ground's change against weight 0 (the network's own error there, summed the same way).
    let keeps_every_ground = |weights: &[usize]| -> bool {
        (0..grounds.len()).all(|g| {
            weights
                .iter()
                .enumerate()
                .map(|(z, &w)| zone_sse[z][w][g] - zone_sse[z][0][g])
                .sum::<f64>()
                <= 0.0
        })
    };
    let alone: Vec<usize> = zone_sse
        .iter()
        .map(|by_weight| {
            let sums: Vec<f64> = by_weight.iter().map(|g| g.iter().sum()).collect();
            // The first of the lowest: weight 0 unless moving helps.
            (0..sums.len()).fold(0, |best, w| if sums[w] < sums[best] { w } else { best })
        })
        .collect();
    let (weights, guard_bound) = if keeps_every_ground(&alone) {
        (alone, false)
    } else {
        let mut best = (vec![0; zones.len()], total(&vec![0; zones.len()]));
        let mut weights = vec![0; zones.len()];
        // Every combination, counting up from all zeros (so a tie keeps the first, smaller, weights).
        'combinations: loop {
            let mut z = 0;
            loop {
                if z == zones.len() {
                    break 'combinations;
                }
                weights[z] += 1;
                if weights[z] < CANDIDATE_WEIGHTS.len() {
                    break;
                }
                weights[z] = 0;
                z += 1;
            }
            if keeps_every_ground(&weights) {
                let sse = total(&weights);
                if sse < best.1 {
                    best = (weights.clone(), sse);
                }
            }
        }
        (best.0, true)
    };
    WeightChoice {
        sse: total(&weights),
        weights,
        zone_sse,
        guard_bound,
    }
}

/// Each kind of ground's validation error with `level` applied over the network's alone.
fn ground_scores(level: &CraterLevel, val: &[ValCrop]) -> Vec<GroundScore> {
    let mut sums = BTreeMap::<&str, (usize, f64, f64)>::new();
    for c in val {
        let entry = sums
            .entry(c.ground.as_deref().unwrap_or("unknown"))
            .or_default();
        entry.0 += 1;
        entry.1 += c.sse(level.factor(c.at.as_ref(), c.slope_deg, c.network_scale));
        entry.2 += c.sse(1.0);
    }
    sums.into_iter()
        .map(|(ground, (n, with, without))| GroundScore {
            ground: ground.to_string(),
            val_crops: n,
            val_sse_ratio: if without > 0.0 { with / without } else { 1.0 },
        })
        .collect()
}

/// The fit's Markdown: each band's regression and chosen weight, then every candidate's validation score.
pub fn markdown(fit: &CraterLevelFit) -> String {
    let level = &fit.level;
    let mut text = format!(
        "# Crater level\n\nTrain crops read: {} ({} with a crater frame). Chosen on {} validation crops ({} \
         framed): the split's summed squared error is **{:.4}** × the network's alone.\n\n\
         ln(scale) = c0 + c1·step + c2·slope/30° + c3·ρ, step = logistic((height against the profile − centre) / width)\n\n\
         | ρ zone | train crops | RMS residual (ln) | c0 | c1 | c2 | c3 | step centre, width (m) | chosen weight | \
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
            "| {:.3}–{:.3} | {} | {:.3} | {:.4} | {:.4} | {:.4} | {:.4} | {:.1}, {:.1} | {} | {:.4} |\n",
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
            "| {:.3}–{:.3} | {} | {} | {:.4} | {:.4} |\n",
            c.rho_min, c.rho_max, c.weight, c.crops_in_band, c.band_sse_ratio, c.val_sse_ratio
        ));
    }
    text.push_str(
        "\nZones grown on train crops, each partition with its own weights chosen on validation:\n\n\
         | zones | inner edges (ρ) | val SSE / network's | held back by the ground guard |\n|---|---|---|---|\n",
    );
    for z in &level.zone_counts {
        let edges: Vec<String> = z.edges.iter().map(|e| format!("{e:.3}")).collect();
        text.push_str(&format!(
            "| {} | {} | {:.4} | {} |\n",
            z.zones,
            edges.join(", "),
            z.val_sse_ratio,
            if z.guard_bound { "yes" } else { "no" }
        ));
    }
    if !level.ground_guard.is_empty() {
        text.push_str(
            "\nBy kind of ground (the world's terrain classes), validation:\n\n\
             | ground | val crops | SSE with the level / network's |\n|---|---|---|\n",
        );
        for g in &level.ground_guard {
            text.push_str(&format!(
                "| {} | {} | {:.4} |\n",
                g.ground, g.val_crops, g.val_sse_ratio
            ));
        }
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
            ground: None,
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

    /// A validation crop in a zone at ρ, of a ground, whose error is least at factor `best` on the network's
    /// rendering, with `mass` as its size.
    fn crop(rho: f64, ground: Option<&str>, best: f64, mass: f64) -> ValCrop {
        ValCrop {
            at: Some(CraterPosition {
                rho,
                relative_height_m: 0.0,
                relief_to_diameter: None,
            }),
            ground: ground.map(str::to_string),
            slope_deg: 0.0,
            network_scale: 0.5,
            ll: mass,
            lg: mass * best,
            gg: mass * (best * best + 0.01),
        }
    }

    /// Lowering the level helps the big ground A and hurts ground B in the inner zone, and helps A alone in the
    /// outer one. Without grounds both zones move all the way; with them the inner zone keeps the network's level
    /// and the outer still moves. Both answers equal the best of every pair of weights found by direct sums here,
    /// the second among the pairs that leave no ground worse.
    #[test]
    fn the_weights_leave_no_ground_worse_than_the_network() {
        let zone = |lo, hi| {
            crate::testing::constant_crater_level(lo, hi, 0.4, 1.0)
                .bands
                .remove(0)
                .regression
        };
        let zones = [zone(0.0, 1.0), zone(1.0, 3.0)];
        let with_grounds = |named: bool| -> Vec<ValCrop> {
            let g = |name| named.then_some(name);
            vec![
                crop(0.5, g("A"), 0.8, 10.0),
                crop(0.6, g("B"), 1.0, 1.0),
                crop(2.0, g("A"), 0.8, 3.0),
                crop(4.0, g("B"), 1.3, 2.0), // beyond the zones: the network's
            ]
        };
        // Direct sums: each crop's error at its zone's factor (0.4 / 0.5)^weight, by ground.
        let brute = |val: &[ValCrop], guarded: bool| -> [usize; 2] {
            let mut best = ([0, 0], f64::INFINITY);
            for w0 in 0..CANDIDATE_WEIGHTS.len() {
                for w1 in 0..CANDIDATE_WEIGHTS.len() {
                    let k = |c: &ValCrop| {
                        let rho = c.at.unwrap().rho;
                        let w = if rho < 1.0 {
                            w0
                        } else if rho < 3.0 {
                            w1
                        } else {
                            return 1.0;
                        };
                        0.8f64.powf(CANDIDATE_WEIGHTS[w])
                    };
                    let worse = ["A", "B"].iter().any(|g| {
                        let of_g = val.iter().filter(|c| c.ground.as_deref() == Some(g));
                        of_g.clone().map(|c| c.sse(k(c))).sum::<f64>()
                            > of_g.map(|c| c.sse(1.0)).sum::<f64>() + 1e-12
                    });
                    let sse: f64 = val.iter().map(|c| c.sse(k(c))).sum();
                    if !(guarded && worse) && sse < best.1 - 1e-12 {
                        best = ([w0, w1], sse);
                    }
                }
            }
            best.0
        };
        let free = with_grounds(false);
        let choice = choose_weights(&zones, &free);
        assert_eq!(choice.weights, brute(&free, false));
        assert_eq!(choice.weights, vec![4, 4], "both zones move all the way");
        assert!(!choice.guard_bound);
        let named = with_grounds(true);
        let choice = choose_weights(&zones, &named);
        assert_eq!(choice.weights, brute(&named, true));
        assert_eq!(
            choice.weights,
            vec![0, 4],
            "the inner zone keeps the network's level"
        );
        assert!(choice.guard_bound);
        let direct: f64 = named
            .iter()
            .map(|c| {
                c.sse(if c.at.unwrap().rho >= 1.0 && c.at.unwrap().rho < 3.0 {
                    0.8
                } else {
                    1.0
                })
            })
            .sum();
        assert!((choice.sse - direct).abs() < 1e-12);
        let mut level = CraterLevel::from_bands(
            zones
                .iter()
                .zip(&choice.weights)
                .map(|(r, &w)| BandLevel {
                    regression: r.clone(),
                    weight: CANDIDATE_WEIGHTS[w],
                    val_level_oracle_sse_ratio: f64::NAN,
                })
                .collect(),
        );
        let scores = ground_scores(&level, &named);
        assert_eq!(scores.len(), 2);
        assert!(scores.iter().all(|g| g.val_sse_ratio <= 1.0), "{scores:?}");
        assert!(scores[0].val_sse_ratio < 1.0, "A gains");
        level.bands[0].weight = 1.0;
        assert!(
            ground_scores(&level, &named)[1].val_sse_ratio > 1.0,
            "unguarded, B loses"
        );
    }
}

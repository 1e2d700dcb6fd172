//! True terrain: fBm background + power-law crater population with simple-crater morphology and diffusion
//! degradation, plus an optional Tycho-like complex crater. Also produces the per-cell *freshness* and *melt*
//! maps that drive the true reflectance (bright fresh ejecta, dark melt floors).

use rand::Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::config::{ComplexCraterConfig, ComplexCraterPopulation, TerrainConfig};
use super::geologic_units::Units;
use super::noise::{smoothstep, Fbm};
use super::Grid;
use crate::rng::{keyed_rng, keyed_u64};
use dataset::contract::world::TerrainClass;

/// One crater of the catalogue written to `truth/craters.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Crater {
    /// Centre, map metres.
    pub x_m: f64,
    pub y_m: f64,
    pub diameter_m: f64,
    /// 0 = formed now, 1 = as old as the oldest surface.
    pub age: f64,
    /// Diffusion length applied to its profile, metres.
    pub diffusion_m: f64,
    /// 1 for pristine material, decaying with age (optical maturity).
    pub freshness: f64,
}

/// Sample the crater population over the scene (plus a margin, so craters just outside still throw ejecta in).
pub fn crater_catalogue(cfg: &TerrainConfig, grid: &Grid, units: &Units, seed: u64) -> Vec<Crater> {
    let mut rng = keyed_rng(seed, "crater-catalogue", 0);
    let margin = 1.5 * cfg.crater_max_diameter_m;
    let (x0, x1) = (grid.min_x - margin, grid.max_x() + margin);
    let (y0, y1) = (grid.min_y() - margin, grid.max_y + margin);
    let area_km2 = (x1 - x0) * (y1 - y0) / 1e6;
    // N(>D) = K·D_km^s per km², truncated to [D_min, D_max]: sample D by inverting the truncated Pareto CDF.
    let s = cfg.sfd_cumulative_slope;
    let n_above = |d_m: f64| cfg.density_per_km2_above_1km * (d_m / 1000.0).powf(s) * area_km2;
    let expected = n_above(cfg.crater_min_diameter_m) - n_above(cfg.crater_max_diameter_m);
    let count = expected.round() as usize;
    let (a, b) = (
        cfg.crater_min_diameter_m.powf(s),
        cfg.crater_max_diameter_m.powf(s),
    );
    let mut craters: Vec<Crater> = (0..count)
        .filter_map(|_| {
            let u: f64 = rng.random();
            let diameter_m = (a + u * (b - a)).powf(1.0 / s);
            let age: f64 = rng.random();
            let (x_m, y_m) = (rng.random_range(x0..x1), rng.random_range(y0..y1));
            // The mare flood buried what formed before it: an old crater survives with the probability that its
            // site is highland.
            let survives: f64 = rng.random();
            (age <= cfg.mare_flood_age || survives < units.highland(x_m, y_m)).then(|| Crater {
                x_m,
                y_m,
                diameter_m,
                age,
                diffusion_m: cfg.max_diffusion_length_m * age.sqrt(),
                // Optical maturity is reached quickly: only the youngest ~10 % stay bright.
                freshness: (1.0 - age).powi(16),
            })
        })
        .collect();
    // Oldest first: younger craters are stamped over older ones.
    craters.sort_by(|p, q| q.age.total_cmp(&p.age));
    craters
}

/// Radial profile of a simple crater (height change, m) at normalised radius ρ = r/R, degraded by diffusion.
///
/// Fresh: parabolic bowl from the floor (−(d − h_rim)) to the rim crest (+h_rim) at ρ = 1, ejecta blanket
/// h_rim·ρ⁻³ outside, tapered to 0 by ρ = 3. Degradation with relative diffusion length σ = L/R lowers the rim
/// and depth (≈ the Gaussian-smoothed profile's amplitudes) and rounds the rim.
pub fn simple_crater_profile(rho: f64, depth_m: f64, rim_m: f64, sigma_rel: f64) -> f64 {
    let depth_keep = (-2.0 * sigma_rel * sigma_rel).exp();
    let rim_keep = (-6.0 * sigma_rel * sigma_rel).exp();
    let (d, h) = (depth_m * depth_keep, rim_m * rim_keep);
    // Rim rounding: blend the two sides over a width ∝ σ around ρ = 1.
    let width = (0.15 + sigma_rel).min(0.8);
    let inside = h - d * (1.0 - rho * rho).max(0.0);
    let outside = h * rho.max(1.0).powi(-3) * ejecta_taper(rho);
    let t = smoothstep(1.0 - width * 0.5, 1.0 + width * 0.5, rho);
    let blended = inside * (1.0 - t) + outside * t;
    if rho <= 1.0 - width * 0.5 {
        inside
    } else if rho >= 1.0 + width * 0.5 {
        outside
    } else {
        blended
    }
}

/// Where a crater's ejecta ends: 1 inside ρ = 2.4, falling smoothly (C¹) to 0 at ρ = 3 and 0 beyond. Heights and
/// freshness both fade with it, so neither ends in a step that no topography explains (world v3).
pub fn ejecta_taper(rho: f64) -> f64 {
    smoothstep(3.0, 2.4, rho)
}

/// Freshness a fresh simple crater lends its surface at normalised radius ρ: all of it inside the rim (ρ ≤ 1.1),
/// then rays of ejecta (`rays`, the azimuthal modulation) thinning like the blanket, ∝ ρ⁻³, and tapered to 0 by
/// ρ = 3.
pub fn simple_ejecta_freshness(rho: f64, rays: f64) -> f64 {
    if rho <= 1.1 {
        1.0
    } else {
        (1.1 / rho).powi(3) * rays * ejecta_taper(rho)
    }
}

/// Freshness of the complex crater's material at normalised radius ρ: its floor (ρ < `floor_rho`, where melt
/// covers it) 0.3, the wall 1, the ejecta ∝ ρ⁻² tapered to 0 by ρ = 3.
pub fn complex_crater_freshness(rho: f64, floor_rho: f64) -> f64 {
    if rho < floor_rho {
        0.3
    } else if rho <= 1.0 {
        1.0
    } else {
        rho.powi(-2) * ejecta_taper(rho)
    }
}

/// Background fBm heights for every fine cell; mare plains are smoother and lie `mare_depth_m` lower.
pub fn background(
    cfg: &TerrainConfig,
    grid: &Grid,
    units: &Units,
    base_height_m: f64,
    seed: u64,
) -> Vec<f32> {
    let fbm = Fbm {
        key: keyed_u64(seed, "terrain-fbm", 0),
        hurst: cfg.hurst,
        amplitude: cfg.fbm_amplitude_m,
        largest_wavelength_m: cfg.fbm_largest_wavelength_m,
        smallest_wavelength_m: 2.0 * grid.gsd_m,
    };
    let mut heights = vec![0f32; grid.width * grid.height];
    heights
        .par_chunks_mut(grid.width)
        .enumerate()
        .for_each(|(row, out)| {
            for (col, h) in out.iter_mut().enumerate() {
                let (x, y) = grid.center(col, row);
                let highland = units.highland(x, y);
                let relief = cfg.mare_relief_factor + (1.0 - cfg.mare_relief_factor) * highland;
                *h = (base_height_m - cfg.mare_depth_m * (1.0 - highland) + relief * fbm.at(x, y))
                    as f32;
            }
        });
    heights
}

/// Stamp craters in age order onto heights, and record freshness (0..1) of the surface material.
/// `first_index` is the catalogue index of `craters[0]` (keys each crater's ray pattern).
pub fn stamp_craters(
    cfg: &TerrainConfig,
    grid: &Grid,
    craters: &[Crater],
    first_index: usize,
    heights: &mut [f32],
    freshness: &mut [f32],
    seed: u64,
) {
    for (offset, crater) in craters.iter().enumerate() {
        let k = first_index + offset;
        let radius = crater.diameter_m / 2.0;
        let depth = cfg.depth_to_diameter * crater.diameter_m;
        let rim = cfg.rim_height_to_diameter * crater.diameter_m;
        let sigma_rel = crater.diffusion_m / radius;
        let reach = 3.0 * radius;
        let Some((c0, c1, r0, r1)) = grid.window(crater.x_m, crater.y_m, reach) else {
            continue;
        };
        // Ray pattern of fresh ejecta: brightness modulated by azimuth.
        let ray_phase = keyed_u64(seed, "crater-rays", k as u64) as f64 / u64::MAX as f64
            * std::f64::consts::TAU;
        let ray_count = 5.0 + (k % 7) as f64;
        for row in r0..r1 {
            for col in c0..c1 {
                let (x, y) = grid.center(col, row);
                let (dx, dy) = (x - crater.x_m, y - crater.y_m);
                let rho = (dx * dx + dy * dy).sqrt() / radius;
                if rho >= 3.0 {
                    continue;
                }
                let i = row * grid.width + col;
                heights[i] += simple_crater_profile(rho, depth, rim, sigma_rel) as f32;
                if crater.freshness > 1e-3 {
                    // Excavated material inside and on the rim; rays of ejecta outside, thinning like the blanket.
                    let rays = 0.6 + 0.4 * (ray_count * dy.atan2(dx) + ray_phase).sin();
                    let weight = simple_ejecta_freshness(rho, rays);
                    let f = crater.freshness * weight;
                    let prev = freshness[i] as f64;
                    freshness[i] = (prev * (1.0 - weight) + f).clamp(0.0, 1.0) as f32;
                } else if rho <= 1.0 {
                    // An old crater's impact resets nothing bright, but its interior overturns older fresh material.
                    freshness[i] *= 0.5;
                }
            }
        }
    }
}

/// Normalised radius of the complex crater's flat melt floor.
pub const COMPLEX_FLOOR_RHO: f64 = 0.45;

/// A complex crater placed in a world: its centre (map metres) and its shape.
#[derive(Debug, Clone)]
pub struct PlacedComplexCrater {
    pub center: (f64, f64),
    pub shape: ComplexCraterConfig,
}

/// Draw a world's complex craters (keyed by the seed, so the same config and seed place the same ones): count,
/// log-uniform diameters, terraces and degradation, and centres uniform over the area where the whole crater
/// (rim included) lies on the world, at least `min_separation_radii` summed radii from every crater placed before
/// (the largest are placed first).
/// Refuses a population it cannot place in 1,000 tries a crater, naming the fields to change.
pub fn draw_complex_craters(
    population: &ComplexCraterPopulation,
    world_center: (f64, f64),
    world_size_m: (f64, f64),
    seed: u64,
) -> Result<Vec<PlacedComplexCrater>, String> {
    let p = population;
    let mut rng = keyed_rng(seed, "complex-craters", 0);
    let count = rng.random_range(p.count_min..=p.count_max);
    let mut shapes: Vec<(f64, u32, f64)> = (0..count)
        .map(|_| {
            let diameter_m = (p.diameter_min_m.ln()
                + rng.random::<f64>() * (p.diameter_max_m / p.diameter_min_m).ln())
            .exp();
            let terraces = rng.random_range(p.terraces_min..=p.terraces_max);
            (
                diameter_m,
                terraces,
                rng.random::<f64>() * p.degradation_max,
            )
        })
        .collect();
    // The largest first: they need the most room, which the smaller ones then fit around.
    shapes.sort_by(|a, b| b.0.total_cmp(&a.0));
    let mut placed: Vec<PlacedComplexCrater> = Vec::new();
    for (diameter_m, terraces, degradation) in shapes {
        let radius = diameter_m / 2.0;
        let (half_w, half_h) = (world_size_m.0 / 2.0 - radius, world_size_m.1 / 2.0 - radius);
        let center = (0..1000).find_map(|_| {
            let offset = (
                (2.0 * rng.random::<f64>() - 1.0) * half_w.max(0.0),
                (2.0 * rng.random::<f64>() - 1.0) * half_h.max(0.0),
            );
            let clear = placed.iter().all(|other| {
                let apart = (offset.0 + world_center.0 - other.center.0)
                    .hypot(offset.1 + world_center.1 - other.center.1);
                apart >= p.min_separation_radii * (radius + other.shape.diameter_m / 2.0)
            });
            clear.then_some(offset)
        });
        let Some((east, north)) = center else {
            return Err(format!(
                "complex_craters: no room for crater {} of {count} ({diameter_m:.0} m) in 1000 tries: lower count_max, diameter_max_m or min_separation_radii",
                placed.len() + 1
            ));
        };
        placed.push(PlacedComplexCrater {
            center: (world_center.0 + east, world_center.1 + north),
            shape: ComplexCraterConfig {
                diameter_m,
                offset_east_m: east,
                offset_north_m: north,
                depth_to_diameter: p.depth_to_diameter,
                terraces,
                degradation,
            },
        });
    }
    Ok(placed)
}

/// Per cell of `grid`: the terrain class code ([`TerrainClass`], by normalised radius from the nearest complex
/// crater in `complex` = (centre, radius) pairs, nearest in radii; plains where there is none) and the highland
/// fraction. Written as `truth/terrain_class.tif` for evaluation.
pub fn terrain_classes(
    grid: &Grid,
    units: &Units,
    complex: &[((f64, f64), f64)],
) -> (Vec<f32>, Vec<f32>) {
    let mut class = vec![0f32; grid.width * grid.height];
    let mut highland = vec![0f32; grid.width * grid.height];
    class
        .par_chunks_mut(grid.width)
        .zip(highland.par_chunks_mut(grid.width))
        .enumerate()
        .for_each(|(row, (class_row, highland_row))| {
            for col in 0..grid.width {
                let (x, y) = grid.center(col, row);
                let rho = complex
                    .iter()
                    .map(|&((cx, cy), radius)| (x - cx).hypot(y - cy) / radius)
                    .reduce(f64::min);
                class_row[col] = TerrainClass::at_radius(rho, COMPLEX_FLOOR_RHO).code() as f32;
                highland_row[col] = units.highland(x, y) as f32;
            }
        });
    (class, highland)
}

/// Stamp a complex crater: terraced wall, flat melt floor with hummocks, central peak, raised rim and ejecta.
/// Marks its melt floor in `melt` and its ejecta as fresh as its degradation leaves them. `index` keys its
/// hummocks (0 for a world's first).
#[allow(clippy::too_many_arguments)]
pub fn stamp_complex_crater(
    cc: &ComplexCraterConfig,
    index: u64,
    grid: &Grid,
    center: (f64, f64),
    heights: &mut [f32],
    freshness: &mut [f32],
    melt: &mut [f32],
    seed: u64,
) {
    let radius = cc.diameter_m / 2.0;
    // Degradation fills the floor, wears the rim down and rounds the terraces (exact no-ops at 0: a fresh crater
    // is what world v3 stamped).
    let worn = cc.degradation;
    let depth = cc.depth_to_diameter * cc.diameter_m * (1.0 - 0.6 * worn);
    let rim = 0.02 * cc.diameter_m * (1.0 - 0.7 * worn);
    let terrace_edge = 0.55 * (1.0 - worn);
    let fresh = 1.0 - worn;
    let floor_rho = COMPLEX_FLOOR_RHO;
    let hummocks = Fbm {
        key: keyed_u64(seed, "melt-hummocks", index),
        hurst: 0.7,
        amplitude: 0.01 * depth,
        largest_wavelength_m: 0.05 * cc.diameter_m,
        smallest_wavelength_m: 4.0 * grid.gsd_m,
    };
    let Some((c0, c1, r0, r1)) = grid.window(center.0, center.1, 3.0 * radius) else {
        return;
    };
    let terraces = cc.terraces.max(1) as f64;
    heights[r0 * grid.width..r1 * grid.width]
        .par_chunks_mut(grid.width)
        .zip(freshness[r0 * grid.width..r1 * grid.width].par_chunks_mut(grid.width))
        .zip(melt[r0 * grid.width..r1 * grid.width].par_chunks_mut(grid.width))
        .enumerate()
        .for_each(|(dr, ((h_row, f_row), m_row))| {
            let row = r0 + dr;
            for col in c0..c1 {
                let (x, y) = grid.center(col, row);
                let (dx, dy) = (x - center.0, y - center.1);
                let rho = (dx * dx + dy * dy).sqrt() / radius;
                if rho >= 3.0 {
                    continue;
                }
                let dh = if rho < floor_rho {
                    let peak = 0.35 * depth * (-(rho / 0.12).powi(2)).exp();
                    -depth + peak + hummocks.at(x, y)
                } else if rho <= 1.0 {
                    // Wall from the floor edge up to the rim, broken into flat-ish terraces (a soft staircase).
                    let t = (rho - floor_rho) / (1.0 - floor_rho);
                    let stairs = (t * terraces).floor()
                        + smoothstep(terrace_edge, 1.0, (t * terraces).fract());
                    let profile = (stairs / terraces).powf(1.3);
                    -depth + (depth + rim) * profile
                } else {
                    rim * rho.powi(-3) * ejecta_taper(rho)
                };
                h_row[col] += dh as f32;
                if rho < floor_rho {
                    m_row[col] = smoothstep(floor_rho, floor_rho - 0.05, rho) as f32;
                }
                f_row[col] =
                    f_row[col].max((fresh * complex_crater_freshness(rho, floor_rho)) as f32);
            }
        });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fresh_profile_has_configured_depth_and_rim() {
        let (depth, rim) = (20.0, 4.0);
        assert!((simple_crater_profile(0.0, depth, rim, 0.0) - (rim - depth)).abs() < 1e-12);
        assert!(
            (simple_crater_profile(1.0, depth, rim, 0.0) - rim).abs() < 0.3,
            "rim crest near ρ = 1"
        );
        assert!(
            (simple_crater_profile(2.0, depth, rim, 0.0) - rim / 8.0).abs() < 1e-12,
            "ejecta ∝ ρ⁻³"
        );
        assert_eq!(simple_crater_profile(3.1, depth, rim, 0.0), 0.0);
        // Heavily degraded craters are nearly erased.
        assert!(simple_crater_profile(0.0, depth, rim, 2.0).abs() < 0.01 * depth);
    }

    /// World v3: ejecta freshness (simple craters' rays, the complex crater's ρ⁻² blanket) falls continuously to
    /// 0 at ρ = 3 instead of stopping with a step (v2: 5 % and 11 % of the material's freshness, i.e. straight
    /// albedo edges with no topography under them). Checked on a fine sweep: no jump between neighbouring radii
    /// larger than the smooth profile's own slope allows, and nothing at or past the cutoff.
    #[test]
    fn ejecta_freshness_fades_to_zero_without_a_step() {
        let step = 1e-4;
        for (name, profile) in [
            (
                "simple",
                Box::new(|rho: f64| simple_ejecta_freshness(rho, 1.0)) as Box<dyn Fn(f64) -> f64>,
            ),
            (
                "complex",
                Box::new(|rho| complex_crater_freshness(rho, 0.45)),
            ),
        ] {
            assert_eq!(profile(3.0), 0.0, "{name}: zero at the cutoff");
            assert_eq!(profile(3.5), 0.0, "{name}: zero beyond it");
            assert!(
                profile(3.0 - step) < 1e-6,
                "{name}: {}",
                profile(3.0 - step)
            );
            // Outside the rim the profile is smooth: a step of 1e-4 in ρ moves it by far less than 1e-3.
            let mut rho = 1.2;
            while rho < 3.2 {
                let jump = (profile(rho + step) - profile(rho)).abs();
                assert!(jump < 1e-3, "{name}: jump {jump} at ρ = {rho}");
                rho += step;
            }
        }
        // Inside ρ = 2.4 the taper leaves the v2 profiles unchanged.
        assert_eq!(
            simple_ejecta_freshness(2.0, 0.8),
            (1.1f64 / 2.0).powi(3) * 0.8
        );
        assert_eq!(complex_crater_freshness(2.0, 0.45), 0.25);
        assert_eq!(complex_crater_freshness(0.2, 0.45), 0.3);
    }

    fn population(
        count: (u32, u32),
        diameters: (f64, f64),
        separation: f64,
    ) -> ComplexCraterPopulation {
        ComplexCraterPopulation {
            count_min: count.0,
            count_max: count.1,
            diameter_min_m: diameters.0,
            diameter_max_m: diameters.1,
            depth_to_diameter: 0.07,
            terraces_min: 2,
            terraces_max: 5,
            degradation_max: 0.8,
            min_separation_radii: separation,
        }
    }

    /// Over many seeds, a drawn population (the many-craters preset's) keeps every bound it states: the count, the diameters, terraces and
    /// degradation in range, each crater wholly on the world and at least the separation from every other; the
    /// same seed draws the same craters, and the seeds between them draw every count.
    #[test]
    fn drawn_complex_craters_keep_their_bounds_and_follow_the_seed() {
        let p = population((3, 4), (8_000.0, 14_000.0), 1.1);
        let (centre, size) = ((1000.0, -5000.0), (40_000.0, 40_000.0));
        let mut counts = std::collections::BTreeSet::new();
        for seed in 0..40 {
            let craters = draw_complex_craters(&p, centre, size, seed).unwrap();
            counts.insert(craters.len());
            assert!((3..=4).contains(&craters.len()));
            for (k, c) in craters.iter().enumerate() {
                let s = &c.shape;
                let radius = s.diameter_m / 2.0;
                assert!((8_000.0..=14_000.0).contains(&s.diameter_m), "{s:?}");
                assert!((2..=5).contains(&s.terraces) && (0.0..0.8).contains(&s.degradation));
                assert!((c.center.0 - centre.0).abs() + radius <= size.0 / 2.0 + 1e-6);
                assert!((c.center.1 - centre.1).abs() + radius <= size.1 / 2.0 + 1e-6);
                assert!((c.center.0 - centre.0 - s.offset_east_m).abs() < 1e-6);
                assert!((c.center.1 - centre.1 - s.offset_north_m).abs() < 1e-6);
                for other in &craters[..k] {
                    let apart = (c.center.0 - other.center.0).hypot(c.center.1 - other.center.1);
                    assert!(apart >= 1.1 * (radius + other.shape.diameter_m / 2.0));
                }
            }
            let again = draw_complex_craters(&p, centre, size, seed).unwrap();
            assert_eq!(format!("{craters:?}"), format!("{again:?}"));
        }
        assert_eq!(counts.into_iter().collect::<Vec<_>>(), vec![3, 4]);
    }

    /// A population that cannot fit is refused, naming the fields to change.
    #[test]
    fn a_population_with_no_room_is_refused() {
        let p = population((6, 6), (18_000.0, 18_000.0), 1.0);
        let err = draw_complex_craters(&p, (0.0, 0.0), (40_000.0, 40_000.0), 1).unwrap_err();
        assert!(
            err.contains("count_max") && err.contains("min_separation_radii"),
            "{err}"
        );
    }
}

//! Geologic units: where the surface is mare (dark, young, flooded basalt plains) and where highland (bright, old,
//! saturated with craters). One field drives both the terrain and the albedo, as on the Moon, where the two units
//! differ in topography as well as in reflectance: maria are smoother, lower and carry fewer craters because the
//! flood buried the older ones. That correlation is what lets a DEM-only model tell the units apart (docs/design.md, Synthetic world:
//! reflectance "correlated with morphology but not determined by it"); without it, the unit albedo would be a
//! ±20 % component no DEM could predict, far past the 5–10 % the design notes budget for.

use rayon::prelude::*;

use super::config::{ReflectanceConfig, UnitMapConfig};
use super::noise::smoothstep;
use super::noise::Fbm;
use super::Grid;
use crate::rng::keyed_u64;

pub struct Units {
    field: Fbm,
}

impl Units {
    pub fn new(cfg: &ReflectanceConfig, seed: u64) -> Self {
        Self {
            field: Fbm {
                key: keyed_u64(seed, "albedo-units", 0),
                hurst: 0.9,
                amplitude: 1.0,
                largest_wavelength_m: cfg.unit_wavelength_m,
                smallest_wavelength_m: cfg.unit_wavelength_m / 8.0,
            },
        }
    }

    /// 0 on mare, 1 on highland, with a soft boundary.
    pub fn highland(&self, x: f64, y: f64) -> f64 {
        smoothstep(-0.25, 0.25, self.field.at(x, y))
    }
}

/// The unit map a site delivers beside its DEM: the true units averaged over a `generalisation_m` square
/// (a map at its scale drops narrower features), moved by a smooth displacement of up to about `displacement_m`
/// (a boundary's positional error), then classed highland (1) where the average is at least one half, mare (0)
/// elsewhere, on `grid`. The unit is the surface material's, inside craters too: what a thresholded FeO map
/// (Clementine, Kaguya) gives, and what a geologic map gives where it maps a crater's floor and walls by the
/// ground they cut. Its own keyed stream, so it moves nothing else of the world.
pub fn unit_map(units: &Units, cfg: &UnitMapConfig, grid: &Grid, seed: u64) -> Vec<f32> {
    let warp = |axis: u64| Fbm {
        key: keyed_u64(seed, "unit-map-displacement", axis),
        hurst: 0.9,
        amplitude: cfg.displacement_m,
        largest_wavelength_m: cfg.displacement_wavelength_m,
        smallest_wavelength_m: cfg.displacement_wavelength_m / 4.0,
    };
    let (warp_x, warp_y) = (warp(0), warp(1));
    // A 5 × 5 stencil across the generalisation square: its mean is the box mean of a field whose shortest
    // wavelength (an eighth of the units' longest) the stencil's spacing still resolves at map scales.
    const STENCIL: usize = 5;
    let step = cfg.generalisation_m / STENCIL as f64;
    let mut map = vec![0f32; grid.width * grid.height];
    map.par_chunks_mut(grid.width)
        .enumerate()
        .for_each(|(row, out)| {
            for (col, value) in out.iter_mut().enumerate() {
                let (x, y) = grid.center(col, row);
                let (wx, wy) = (x + warp_x.at(x, y), y + warp_y.at(x, y));
                let mut sum = 0.0;
                for i in 0..STENCIL {
                    for j in 0..STENCIL {
                        let offset =
                            |k: usize| (k as f64 + 0.5) * step - cfg.generalisation_m / 2.0;
                        sum += units.highland(wx + offset(j), wy + offset(i));
                    }
                }
                *value = if sum / (STENCIL * STENCIL) as f64 >= 0.5 {
                    1.0
                } else {
                    0.0
                };
            }
        });
    map
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::config::tiny;

    fn map_config() -> UnitMapConfig {
        UnitMapConfig {
            gsd_m: 100.0,
            generalisation_m: 1000.0,
            displacement_m: 400.0,
            displacement_wavelength_m: 4000.0,
        }
    }

    fn grid() -> Grid {
        Grid {
            min_x: -10_000.0,
            max_y: 10_000.0,
            gsd_m: 100.0,
            width: 200,
            height: 200,
        }
    }

    /// The map is classes, mostly right, not the truth: a coarse, displaced copy misclasses a band along the
    /// boundaries and nowhere else, and the same seed gives the same map.
    #[test]
    fn the_unit_map_is_the_truth_generalised_and_displaced() {
        let cfg = tiny();
        let units = Units::new(&cfg.reflectance, 7);
        let (grid, map_cfg) = (grid(), map_config());
        let map = unit_map(&units, &map_cfg, &grid, 7);
        assert!(map.iter().all(|&v| v == 0.0 || v == 1.0));
        assert_eq!(map, unit_map(&units, &map_cfg, &grid, 7));
        let truth = |col: usize, row: usize| {
            let (x, y) = grid.center(col, row);
            units.highland(x, y) >= 0.5
        };
        let (mut wrong, mut both) = (0usize, [0usize; 2]);
        for row in 0..grid.height {
            for col in 0..grid.width {
                let mapped = map[row * grid.width + col] == 1.0;
                both[usize::from(mapped)] += 1;
                if mapped != truth(col, row) {
                    wrong += 1;
                    // Misclassed only near a true boundary: within the displacement's reach (its octaves sum to
                    // under 2.2 × the largest's amplitude) plus half the generalisation square's diagonal.
                    let reach = 2.2 * map_cfg.displacement_m + map_cfg.generalisation_m * 0.71;
                    let cells = (reach / grid.gsd_m).ceil() as isize;
                    let near_boundary = (-cells..=cells).any(|dr| {
                        (-cells..=cells).any(|dc| {
                            let (r, c) = (row as isize + dr, col as isize + dc);
                            (0..grid.height as isize).contains(&r)
                                && (0..grid.width as isize).contains(&c)
                                && truth(c as usize, r as usize) != truth(col, row)
                        })
                    });
                    assert!(
                        near_boundary,
                        "cell ({col}, {row}) misclassed far from any boundary"
                    );
                }
            }
        }
        let fraction_wrong = wrong as f64 / map.len() as f64;
        assert!(both[0] > 0 && both[1] > 0, "both units mapped: {both:?}");
        assert!(
            (0.02..0.3).contains(&fraction_wrong),
            "misclassed fraction {fraction_wrong}: a map's errors, neither none nor most"
        );
        // No displacement and a generalisation finer than the units' shortest wavelength: the truth's classes.
        let sharp = UnitMapConfig {
            displacement_m: 0.0,
            generalisation_m: 1.0,
            ..map_cfg
        };
        let exact = unit_map(&units, &sharp, &grid, 7);
        let agree = (0..grid.height)
            .flat_map(|row| (0..grid.width).map(move |col| (col, row)))
            .filter(|&(col, row)| (exact[row * grid.width + col] == 1.0) == truth(col, row))
            .count();
        assert!(
            agree as f64 > 0.995 * exact.len() as f64,
            "{agree} of {}",
            exact.len()
        );
    }
}

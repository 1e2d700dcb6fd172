//! Geologic units: where the surface is mare (dark, young, flooded basalt plains) and where highland (bright, old,
//! saturated with craters). One field drives both the terrain and the albedo, as on the Moon, where the two units
//! differ in topography as well as in reflectance: maria are smoother, lower and carry fewer craters because the
//! flood buried the older ones. That correlation is what lets a DEM-only model tell the units apart (docs/design.md, Synthetic world:
//! reflectance "correlated with morphology but not determined by it"); without it, the unit albedo would be a
//! ±20 % component no DEM could predict, far past the 5–10 % the design notes budget for.

use super::config::ReflectanceConfig;
use super::noise::smoothstep;
use super::noise::Fbm;
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

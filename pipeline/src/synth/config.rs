//! World configuration, read from `manifests/world-*.toml` (every knob of the synthetic Moon lives there).

use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WorldConfig {
    pub world: WorldExtent,
    pub terrain: TerrainConfig,
    pub complex_crater: Option<ComplexCraterConfig>,
    /// Several complex craters drawn per world (sizes, places, terraces, degradation) instead of the one pinned
    /// by `[complex_crater]`: a model fitted on them sees more than one crater's wall and rim.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub complex_craters: Option<ComplexCraterPopulation>,
    pub reflectance: ReflectanceConfig,
    pub acquisitions: AcquisitionConfig,
    /// The acquisition count and the sun's incidence range drawn per world instead of fixed by `[acquisitions]`:
    /// worlds of one preset then differ in their lighting as they do in their craters.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub acquisition_draws: Option<AcquisitionDraws>,
    pub dem_product: DemProductConfig,
    /// A mare/highland unit map delivered beside the DEM (`map/units.tif`), as coarse and as misplaced as a real
    /// site's: without the section, none is written.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub unit_map: Option<UnitMapConfig>,
}

/// The delivered unit map ([`super::geologic_units::unit_map`]): the true units generalised and displaced, then
/// classed mare (0) or highland (1), as a geologic map's polygons or a thresholded FeO map give them.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UnitMapConfig {
    /// Cell size of the raster, metres.
    pub gsd_m: f64,
    /// Side of the square the true units are averaged over before classing: features narrower than about half
    /// of it are lost, as a map at its scale drops them.
    pub generalisation_m: f64,
    /// Amplitude of the smooth displacement of the whole map (the largest octave of an fBm warp), metres: a
    /// boundary's positional error.
    pub displacement_m: f64,
    /// Longest wavelength of the displacement, metres.
    pub displacement_wavelength_m: f64,
}

/// Bounds of a world's drawn acquisitions ([`WorldConfig::with_drawn_acquisitions`]); each draw is uniform.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AcquisitionDraws {
    /// Acquisitions, in `count_min..=count_max`: replaces `acquisitions.count`.
    pub count_min: usize,
    pub count_max: usize,
    /// The incidence range's low end, in `incidence_low_min_deg..=incidence_low_max_deg`, and its width, in
    /// `incidence_span_min_deg..=incidence_span_max_deg`: replace `acquisitions.incidence_min_deg` and
    /// `incidence_max_deg`.
    pub incidence_low_min_deg: f64,
    pub incidence_low_max_deg: f64,
    pub incidence_span_min_deg: f64,
    pub incidence_span_max_deg: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WorldExtent {
    pub name: String,
    /// Scene centre, planetocentric degrees (the map CRS is equirectangular, true scale at this latitude).
    pub center_lon_deg: f64,
    pub center_lat_deg: f64,
    pub width_m: f64,
    pub height_m: f64,
    /// Grid of the true (fine) DEM and reflectance maps.
    pub fine_gsd_m: f64,
    /// Grid of the delivered stereo-like DEM (an integer multiple of `fine_gsd_m`).
    pub dem_gsd_m: f64,
    /// Mean height of the scene above the 1737400 m sphere.
    pub base_height_m: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TerrainConfig {
    pub hurst: f64,
    /// Amplitude of the largest fBm octave, metres.
    pub fbm_amplitude_m: f64,
    pub fbm_largest_wavelength_m: f64,
    pub crater_min_diameter_m: f64,
    pub crater_max_diameter_m: f64,
    /// Exponent of the cumulative size–frequency distribution N(>D) ∝ D^slope (≈ −2 near equilibrium).
    pub sfd_cumulative_slope: f64,
    /// N(>1 km) per km² (density scale of the SFD).
    pub density_per_km2_above_1km: f64,
    /// Rim-to-floor depth over diameter of a fresh simple crater.
    pub depth_to_diameter: f64,
    /// Rim height over diameter (0.036–0.043 for fresh simple craters).
    pub rim_height_to_diameter: f64,
    /// Diffusion length of the oldest craters, metres: craters much smaller than this are erased.
    pub max_diffusion_length_m: f64,
    /// Relief of the background fBm on mare relative to highland (maria are smoother plains), 0..1.
    pub mare_relief_factor: f64,
    /// Craters older than this (crater age runs 0 = now .. 1 = oldest surface) predate the mare flood and are
    /// buried where they formed on mare, so maria carry fewer, fresher craters (see `synth::geologic_units`).
    pub mare_flood_age: f64,
    /// How far mare plains lie below highlands, metres.
    pub mare_depth_m: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ComplexCraterConfig {
    pub diameter_m: f64,
    /// Centre offset from the scene centre, metres (east, north).
    pub offset_east_m: f64,
    pub offset_north_m: f64,
    pub depth_to_diameter: f64,
    pub terraces: u32,
    /// 0 fresh .. 1 most degraded: shallower (−60 % depth), a lower rim (−70 %), softer terraces, and ejecta and
    /// wall no longer fresh. Absent in a `[complex_crater]` section: fresh.
    #[serde(default, skip_serializing_if = "is_fresh")]
    pub degradation: f64,
}

fn is_fresh(degradation: &f64) -> bool {
    *degradation == 0.0
}

/// The complex craters of one world, drawn from its seed ([`super::terrain::draw_complex_craters`]).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ComplexCraterPopulation {
    /// How many, drawn uniformly in `count_min..=count_max`.
    pub count_min: u32,
    pub count_max: u32,
    /// Rim diameters, drawn log-uniformly (more small craters than large), metres.
    pub diameter_min_m: f64,
    pub diameter_max_m: f64,
    /// Depth over diameter of a fresh one.
    pub depth_to_diameter: f64,
    /// Terrace count, drawn uniformly.
    pub terraces_min: u32,
    pub terraces_max: u32,
    /// Degradation, drawn uniformly in `0..degradation_max` ([`ComplexCraterConfig::degradation`]).
    pub degradation_max: f64,
    /// Centres at least this many summed radii apart (1: rims may touch).
    pub min_separation_radii: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReflectanceConfig {
    pub w_mare: f64,
    pub w_highland: f64,
    /// Wavelength of the mare/highland mixing pattern, metres.
    pub unit_wavelength_m: f64,
    /// Relative brightening of fresh ejecta and rims (0.2–1.0 = +20–100 %).
    pub fresh_brightening: f64,
    /// Relative brightening of slopes steeper than `steep_slope_deg`.
    pub steep_brightening: f64,
    pub steep_slope_deg: f64,
    /// Relative darkening of impact-melt floors.
    pub melt_darkening: f64,
    /// Amplitude of the albedo component no DEM can predict (0.05–0.10).
    pub independent_variation: f64,
    pub independent_wavelength_m: f64,
    pub b: f64,
    pub c: f64,
    pub b_s0: f64,
    pub h_s: f64,
    pub theta_bar_deg: f64,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AcquisitionConfig {
    pub count: usize,
    pub ortho_gsd_m: f64,
    pub strip_width_m: f64,
    /// Strip length as a fraction of the scene height (strips run roughly north–south, like polar-orbit NACs).
    pub strip_length_fraction: f64,
    pub max_heading_deg: f64,
    pub incidence_min_deg: f64,
    pub incidence_max_deg: f64,
    /// Share of slewed (off-nadir) acquisitions and their roll range.
    pub slewed_fraction: f64,
    pub slew_min_deg: f64,
    pub slew_max_deg: f64,
    pub altitude_m: f64,
    /// Amplitude of the irregular nodata border, metres.
    pub border_roughness_m: f64,
    /// Relative (shot-like) and absolute (read) noise, I/F units.
    pub noise_relative: f64,
    pub noise_absolute: f64,
    /// Elevation samples across the sun's disk for soft shadows.
    pub sun_disk_samples: usize,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DemProductConfig {
    /// Gaussian smoothing of the stereo product, in DEM pixels.
    pub smoothing_sigma_px: f64,
    pub noise_m: f64,
    /// Long-wavelength stereo error amplitude, metres.
    pub correlated_error_m: f64,
    pub correlated_error_wavelength_m: f64,
    /// Matching blunders (pits/spikes) and nodata holes.
    pub blunders: usize,
    pub holes: usize,
}

/// Built-in presets: the manifests shipped in `manifests/`, embedded so the binary works from anywhere.
pub fn preset(name: &str) -> Option<&'static str> {
    match name {
        "demo" => Some(include_str!("../../../manifests/world-demo.toml")),
        "tycho-full" => Some(include_str!("../../../manifests/world-tycho-full.toml")),
        "many-craters" => Some(include_str!("../../../manifests/world-many-craters.toml")),
        _ => None,
    }
}

/// A tiny world (4 × 4 km, three 2 km strips, no complex crater) that generates in seconds: for tests and smoke
/// runs of the pipeline.
pub fn tiny() -> WorldConfig {
    let mut cfg =
        WorldConfig::from_toml(preset("demo").expect("demo preset")).expect("demo preset parses");
    cfg.world.width_m = 4000.0;
    cfg.world.height_m = 4000.0;
    cfg.terrain.crater_max_diameter_m = 300.0;
    cfg.terrain.fbm_largest_wavelength_m = 2000.0;
    cfg.complex_crater = None;
    cfg.complex_craters = None;
    cfg.acquisition_draws = None;
    cfg.acquisitions.count = 3;
    cfg.acquisitions.strip_width_m = 2000.0;
    cfg
}

impl WorldConfig {
    pub fn from_toml(text: &str) -> Result<Self, toml::de::Error> {
        toml::from_str(text)
    }

    /// This config with `[acquisition_draws]` drawn for `seed` into `[acquisitions]` (count and incidence range),
    /// from its own keyed stream, so the draw moves nothing else of the world; without the section, itself.
    /// `world.json` echoes the drawn config, so a world's lighting is read off its manifest.
    pub fn with_drawn_acquisitions(&self, seed: u64) -> Self {
        use rand::Rng;
        let mut drawn = self.clone();
        if let Some(d) = &self.acquisition_draws {
            let mut rng = dataset::contract::rng::keyed_rng(seed, "world acquisition draws", 0);
            let a = &mut drawn.acquisitions;
            a.count = rng.random_range(d.count_min..=d.count_max);
            a.incidence_min_deg =
                rng.random_range(d.incidence_low_min_deg..=d.incidence_low_max_deg);
            a.incidence_max_deg = a.incidence_min_deg
                + rng.random_range(d.incidence_span_min_deg..=d.incidence_span_max_deg);
        }
        drawn
    }

    /// Reject configurations the generator can't honour, with the field to fix.
    pub fn validate(&self) -> Result<(), String> {
        let w = &self.world;
        let ratio = w.dem_gsd_m / w.fine_gsd_m;
        if (ratio - ratio.round()).abs() > 1e-9 || ratio < 1.0 {
            return Err(format!(
                "world.dem_gsd_m ({}) must be an integer multiple of world.fine_gsd_m ({})",
                w.dem_gsd_m, w.fine_gsd_m
            ));
        }
        if self.terrain.crater_min_diameter_m < 4.0 * w.fine_gsd_m {
            return Err("terrain.crater_min_diameter_m must be at least 4 fine pixels".into());
        }
        let t = &self.terrain;
        if !(0.0..=1.0).contains(&t.mare_relief_factor) || !(0.0..=1.0).contains(&t.mare_flood_age)
        {
            return Err(
                "terrain.mare_relief_factor and terrain.mare_flood_age must lie in [0, 1]".into(),
            );
        }
        if let Some(p) = &self.complex_craters {
            if self.complex_crater.is_some() {
                return Err("[complex_crater] pins one crater and [complex_craters] draws several: keep one of the two sections".into());
            }
            if p.count_min > p.count_max
                || !(p.diameter_min_m > 0.0 && p.diameter_min_m <= p.diameter_max_m)
                || p.terraces_min > p.terraces_max
                || !(0.0..=1.0).contains(&p.degradation_max)
                || !(p.depth_to_diameter > 0.0 && p.min_separation_radii >= 0.0)
            {
                return Err("complex_craters: need count_min ≤ count_max, 0 < diameter_min_m ≤ diameter_max_m, terraces_min ≤ terraces_max, degradation_max in [0, 1], a positive depth_to_diameter and min_separation_radii ≥ 0".into());
            }
            if p.diameter_max_m > w.width_m.min(w.height_m) {
                return Err("complex_craters.diameter_max_m must be at most the world's width and height: a crater must fit".into());
            }
        }
        if let Some(d) = &self.acquisition_draws {
            let ordered = |lo: f64, hi: f64| lo.is_finite() && hi.is_finite() && lo <= hi;
            let in_bounds = 1 <= d.count_min
                && d.count_min <= d.count_max
                && ordered(d.incidence_low_min_deg, d.incidence_low_max_deg)
                && ordered(d.incidence_span_min_deg, d.incidence_span_max_deg)
                && d.incidence_low_min_deg >= 0.0
                && d.incidence_span_min_deg >= 0.0
                && d.incidence_low_max_deg + d.incidence_span_max_deg < 90.0;
            if !in_bounds {
                return Err("acquisition_draws: need 1 ≤ count_min ≤ count_max, 0 ≤ incidence_low_min_deg ≤ incidence_low_max_deg, 0 ≤ incidence_span_min_deg ≤ incidence_span_max_deg, and incidence_low_max_deg + incidence_span_max_deg < 90 (sun above the horizon)".into());
            }
        }
        if let Some(m) = &self.unit_map {
            let positive = |v: f64| v.is_finite() && v > 0.0;
            if !(positive(m.gsd_m)
                && positive(m.generalisation_m)
                && positive(m.displacement_wavelength_m)
                && m.displacement_m.is_finite()
                && m.displacement_m >= 0.0)
            {
                return Err("unit_map: need positive gsd_m, generalisation_m and displacement_wavelength_m, and displacement_m ≥ 0".into());
            }
        }
        let a = &self.acquisitions;
        if !(0.0..90.0).contains(&a.incidence_min_deg)
            || a.incidence_max_deg >= 90.0
            || a.incidence_min_deg > a.incidence_max_deg
        {
            return Err("acquisitions.incidence_min_deg..incidence_max_deg must lie in [0, 90) (sun above the horizon)".into());
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn with_draws() -> WorldConfig {
        let mut cfg = tiny();
        cfg.acquisition_draws = Some(AcquisitionDraws {
            count_min: 2,
            count_max: 5,
            incidence_low_min_deg: 15.0,
            incidence_low_max_deg: 35.0,
            incidence_span_min_deg: 30.0,
            incidence_span_max_deg: 50.0,
        });
        cfg
    }

    #[test]
    fn a_world_without_acquisition_draws_keeps_its_acquisitions() {
        let cfg = tiny();
        let json = |c: &WorldConfig| serde_json::to_string(c).unwrap();
        assert_eq!(json(&cfg.with_drawn_acquisitions(7)), json(&cfg));
    }

    #[test]
    fn drawn_acquisitions_lie_in_their_bounds_reach_both_ends_and_follow_the_seed() {
        let cfg = with_draws();
        assert_eq!(cfg.validate(), Ok(()));
        let mut counts = std::collections::BTreeSet::new();
        let (mut lows, mut spans) = (Vec::new(), Vec::new());
        for seed in 0..200 {
            let a = cfg.with_drawn_acquisitions(seed).acquisitions;
            counts.insert(a.count);
            assert!(
                (15.0..=35.0).contains(&a.incidence_min_deg),
                "{}",
                a.incidence_min_deg
            );
            let span = a.incidence_max_deg - a.incidence_min_deg;
            assert!((30.0..=50.0).contains(&span), "{span}");
            lows.push(a.incidence_min_deg);
            spans.push(span);
        }
        // 200 uniform draws of 4 counts: each is missed with probability (3/4)^200 ≈ 1e-25.
        assert_eq!(counts.into_iter().collect::<Vec<_>>(), [2, 3, 4, 5]);
        // 200 uniform draws over 20° each: the smallest within 1° of the low end misses with probability
        // (19/20)^200 ≈ 3.5e-5, and likewise the largest of the high end.
        for (values, lo, hi) in [(&lows, 15.0, 35.0), (&spans, 30.0, 50.0)] {
            let smallest = values.iter().cloned().fold(f64::INFINITY, f64::min);
            let largest = values.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
            assert!(
                smallest < lo + 1.0 && largest > hi - 1.0,
                "{smallest} … {largest}"
            );
        }
        let a = |seed| {
            cfg.with_drawn_acquisitions(seed)
                .acquisitions
                .incidence_min_deg
        };
        assert_eq!(a(3), a(3));
        assert_ne!(a(3), a(4));
    }

    #[test]
    fn every_preset_parses_and_validates_and_many_craters_draws_its_lighting() {
        for name in ["demo", "tycho-full", "many-craters"] {
            let cfg = WorldConfig::from_toml(preset(name).unwrap()).unwrap();
            assert_eq!(cfg.validate(), Ok(()), "{name}");
            assert_eq!(
                cfg.acquisition_draws.is_some(),
                name == "many-craters",
                "{name}"
            );
        }
        let cfg = WorldConfig::from_toml(preset("many-craters").unwrap()).unwrap();
        let d = cfg.acquisition_draws.clone().unwrap();
        let a = cfg.with_drawn_acquisitions(42).acquisitions;
        assert!((d.count_min..=d.count_max).contains(&a.count));
        assert!((d.incidence_low_min_deg..=d.incidence_low_max_deg).contains(&a.incidence_min_deg));
    }

    #[test]
    fn acquisition_draws_out_of_bounds_are_refused_naming_the_section() {
        let bad = |edit: fn(&mut AcquisitionDraws)| {
            let mut cfg = with_draws();
            edit(cfg.acquisition_draws.as_mut().unwrap());
            cfg.validate().unwrap_err()
        };
        for err in [
            bad(|d| d.count_min = 0),
            bad(|d| d.count_max = 1),
            bad(|d| d.incidence_low_max_deg = 10.0),
            bad(|d| d.incidence_span_max_deg = 60.0),
        ] {
            assert!(err.contains("acquisition_draws"), "{err}");
        }
    }
}

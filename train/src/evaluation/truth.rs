//! The world's hidden truth maps (Hapke parameters, morphology albedo, the true DEM, terrain classes) sampled at a
//! crop's pixels: the oracle rows and the breakdown of errors by kind of ground.

use std::path::Path;

use anyhow::{bail, Result};
use dataset::contract::schema::{Sample, CROP_PX, DEM_PX};
use dataset::contract::world::TerrainClass;
use dataset::science::geometry::PixelGeometry;
use dataset::science::hapke::{hapke_i_over_f, HFunction, HapkeParams};
use dataset::science::raster::{read_bands, read_raster, Raster};

use super::model_form::ModelFormTable;

/// The world's true Hapke parameter maps (`truth/hapke_params.tif`: w, b, c, B_S0, h_S, θ̄ in degrees), and w
/// without its independent component (`truth/w_morphology.tif`, on the same grid) when the world has it.
pub struct TruthMaps {
    bands: Vec<Raster>,
    w_morphology: Option<Raster>,
    /// `truth/dem_true.tif`, for the oracle on the true DEM (worlds always carry it; tiny test worlds may not).
    true_dem: Option<Raster>,
    /// `truth/terrain_class.tif` (world v3 on).
    terrain: Option<TerrainMap>,
}

/// `truth/terrain_class.tif` (world v3 on): class code and highland fraction per delivered-DEM cell. Opened alone
/// where only the kind of ground is needed (`crater-level --world`), without the truth's large parameter maps.
pub struct TerrainMap {
    class: Raster,
    highland: Raster,
}

impl TerrainMap {
    /// The world's terrain classes; `None` for worlds generated before they were written (before v3).
    pub fn open(world: &Path) -> Result<Option<Self>> {
        let path = world.join(dataset::contract::world::TRUE_TERRAIN_CLASS);
        if !path.exists() {
            return Ok(None);
        }
        let mut bands = read_bands(&path)?;
        if bands.len() != 2 {
            bail!(
                "{}: {} bands, expected 2 (class, highland fraction); regenerate the world",
                path.display(),
                bands.len()
            );
        }
        let highland = bands.pop().expect("two bands");
        let class = bands.pop().expect("two bands");
        Ok(Some(Self { class, highland }))
    }

    /// The terrain class and highland fraction of the delivered-DEM cell holding (x, y); `None` outside it.
    pub fn ground_at(&self, x: f64, y: f64) -> Option<Ground> {
        let (col, row) = self.class.transform.map_to_pixel(x, y);
        let (col, row) = (col.round(), row.round());
        if col < 0.0
            || row < 0.0
            || col >= self.class.width as f64
            || row >= self.class.height as f64
        {
            return None;
        }
        let (col, row) = (col as usize, row as usize);
        Some(Ground {
            class: TerrainClass::from_code(self.class.get(col, row) as f64)?,
            highland: self.highland.get(col, row) as f64,
        })
    }
}

/// The ground under a crop's centre, from `truth/terrain_class.tif`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ground {
    pub class: TerrainClass,
    /// 0 mare, 1 highland.
    pub highland: f64,
}

/// The unit as reports name it: highland where the highland fraction is at least one half, else mare.
pub fn unit_name(highland: f64) -> &'static str {
    if highland >= 0.5 {
        "highland"
    } else {
        "mare"
    }
}

/// A kind of ground as reports label it: class and unit (`rim, highland`).
pub fn ground_label(class: &str, highland: f64) -> String {
    format!("{class}, {}", unit_name(highland))
}

impl Ground {
    /// Class and unit, as `eval`'s `terrain_class_and_unit` breakdown labels them.
    pub fn label(&self) -> String {
        ground_label(self.class.name(), self.highland)
    }
}

/// Which true albedo an oracle rendering uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TrueAlbedo {
    /// The albedo the orthos were rendered with.
    Full,
    /// Without the independent component (`truth/w_morphology.tif`).
    Morphology,
}

impl TruthMaps {
    pub fn open(world: &Path) -> Result<Self> {
        let path = world.join(dataset::contract::world::TRUE_HAPKE);
        if !path.exists() {
            bail!(
                "{}: missing: --world must be a synthetic world directory (g2r-pipeline synth --out) with truth/",
                path.display()
            );
        }
        let bands = read_bands(&path)?;
        if bands.len() != 6 {
            bail!(
                "{}: {} bands, expected 6 (w, b, c, B_S0, h_S, theta_bar_deg); regenerate the world",
                path.display(),
                bands.len()
            );
        }
        // Worlds generated before the morphology map existed have only the full oracle.
        let morphology_path = world.join(dataset::contract::world::TRUE_W_MORPHOLOGY);
        let w_morphology = if morphology_path.exists() {
            let morphology = read_bands(&morphology_path)?.remove(0);
            let full = &bands[0];
            if (morphology.width, morphology.height) != (full.width, full.height)
                || morphology.transform != full.transform
            {
                bail!(
                    "{}: not on the grid of {}: regenerate the world",
                    morphology_path.display(),
                    path.display()
                );
            }
            Some(morphology)
        } else {
            None
        };
        let true_dem_path = world.join(dataset::contract::world::TRUE_DEM);
        let true_dem = if true_dem_path.exists() {
            Some(read_raster(&true_dem_path)?)
        } else {
            None
        };
        let terrain = TerrainMap::open(world)?;
        Ok(Self {
            bands,
            w_morphology,
            true_dem,
            terrain,
        })
    }

    /// The terrain class and highland fraction of the delivered-DEM cell holding (x, y); `None` for worlds
    /// without `truth/terrain_class.tif` (before world v3) or outside it.
    pub fn ground_at(&self, x: f64, y: f64) -> Option<Ground> {
        self.terrain.as_ref()?.ground_at(x, y)
    }

    /// The sample with its DEM crop replaced by the true DEM averaged over the same 5 m cells (bilinear at each
    /// cell's centre: the mean of the 2 × 2 true cells when the grids nest, as the world's do): the delivered
    /// DEM's smoothing, noise, blunders and long-wavelength error removed, its resolution kept. `None` without
    /// the true DEM or where the crop leaves it.
    pub fn on_true_dem(&self, sample: &Sample) -> Option<Sample> {
        let dem = self.true_dem.as_ref()?;
        let grid = sample.crop_grid();
        let mut heights = Vec::with_capacity(DEM_PX * DEM_PX);
        for row in 0..DEM_PX {
            for col in 0..DEM_PX {
                let (dx, dy) = grid.map_offset(col, row, DEM_PX);
                let (c, r) = dem
                    .transform
                    .map_to_pixel(sample.center_x_m + dx, sample.center_y_m + dy);
                if c < 0.0 || r < 0.0 || c > dem.width as f64 - 1.0 || r > dem.height as f64 - 1.0 {
                    return None;
                }
                let h = dem.bilinear(c, r);
                if !h.is_finite() {
                    return None;
                }
                heights.push(h);
            }
        }
        Some(Sample {
            dem_m: heights,
            ..sample.clone()
        })
    }

    /// Parameters at map point (x, y), bilinear; `None` outside the maps or on nodata (or when `albedo` asks
    /// for a map the world does not have).
    pub fn params_at(&self, x: f64, y: f64, albedo: TrueAlbedo) -> Option<HapkeParams> {
        let first = &self.bands[0];
        let (col, row) = first.transform.map_to_pixel(x, y);
        // Bilinear sampling clamps at the edges: points beyond the outer pixel edges are outside the maps.
        if col < -0.5
            || row < -0.5
            || col > first.width as f64 - 0.5
            || row > first.height as f64 - 0.5
        {
            return None;
        }
        let mut v: Vec<f64> = self
            .bands
            .iter()
            .map(|b| b.bilinear(col, row) as f64)
            .collect();
        if albedo == TrueAlbedo::Morphology {
            v[0] = self.w_morphology.as_ref()?.bilinear(col, row) as f64;
        }
        v.iter().all(|x| x.is_finite()).then(|| HapkeParams {
            w: v[0],
            b: v[1],
            c: v[2],
            b_s0: v[3],
            h_s: v[4],
            theta_bar_rad: v[5].to_radians(),
            porosity_k: 1.0,
        })
    }

    /// Whether the world carries the morphology albedo (the `oracle_morphology` method).
    pub fn has_morphology(&self) -> bool {
        self.w_morphology.is_some()
    }

    /// The material parameters the model-form fits hold fixed (c, B_S0, h_S, θ̄), when they are the same across
    /// the maps (sampled at the centre and the four quadrants' centres), as the generator writes them; `None`
    /// otherwise, and then no model-form oracle is drawn.
    pub fn fixed_material(&self) -> Option<HapkeParams> {
        let first = &self.bands[0];
        let probe = |fx: f64, fy: f64| {
            let (x, y) = first
                .transform
                .pixel_center(fx * first.width as f64, fy * first.height as f64);
            self.params_at(x, y, TrueAlbedo::Full)
        };
        let centre = probe(0.5, 0.5)?;
        for (fx, fy) in [(0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)] {
            let p = probe(fx, fy)?;
            let same = |a: f64, b: f64| (a - b).abs() <= 1e-6 * a.abs().max(1.0);
            if !(same(p.c, centre.c)
                && same(p.b_s0, centre.b_s0)
                && same(p.h_s, centre.h_s)
                && same(p.theta_bar_rad, centre.theta_bar_rad))
            {
                return None;
            }
        }
        Some(centre)
    }

    /// I/F of a crop under `table`'s model with, at each pixel, the best geometry-blind coefficients for the true
    /// (w, b) there ([`ModelFormTable`]); NaN outside the maps.
    pub fn render_model_form(&self, sample: &Sample, table: &ModelFormTable) -> Vec<f64> {
        self.render_with(sample, TrueAlbedo::Full, |p, g| {
            table
                .model
                .visible_terms(&g.cosines, &g.half_diff)
                .map_or(0.0, |terms| {
                    table
                        .coefficients(p.w, p.b)
                        .iter()
                        .zip(terms)
                        .map(|(c, t)| c * t)
                        .sum::<f64>()
                })
        })
    }

    /// I/F of a crop under the true maps (lit fraction × Hapke); pixels outside the maps render NaN.
    pub fn render(&self, sample: &Sample, albedo: TrueAlbedo) -> Vec<f64> {
        self.render_with(sample, albedo, |p, g| {
            let c = &g.cosines;
            hapke_i_over_f(p, c.cos_i, c.cos_e, c.cos_g, HFunction::Hapke2002)
        })
    }

    /// Lit fraction × `reflect(true parameters, geometry)` at each pixel of a crop; NaN outside the maps.
    fn render_with(
        &self,
        sample: &Sample,
        albedo: TrueAlbedo,
        reflect: impl Fn(&HapkeParams, &PixelGeometry) -> f64,
    ) -> Vec<f64> {
        let grid = sample.crop_grid();
        sample
            .pixel_geometry()
            .iter()
            .zip(&sample.sun_lit)
            .enumerate()
            .map(|(k, (g, &lit))| {
                let (dx, dy) = grid.map_offset(k % CROP_PX, k / CROP_PX, CROP_PX);
                self.params_at(sample.center_x_m + dx, sample.center_y_m + dy, albedo)
                    .map_or(f64::NAN, |p| lit as f64 * reflect(&p, g))
            })
            .collect()
    }
}

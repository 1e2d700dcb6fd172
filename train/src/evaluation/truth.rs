//! The world's hidden truth maps (Hapke parameters, morphology albedo) sampled at a crop's pixels: the oracle rows.

use std::path::Path;

use anyhow::{bail, Result};
use dataset::hapke::{hapke_i_over_f, HFunction, HapkeParams};
use dataset::raster::{read_bands, Raster};
use dataset::schema::{Sample, CROP_PX};

/// The world's true Hapke parameter maps (`truth/hapke_params.tif`: w, b, c, B_S0, h_S, θ̄ in degrees), and w
/// without its independent component (`truth/w_morphology.tif`, on the same grid) when the world has it.
pub struct TruthMaps {
    bands: Vec<Raster>,
    w_morphology: Option<Raster>,
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
        let path = world.join(dataset::world::TRUE_HAPKE);
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
        let morphology_path = world.join(dataset::world::TRUE_W_MORPHOLOGY);
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
        Ok(Self {
            bands,
            w_morphology,
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

    /// I/F of a crop under the true maps (lit fraction × Hapke); pixels outside the maps render NaN.
    pub fn render(&self, sample: &Sample, albedo: TrueAlbedo) -> Vec<f64> {
        let grid = sample.crop_grid();
        sample
            .pixel_geometry()
            .iter()
            .zip(&sample.sun_lit)
            .enumerate()
            .map(|(k, (g, &lit))| {
                let (dx, dy) = grid.map_offset(k % CROP_PX, k / CROP_PX, CROP_PX);
                let c = &g.cosines;
                self.params_at(sample.center_x_m + dx, sample.center_y_m + dy, albedo)
                    .map_or(f64::NAN, |p| {
                        lit as f64
                            * hapke_i_over_f(&p, c.cos_i, c.cos_e, c.cos_g, HFunction::Hapke2002)
                    })
            })
            .collect()
    }
}

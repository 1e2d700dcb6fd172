//! A real crater catalogue's errors, simulated, so that a network that learns from crater frames learns to expect
//! them. A published catalogue lists a crater's centre a few hundred metres off and its diameter a few per cent
//! off, misses some craters and lists some that are not there (Robbins 2018 gives the spread between its
//! analysts). A network trained only on a world's exact catalogue reads the frame as exact, and loses more than
//! it gains on a real site.
//!
//! The project stage frames each sample with one of several draws of the catalogue ([`FramedCatalogue`]), the
//! draw chosen by the sample's id: crops of one crater see its frame placed differently, and crops whose crater
//! a draw misses see the nearest other one, or none within reach. Every draw comes from a stream keyed by the
//! dataset's seed, the draw and the crater's place in the catalogue, so one crater's fate never shifts another's.

use std::path::Path;

use anyhow::{bail, Context, Result};
use rand::Rng;
use rand_distr::{Distribution, Normal, Poisson};

use super::crater_frame::{read_catalogue, CatalogueCrater, CraterFrames, CraterPosition};
use super::rng::{draw_at, keyed_rng, keyed_u64};
use crate::science::crs::LocalFrame;
use crate::science::raster::Raster;

/// How a simulated catalogue differs from the truth it was drawn from (`project.crater_catalogue_error` in a
/// pipeline manifest; the dataset manifest records it with the catalogue).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CatalogueError {
    /// Standard deviation of a listed centre's offset from the true one, along each ground axis (east, north),
    /// metres.
    pub centre_sd_m: f64,
    /// Standard deviation of ln(listed diameter / true diameter): 0.05 lists one crater in three more than 5 %
    /// off.
    pub diameter_log_sd: f64,
    /// Probability that a draw leaves a crater out.
    pub missed_fraction: f64,
    /// Craters listed that are not there, per draw over the DEM (the mean of a Poisson count): each at a uniform
    /// place on the DEM, as wide as a catalogued crater that frames.
    pub false_craters: f64,
    /// Draws of the catalogue; each sample is framed by one.
    pub draws: usize,
}

impl CatalogueError {
    /// A one-line reason when a field is out of range.
    pub fn validate(&self) -> std::result::Result<(), String> {
        let ok = self.centre_sd_m.is_finite()
            && self.centre_sd_m >= 0.0
            && self.diameter_log_sd.is_finite()
            && self.diameter_log_sd >= 0.0
            && (0.0..1.0).contains(&self.missed_fraction)
            && self.false_craters.is_finite()
            && self.false_craters >= 0.0;
        if !ok {
            return Err(format!(
                "centre_sd_m = {}, diameter_log_sd = {}, missed_fraction = {}, false_craters = {}: use standard \
                 deviations ≥ 0, a missed fraction in [0, 1) and a mean count of false craters ≥ 0",
                self.centre_sd_m, self.diameter_log_sd, self.missed_fraction, self.false_craters
            ));
        }
        if !(1..=1000).contains(&self.draws) {
            return Err(format!(
                "draws = {}: use 1 to 1000 draws of the catalogue",
                self.draws
            ));
        }
        Ok(())
    }

    /// Draw `draw` of `catalogue` as a catalogue with these errors would list it over `dem`: true craters moved,
    /// rescaled or left out, in catalogue order, then the false ones. Craters whose listed diameter falls under
    /// `min_diameter_m` frame nothing, so they are kept where the truth has them, unmoved (a global catalogue
    /// holds a million of them, and moving one costs a projection).
    pub fn draw(
        &self,
        dem: &Raster,
        catalogue: &[CatalogueCrater],
        min_diameter_m: f64,
        seed: u64,
        draw: u64,
    ) -> Result<Vec<CatalogueCrater>> {
        let centre = Normal::new(0.0, self.centre_sd_m)?;
        let log_scale = Normal::new(0.0, self.diameter_log_sd)?;
        let purpose = format!("crater catalogue error, draw {draw}");
        let mut listed = Vec::with_capacity(catalogue.len());
        for (index, crater) in catalogue.iter().enumerate() {
            let mut rng = keyed_rng(seed, &purpose, index as u64);
            let missed = rng.random::<f64>() < self.missed_fraction;
            let (east_m, north_m) = (centre.sample(&mut rng), centre.sample(&mut rng));
            let diameter_m = crater.diameter_m * log_scale.sample(&mut rng).exp();
            if missed {
                continue;
            }
            if diameter_m < min_diameter_m {
                listed.push(CatalogueCrater {
                    diameter_m,
                    ..*crater
                });
                continue;
            }
            let (x, y) = dem.crs.from_lonlat_deg(crater.lon_deg, crater.lat_deg)?;
            let offset = LocalFrame::new(&dem.crs, x, y, 0.0)?.en_to_map(east_m, north_m);
            let (lon_deg, lat_deg) = dem.crs.to_lonlat_deg(x + offset.x, y + offset.y)?;
            listed.push(CatalogueCrater {
                lon_deg,
                lat_deg,
                diameter_m,
            });
        }
        let framing: Vec<f64> = catalogue
            .iter()
            .map(|c| c.diameter_m)
            .filter(|&d| d >= min_diameter_m)
            .collect();
        if self.false_craters > 0.0 && !framing.is_empty() {
            let mut rng = keyed_rng(seed, "crater catalogue false craters", draw);
            let count = Poisson::new(self.false_craters)?.sample(&mut rng) as usize;
            let (x0, y0, x1, y1) = dem.transform.bounds(dem.width, dem.height);
            for _ in 0..count {
                let (x, y) = (rng.random_range(x0..x1), rng.random_range(y0..y1));
                let (lon_deg, lat_deg) = dem.crs.to_lonlat_deg(x, y)?;
                listed.push(CatalogueCrater {
                    lon_deg,
                    lat_deg,
                    diameter_m: framing[rng.random_range(0..framing.len())],
                });
            }
        }
        Ok(listed)
    }
}

/// The frames a dataset's samples are placed in: the catalogue's own, or, with a [`CatalogueError`], each of its
/// draws, one per sample.
pub struct FramedCatalogue {
    draws: Vec<CraterFrames>,
    /// Keys which draw frames a sample; `None` with the catalogue's own frames.
    draw_key: Option<u64>,
}

impl FramedCatalogue {
    /// The catalogue file's frames over `dem` ([`CraterFrames::from_catalogue`]: a catalogue that frames nothing
    /// is refused), or with `error`, the frames of each of its draws. A draw may frame nothing (every crater
    /// missed): its samples are unframed, as crops far from any listed crater are.
    pub fn new(
        dem: &Raster,
        catalogue: &Path,
        min_diameter_m: f64,
        error: Option<&CatalogueError>,
        seed: u64,
    ) -> Result<Self> {
        let own = CraterFrames::from_catalogue(dem, catalogue, min_diameter_m)?;
        let Some(error) = error else {
            return Ok(Self {
                draws: vec![own],
                draw_key: None,
            });
        };
        if let Err(reason) = error.validate() {
            bail!(
                "{}: project.crater_catalogue_error: {reason}",
                catalogue.display()
            );
        }
        let craters = read_catalogue(catalogue)?;
        let mut draws = Vec::with_capacity(error.draws);
        let (mut framed, mut empty) = (0, 0);
        for draw in 0..error.draws as u64 {
            let listed = error.draw(dem, &craters, min_diameter_m, seed, draw)?;
            let (frames, report) = CraterFrames::new(dem, &listed, min_diameter_m)
                .with_context(|| format!("{}: draw {draw} of its errors", catalogue.display()))?;
            framed += report.framed;
            empty += usize::from(frames.is_empty());
            draws.push(frames);
        }
        tracing::info!(
            draws = error.draws,
            mean_framed = framed as f64 / error.draws as f64,
            draws_framing_nothing = empty,
            "crater catalogue with simulated errors"
        );
        Ok(Self {
            draws,
            draw_key: Some(keyed_u64(seed, "crater catalogue draw of a sample", 0)),
        })
    }

    /// Which draw frames the sample `sample_id`: a function of the id alone, so the same sample gets the same
    /// frame whatever the thread or partition that projects it.
    pub fn draw_of(&self, sample_id: &str) -> usize {
        match self.draw_key {
            None => 0,
            Some(key) => {
                let id = blake3::hash(sample_id.as_bytes());
                let index = u64::from_le_bytes(id.as_bytes()[..8].try_into().expect("8 bytes"));
                (draw_at(key, index) % self.draws.len() as u64) as usize
            }
        }
    }

    /// The sample's crop at map `(x, y)` with mean height `crop_mean_m` in the frame of its draw
    /// ([`CraterFrames::position`]); `None` when that draw frames nothing.
    pub fn position(
        &self,
        sample_id: &str,
        x: f64,
        y: f64,
        crop_mean_m: f64,
    ) -> Option<CraterPosition> {
        self.draws[self.draw_of(sample_id)].position(x, y, crop_mean_m)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::science::crs::LunarCrs;
    use crate::science::raster::GeoTransform;

    /// A flat 40 km square DEM at 100 m on an equator-true equirectangular map.
    fn flat_dem() -> Raster {
        let transform = GeoTransform::north_up(-20_000.0, 20_000.0, 100.0);
        Raster::new(
            400,
            400,
            transform,
            LunarCrs::equirectangular(0.0, 0.0),
            -1000.0,
        )
    }

    /// `n` craters of 2–4 km on a grid over the DEM.
    fn catalogue(dem: &Raster, n: usize) -> Vec<CatalogueCrater> {
        (0..n)
            .map(|i| {
                let (x, y) = (
                    -15_000.0 + 1500.0 * (i % 20) as f64,
                    -15_000.0 + 1500.0 * (i / 20) as f64,
                );
                let (lon_deg, lat_deg) = dem.crs.to_lonlat_deg(x, y).unwrap();
                CatalogueCrater {
                    lon_deg,
                    lat_deg,
                    diameter_m: 2000.0 + 100.0 * (i % 21) as f64,
                }
            })
            .collect()
    }

    fn error(
        centre_sd_m: f64,
        diameter_log_sd: f64,
        missed: f64,
        false_craters: f64,
    ) -> CatalogueError {
        CatalogueError {
            centre_sd_m,
            diameter_log_sd,
            missed_fraction: missed,
            false_craters,
            draws: 1,
        }
    }

    /// Ground (east, north) metres from `a` to `b` on this map (equator-true: one map metre is one ground metre
    /// near the equator).
    fn offset_m(dem: &Raster, a: &CatalogueCrater, b: &CatalogueCrater) -> (f64, f64) {
        let pa = dem.crs.from_lonlat_deg(a.lon_deg, a.lat_deg).unwrap();
        let pb = dem.crs.from_lonlat_deg(b.lon_deg, b.lat_deg).unwrap();
        (pb.0 - pa.0, pb.1 - pa.1)
    }

    #[test]
    fn without_errors_a_draw_lists_the_catalogue_as_it_is() {
        let dem = flat_dem();
        let truth = catalogue(&dem, 40);
        let listed = error(0.0, 0.0, 0.0, 0.0)
            .draw(&dem, &truth, 1000.0, 7, 0)
            .unwrap();
        assert_eq!(listed.len(), truth.len());
        for (t, l) in truth.iter().zip(&listed) {
            let (e, n) = offset_m(&dem, t, l);
            assert!(e.hypot(n) < 1e-6, "moved {e} m east, {n} m north");
            assert_eq!(t.diameter_m, l.diameter_m);
        }
    }

    #[test]
    fn centre_and_diameter_errors_have_the_stated_spread() {
        // 400 craters × 5 draws = 2000 offsets per axis: the sample sd is within 1.6 % (1σ) of the true one, so
        // 6 % is 3.8σ; the sample mean within 300/√2000 = 6.7 m (1σ), so 30 m is 4.5σ.
        let dem = flat_dem();
        let truth = catalogue(&dem, 400);
        let e = error(300.0, 0.05, 0.0, 0.0);
        let (mut offsets, mut log_scales) = (Vec::new(), Vec::new());
        for draw in 0..5 {
            let listed = e.draw(&dem, &truth, 1000.0, 11, draw).unwrap();
            assert_eq!(listed.len(), truth.len());
            for (t, l) in truth.iter().zip(&listed) {
                let (east, north) = offset_m(&dem, t, l);
                offsets.extend([east, north]);
                log_scales.push((l.diameter_m / t.diameter_m).ln());
            }
        }
        let (mean, sd) = mean_sd(&offsets);
        assert!(mean.abs() < 30.0, "mean offset {mean} m");
        assert!((sd / 300.0 - 1.0).abs() < 0.06, "offset sd {sd} m");
        let (mean, sd) = mean_sd(&log_scales);
        assert!(mean.abs() < 0.005, "mean log scale {mean}");
        assert!((sd / 0.05 - 1.0).abs() < 0.08, "log scale sd {sd}");
    }

    fn mean_sd(values: &[f64]) -> (f64, f64) {
        let n = values.len() as f64;
        let mean = values.iter().sum::<f64>() / n;
        let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
        (mean, var.sqrt())
    }

    #[test]
    fn a_missed_crater_leaves_every_other_craters_draw_as_it_was() {
        let dem = flat_dem();
        let truth = catalogue(&dem, 400);
        let all = error(300.0, 0.05, 0.0, 0.0)
            .draw(&dem, &truth, 1000.0, 3, 2)
            .unwrap();
        let some = error(300.0, 0.05, 0.1, 0.0)
            .draw(&dem, &truth, 1000.0, 3, 2)
            .unwrap();
        // 400 craters at 10 %: 40 missed, binomial sd 6; 3.3σ either way.
        let missed = all.len() - some.len();
        assert!((20..=60).contains(&missed), "{missed} of 400 missed");
        // The survivors are a subsequence of the complete draw, unchanged.
        let mut rest = all.iter();
        for listed in &some {
            assert!(
                rest.any(|c| c == listed),
                "{listed:?} is not in the complete draw"
            );
        }
    }

    #[test]
    fn false_craters_lie_on_the_dem_as_wide_as_a_framing_crater_with_the_stated_mean_count() {
        let dem = flat_dem();
        let truth = catalogue(&dem, 40);
        let min_diameter_m = 3000.0;
        let framing: Vec<f64> = truth
            .iter()
            .map(|c| c.diameter_m)
            .filter(|&d| d >= min_diameter_m)
            .collect();
        let e = error(0.0, 0.0, 0.0, 2.0);
        let (x0, y0, x1, y1) = dem.transform.bounds(dem.width, dem.height);
        let mut count = 0;
        // 500 draws of a Poisson(2) count: the mean is within √(2/500) = 0.063 (1σ) of 2; 0.25 is 4σ.
        for draw in 0..500 {
            let listed = e.draw(&dem, &truth, min_diameter_m, 5, draw).unwrap();
            assert_eq!(&listed[..truth.len()], &truth[..]);
            for false_crater in &listed[truth.len()..] {
                let (x, y) = dem
                    .crs
                    .from_lonlat_deg(false_crater.lon_deg, false_crater.lat_deg)
                    .unwrap();
                assert!((x0..x1).contains(&x) && (y0..y1).contains(&y));
                assert!(framing.contains(&false_crater.diameter_m));
                count += 1;
            }
        }
        let mean = count as f64 / 500.0;
        assert!(
            (mean - 2.0).abs() < 0.25,
            "mean false craters per draw {mean}"
        );
    }

    #[test]
    fn draws_are_reproducible_and_differ_from_each_other() {
        let dem = flat_dem();
        let truth = catalogue(&dem, 20);
        let e = error(300.0, 0.05, 0.1, 1.0);
        let a = e.draw(&dem, &truth, 1000.0, 9, 0).unwrap();
        assert_eq!(a, e.draw(&dem, &truth, 1000.0, 9, 0).unwrap());
        assert_ne!(a, e.draw(&dem, &truth, 1000.0, 9, 1).unwrap());
        assert_ne!(a, e.draw(&dem, &truth, 1000.0, 10, 0).unwrap());
    }

    #[test]
    fn a_sample_keeps_its_draw_and_the_draws_share_the_samples() {
        let dem = flat_dem();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("catalogue.csv");
        let mut text = String::from("lon_deg,lat_deg,diameter_m\n");
        for c in catalogue(&dem, 4) {
            text += &format!("{},{},{}\n", c.lon_deg, c.lat_deg, c.diameter_m);
        }
        std::fs::write(&path, text).unwrap();
        let e = CatalogueError {
            draws: 4,
            ..error(300.0, 0.05, 0.0, 0.0)
        };
        let framed = FramedCatalogue::new(&dem, &path, 1000.0, Some(&e), 1).unwrap();
        let again = FramedCatalogue::new(&dem, &path, 1000.0, Some(&e), 1).unwrap();
        let mut per_draw = [0usize; 4];
        for i in 0..4000 {
            let id = format!("M{i}:{}:{}", i % 97, i % 89);
            assert_eq!(framed.draw_of(&id), again.draw_of(&id));
            per_draw[framed.draw_of(&id)] += 1;
        }
        // 4000 ids in 4 draws: 1000 each, binomial sd 27; 120 is 4.4σ.
        for n in per_draw {
            assert!(n.abs_diff(1000) < 120, "{per_draw:?}");
        }
        // A crop at the first crater's true centre: the draws place the centre apart, so ρ differs between them.
        let c = catalogue(&dem, 1)[0];
        let (x, y) = dem.crs.from_lonlat_deg(c.lon_deg, c.lat_deg).unwrap();
        let rhos: Vec<f64> = framed
            .draws
            .iter()
            .map(|d| d.position(x, y, -1000.0).unwrap().rho)
            .collect();
        assert!(rhos.iter().all(|&r| r > 0.0) && rhos.windows(2).any(|w| w[0] != w[1]));
        // Without errors there is one draw, the catalogue's own.
        let own = FramedCatalogue::new(&dem, &path, 1000.0, None, 1).unwrap();
        assert_eq!(own.draws.len(), 1);
        assert!(own.position("any", x, y, -1000.0).unwrap().rho < 1e-9);
    }
}

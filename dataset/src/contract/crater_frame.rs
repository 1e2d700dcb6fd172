//! The crater frame of a crop: where it lies relative to the nearest large catalogued crater, and how high it
//! stands against that crater's own mean profile. One home for it: the project stage computes it for the
//! published samples and `g2r-train infer` for crops of a new DEM, both through [`CraterFrames`].
//!
//! Why: on a complex crater's wall the crater's profile (kilometres of relief over a few kilometres) swamps the
//! few hundred metres by which mare lies below highland, so a crop's height alone no longer tells the unit under
//! it, as it does on the plains. Against the crater's *azimuthal median profile* taken from the same DEM, it does
//! again: the crop's height minus the profile's height at its normalised radius is the unit's offset
//! (docs/crater-diagnosis.md measures how much of the unit this reads on two worlds' held-out walls).
//!
//! The catalogue gives each crater's centre and diameter, as the Moon's published catalogues do (Robbins 2018:
//! `LAT_CIRC_IMG`, `LON_CIRC_IMG`, `DIAM_CIRC_IMG` in km); nothing else is taken from it. The profile is the
//! median height of the DEM's pixels in rings of [`PROFILE_BIN_RHO`] radii out to [`PROFILE_RHO_MAX`] radii,
//! with ground distances from the map through the local scale at the crater's centre.

use std::path::Path;

use anyhow::{bail, Context, Result};

use crate::science::crs::LocalFrame;
use crate::science::raster::Raster;

/// The profile reaches this many radii: past the ejecta blanket, onto the plains around.
pub const PROFILE_RHO_MAX: f64 = 3.0;
/// Ring width of the profile, in radii (45 m on an 18 km crater).
pub const PROFILE_BIN_RHO: f64 = 0.005;
/// Craters smaller than this are left out of the frame by default: lunar craters turn complex (terraced walls,
/// flat floors) at about 15–20 km across, and a simple crater's relief does not swamp a unit's offset.
pub const DEFAULT_MIN_DIAMETER_M: f64 = 15_000.0;

/// One catalogue entry: centre (planetocentric, east-positive) and rim diameter.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CatalogueCrater {
    pub lon_deg: f64,
    pub lat_deg: f64,
    pub diameter_m: f64,
}

/// Reads a crater catalogue CSV: either this project's columns `lon_deg`, `lat_deg`, `diameter_m`, or the Robbins
/// (2018) lunar catalogue's `LON_CIRC_IMG`, `LAT_CIRC_IMG` (degrees) and `DIAM_CIRC_IMG` (km). Other columns are
/// ignored; longitudes may run 0–360 or −180–180.
pub fn read_catalogue(path: &Path) -> Result<Vec<CatalogueCrater>> {
    let fix = "give a CSV with columns lon_deg,lat_deg,diameter_m (or Robbins 2018's LON_CIRC_IMG,LAT_CIRC_IMG,DIAM_CIRC_IMG)";
    let mut reader = csv::ReaderBuilder::new()
        .comment(Some(b'#'))
        .trim(csv::Trim::All)
        .from_path(path)
        .with_context(|| format!("{}: cannot read the crater catalogue", path.display()))?;
    let headers = reader
        .headers()
        .with_context(|| format!("{}: no header row; {fix}", path.display()))?
        .clone();
    let find = |name: &str| headers.iter().position(|h| h == name);
    let (lon, lat, diameter, metres_per_unit) = match (
        find("lon_deg"),
        find("lat_deg"),
        find("diameter_m"),
        find("LON_CIRC_IMG"),
        find("LAT_CIRC_IMG"),
        find("DIAM_CIRC_IMG"),
    ) {
        (Some(lon), Some(lat), Some(d), ..) => (lon, lat, d, 1.0),
        (.., Some(lon), Some(lat), Some(d)) => (lon, lat, d, 1000.0),
        _ => bail!(
            "{}: columns {:?} name no crater centre and diameter; {fix}",
            path.display(),
            headers.iter().collect::<Vec<_>>()
        ),
    };
    let mut craters = Vec::new();
    for (k, record) in reader.records().enumerate() {
        let record =
            record.with_context(|| format!("{}: unreadable row; {fix}", path.display()))?;
        let line = record.position().map_or(k + 2, |p| p.line() as usize);
        let value = |i: usize, what: &str| -> Result<f64> {
            let text = record.get(i).unwrap_or("");
            text.parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .with_context(|| {
                    format!("{}:{line}: {what} '{text}' is not a number", path.display())
                })
        };
        let crater = CatalogueCrater {
            lon_deg: wrap_lon_deg(value(lon, "longitude")?),
            lat_deg: value(lat, "latitude")?,
            diameter_m: value(diameter, "diameter")? * metres_per_unit,
        };
        if crater.lat_deg.abs() > 90.0 || crater.diameter_m <= 0.0 {
            bail!(
                "{}:{line}: latitude {} and diameter {} m: a latitude lies in −90…90 and a diameter is positive",
                path.display(),
                crater.lat_deg,
                crater.diameter_m
            );
        }
        craters.push(crater);
    }
    Ok(craters)
}

fn wrap_lon_deg(lon: f64) -> f64 {
    (lon + 180.0).rem_euclid(360.0) - 180.0
}

/// Where a crop lies in its crater's frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CraterPosition {
    /// Ground distance of the crop centre from the nearest catalogued crater's centre, in that crater's radii.
    pub rho: f64,
    /// The crop's mean height minus the crater's azimuthal median profile at `rho` (at [`PROFILE_RHO_MAX`] past
    /// it), metres.
    pub relative_height_m: f64,
    /// The crater's relief over its diameter ([`rim_relief_to_diameter`]); `None` in shards older than schema 1.4.
    pub relief_to_diameter: Option<f64>,
}

/// Rays from the catalogued centre along which [`rim_relief_to_diameter`] reads the rim and floor (5° apart).
pub const RELIEF_RAYS: usize = 72;
/// Each ray's rim crest is its highest DEM cell from this many radii ...
pub const RELIEF_CREST_RHO_MIN: f64 = 0.7;
/// ... out to this many (past the rim, so a catalogue diameter several per cent small still finds it).
pub const RELIEF_CREST_RHO_MAX: f64 = 1.5;
/// Each ray's floor is its lowest DEM cell inside this many radii (a complex crater's flat floor spans about half
/// its diameter; a simple crater's bowl bottoms out at its centre).
pub const RELIEF_FLOOR_RHO_MAX: f64 = 0.6;
/// Step along a ray, in radii.
pub const RELIEF_STEP_RHO: f64 = 0.01;
/// A crater is measured only where at least this many of its rays cross DEM at both their crest and floor (a
/// ninth of them: a crater at the DEM's corner still has a quadrant's worth).
pub const RELIEF_MIN_RAYS: usize = 8;

/// One crater's frame on the map.
#[derive(Debug, Clone)]
struct Frame {
    centre: (f64, f64),
    /// Map offset → ground east/north metres at the centre.
    map_to_en: [[f64; 2]; 2],
    radius_m: f64,
    /// Median height of each ring, metres; ring `i` spans `i..i+1` × [`PROFILE_BIN_RHO`].
    profile_m: Vec<f64>,
    /// [`rim_relief_to_diameter`].
    relief_to_diameter: f64,
}

impl Frame {
    fn rho(&self, x: f64, y: f64) -> f64 {
        let (dx, dy) = (x - self.centre.0, y - self.centre.1);
        let m = self.map_to_en;
        let (e, n) = (m[0][0] * dx + m[0][1] * dy, m[1][0] * dx + m[1][1] * dy);
        e.hypot(n) / self.radius_m
    }

    /// The profile's height at `rho` (clamped to the profile's reach), linear between ring centres.
    fn profile_at(&self, rho: f64) -> f64 {
        let t = (rho.min(PROFILE_RHO_MAX) / PROFILE_BIN_RHO - 0.5).max(0.0);
        let last = self.profile_m.len() - 1;
        let i = (t.floor() as usize).min(last);
        let j = (i + 1).min(last);
        let f = (t - i as f64).clamp(0.0, 1.0);
        self.profile_m[i] * (1.0 - f) + self.profile_m[j] * f
    }
}

/// What building the frames did with the catalogue: every crater is counted, none silently dropped.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct FramesReport {
    pub catalogued: usize,
    /// Smaller than the minimum diameter.
    pub too_small: usize,
    /// At least the minimum diameter, but with no DEM within [`PROFILE_RHO_MAX`] radii, or too little on its rim
    /// and floor to measure its relief ([`rim_relief_to_diameter`]).
    pub off_the_dem: usize,
    pub framed: usize,
}

/// The frames of a DEM's large catalogued craters.
#[derive(Debug, Clone)]
pub struct CraterFrames {
    frames: Vec<Frame>,
}

impl CraterFrames {
    /// One profile per catalogued crater at least `min_diameter_m` across with DEM around it (one pass over its
    /// square of the DEM each; the DEM is read on a stride of half a ring, which keeps the memory to a few MB).
    pub fn new(
        dem: &Raster,
        catalogue: &[CatalogueCrater],
        min_diameter_m: f64,
    ) -> Result<(Self, FramesReport)> {
        let mut report = FramesReport {
            catalogued: catalogue.len(),
            ..FramesReport::default()
        };
        let mut frames = Vec::new();
        for crater in catalogue {
            if crater.diameter_m < min_diameter_m {
                report.too_small += 1;
                continue;
            }
            let (x, y) = dem.crs.from_lonlat_deg(crater.lon_deg, crater.lat_deg)?;
            let local = LocalFrame::new(&dem.crs, x, y, 0.0)?;
            match profile(dem, (x, y), &local, crater.diameter_m / 2.0) {
                Some(frame) => {
                    frames.push(frame);
                    report.framed += 1;
                }
                None => report.off_the_dem += 1,
            }
        }
        Ok((Self { frames }, report))
    }

    /// The frames of a catalogue file's craters at least `min_diameter_m` wide over `dem` ([`read_catalogue`], then
    /// [`Self::new`]): how the project stage frames its crops, and `infer` a new DEM's. What was framed and skipped
    /// is logged. A catalogue that frames no crater of the DEM is an error, wherever it is given: it is the wrong
    /// catalogue, its coordinates are off, or it has nothing to do here; errors name the file.
    pub fn from_catalogue(dem: &Raster, catalogue: &Path, min_diameter_m: f64) -> Result<Self> {
        let craters = read_catalogue(catalogue)?;
        let (frames, report) = Self::new(dem, &craters, min_diameter_m).with_context(|| {
            format!(
                "{}: cannot place its craters on the DEM",
                catalogue.display()
            )
        })?;
        tracing::info!(
            catalogued = report.catalogued,
            too_small = report.too_small,
            off_the_dem = report.off_the_dem,
            framed = report.framed,
            "crater frames"
        );
        if frames.is_empty() {
            bail!(
                "{}: no crater frames the DEM ({} catalogued, {} under the minimum diameter of {min_diameter_m} m, {} \
                 with no DEM within {PROFILE_RHO_MAX} radii or too little on rim and floor): lower the minimum diameter (project.crater_frame_min_diameter_m, \
                 --crater-frame-min-diameter-m) or leave the catalogue out",
                catalogue.display(),
                report.catalogued,
                report.too_small,
                report.off_the_dem,
            );
        }
        Ok(frames)
    }

    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// The crop at map `(x, y)` with mean height `crop_mean_m` in the frame of the crater it lies nearest to, in
    /// radii; `None` without frames.
    pub fn position(&self, x: f64, y: f64, crop_mean_m: f64) -> Option<CraterPosition> {
        let (rho, frame) = self
            .frames
            .iter()
            .map(|f| (f.rho(x, y), f))
            .min_by(|a, b| a.0.total_cmp(&b.0))?;
        Some(CraterPosition {
            rho,
            relative_height_m: crop_mean_m - frame.profile_at(rho),
            relief_to_diameter: Some(frame.relief_to_diameter),
        })
    }
}

/// The azimuthal median profile around `centre` (map metres), or `None` when no DEM lies within its reach.
fn profile(dem: &Raster, centre: (f64, f64), local: &LocalFrame, radius_m: f64) -> Option<Frame> {
    let map_to_en = local.map_to_en;
    let mut frame = Frame {
        centre,
        map_to_en,
        radius_m,
        profile_m: Vec::new(),
        relief_to_diameter: f64::NAN,
    };
    let bins = (PROFILE_RHO_MAX / PROFILE_BIN_RHO).round() as usize;
    let t = dem.transform;
    let pixel_m = t.pixel_width.abs().min(t.pixel_height.abs());
    let stride = ((PROFILE_BIN_RHO * radius_m / (2.0 * pixel_m)).floor() as usize).max(1);
    // The map square that holds the profile's reach: ground reach through the inverse of map_to_en.
    let m = map_to_en;
    let det = m[0][0] * m[1][1] - m[0][1] * m[1][0];
    let reach = PROFILE_RHO_MAX * radius_m;
    let half_x = reach * (m[1][1].abs() + m[0][1].abs()) / det.abs();
    let half_y = reach * (m[1][0].abs() + m[0][0].abs()) / det.abs();
    let (c0, r0) = t.map_to_pixel(centre.0 - half_x, centre.1 + half_y);
    let (c1, r1) = t.map_to_pixel(centre.0 + half_x, centre.1 - half_y);
    let clamp = |v: f64, n: usize| (v.floor().max(0.0) as usize).min(n);
    let (cols, rows) = (
        clamp(c0.min(c1), dem.width)..clamp(c0.max(c1) + 1.0, dem.width),
        clamp(r0.min(r1), dem.height)..clamp(r0.max(r1) + 1.0, dem.height),
    );
    let mut rings: Vec<Vec<f32>> = vec![Vec::new(); bins];
    for row in rows.step_by(stride) {
        for col in cols.clone().step_by(stride) {
            let z = dem.get(col, row);
            if !z.is_finite() {
                continue;
            }
            let (x, y) = t.pixel_center(col as f64, row as f64);
            let ring = (frame.rho(x, y) / PROFILE_BIN_RHO) as usize;
            if ring < bins {
                rings[ring].push(z);
            }
        }
    }
    // The rings with pixels, in order, with their medians.
    let known: Vec<(usize, f64)> = rings
        .iter_mut()
        .enumerate()
        .filter_map(|(i, ring)| median(ring).map(|m| (i, m)))
        .collect();
    if known.is_empty() {
        return None;
    }
    // A ring with no pixels (near the centre, or where the DEM has a hole) takes the line between its neighbours,
    // or the nearest one's height past either end.
    frame.profile_m = (0..bins)
        .map(|i| {
            let k = known.partition_point(|&(j, _)| j < i);
            match (k.checked_sub(1).map(|b| known[b]), known.get(k).copied()) {
                (_, Some((j, v))) if j == i => v,
                (Some((jb, vb)), Some((ja, va))) => {
                    vb + (va - vb) * (i - jb) as f64 / (ja - jb) as f64
                }
                (Some((_, v)), None) | (None, Some((_, v))) => v,
                (None, None) => unreachable!("`known` is not empty"),
            }
        })
        .collect();
    frame.relief_to_diameter = rim_relief_to_diameter(dem, centre, local, radius_m)?;
    Some(frame)
}

/// A crater's relief over its diameter: along each of [`RELIEF_RAYS`] rays from the catalogued centre, the highest
/// DEM cell from [`RELIEF_CREST_RHO_MIN`] to [`RELIEF_CREST_RHO_MAX`] radii (the rim crest) minus the lowest inside
/// [`RELIEF_FLOOR_RHO_MAX`] (the floor), the median over the rays that cross DEM at both, over the diameter.
/// `None` when fewer than [`RELIEF_MIN_RAYS`] rays do (a crater mostly off the DEM).
///
/// Why: crest minus floor over diameter is the depth/diameter ratio by which crater morphometry dates a crater's
/// wear; a fresh crater is deeper for its size and its wall and ejecta are brighter, fresh material not yet
/// darkened by space weathering. It is read from the DEM and the catalogue's centre and diameter alone, so a new
/// site gives it as the training worlds do. Each ray finds the crest wherever it lies, so a catalogue centre off
/// by a tenth of a radius moves no crest, where a ring's median at a fixed radius mixes rim with wall and ejecta
/// and reads the crater shallower than an exact catalogue would (docs/scripts/relief_estimators.py measures both).
/// The median lets the rays that cross a unit boundary, a superposed crater or a DEM blunder go, while they are a
/// minority.
pub fn rim_relief_to_diameter(
    dem: &Raster,
    centre: (f64, f64),
    local: &LocalFrame,
    radius_m: f64,
) -> Option<f64> {
    let t = dem.transform;
    // The DEM cell nearest ground offset (east, north) from the centre, if it holds a height.
    let height = |east: f64, north: f64| {
        let d = local.en_to_map(east, north);
        let (col, row) = t.map_to_pixel(centre.0 + d.x, centre.1 + d.y);
        let (col, row) = (col.round(), row.round());
        let inside = col >= 0.0 && row >= 0.0 && col < dem.width as f64 && row < dem.height as f64;
        inside
            .then(|| dem.get(col as usize, row as usize))
            .filter(|z| z.is_finite())
            .map(f64::from)
    };
    let steps = (RELIEF_CREST_RHO_MAX / RELIEF_STEP_RHO).round() as usize;
    let mut reliefs: Vec<f32> = (0..RELIEF_RAYS)
        .filter_map(|ray| {
            let azimuth = std::f64::consts::TAU * ray as f64 / RELIEF_RAYS as f64;
            let (mut crest, mut floor) = (f64::NEG_INFINITY, f64::INFINITY);
            for step in 0..steps {
                let rho = step as f64 * RELIEF_STEP_RHO;
                let along = rho * radius_m;
                let Some(z) = height(along * azimuth.cos(), along * azimuth.sin()) else {
                    continue;
                };
                if rho < RELIEF_FLOOR_RHO_MAX {
                    floor = floor.min(z);
                }
                if rho >= RELIEF_CREST_RHO_MIN {
                    crest = crest.max(z);
                }
            }
            (crest.is_finite() && floor.is_finite()).then_some((crest - floor) as f32)
        })
        .collect();
    if reliefs.len() < RELIEF_MIN_RAYS {
        return None;
    }
    median(&mut reliefs).map(|relief| relief / (2.0 * radius_m))
}

/// Median of the values (the mean of the middle two for an even count); `None` for none.
fn median(values: &mut [f32]) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    values.sort_unstable_by(f32::total_cmp);
    let n = values.len();
    Some(if n % 2 == 1 {
        f64::from(values[n / 2])
    } else {
        (f64::from(values[n / 2 - 1]) + f64::from(values[n / 2])) / 2.0
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::science::crs::LunarCrs;
    use crate::science::raster::GeoTransform;

    /// A 20 km square DEM at 20 m on an equator-true equirectangular map, holding a crater of radius `radius_m` at
    /// the map's centre whose height rises linearly with ρ (`slope_m` per radius) to a flat plain past ρ = 1.2,
    /// with `offset_m` added north of the centre and east of x = radius/2 (the minority unit, under a quarter of
    /// any ring: the median profile follows the majority's heights).
    fn crater_dem(radius_m: f64, slope_m: f64, offset_m: f64) -> (Raster, CatalogueCrater) {
        let crs = LunarCrs::equirectangular(0.0, 0.0);
        let (px, n) = (20.0, 1000);
        let transform = GeoTransform::north_up(-10_000.0, 10_000.0, px);
        let mut dem = Raster::new(n, n, transform, crs.clone(), 0.0);
        for row in 0..n {
            for col in 0..n {
                let (x, y) = transform.pixel_center(col as f64, row as f64);
                dem.data[row * n + col] = height(x, y, radius_m, slope_m, offset_m) as f32;
            }
        }
        let (lon_deg, lat_deg) = crs.to_lonlat_deg(0.0, 0.0).unwrap();
        let crater = CatalogueCrater {
            lon_deg,
            lat_deg,
            diameter_m: 2.0 * radius_m,
        };
        (dem, crater)
    }

    fn height(x: f64, y: f64, radius_m: f64, slope_m: f64, offset_m: f64) -> f64 {
        let rho = x.hypot(y) / radius_m;
        let minority = y > 0.0 && x > radius_m / 2.0;
        -2000.0 + slope_m * rho.min(1.2) + if minority { offset_m } else { 0.0 }
    }

    #[test]
    fn against_the_median_profile_a_minority_units_offset_reads_as_its_relative_height() {
        let (radius, slope, offset) = (6000.0, 1600.0, 300.0);
        let (dem, crater) = crater_dem(radius, slope, offset);
        let (frames, report) = CraterFrames::new(&dem, &[crater], 10_000.0).unwrap();
        assert_eq!(
            report,
            FramesReport {
                catalogued: 1,
                framed: 1,
                ..FramesReport::default()
            }
        );
        // On the wall the crater's rise (1,600 m per radius) swamps the 300 m offset; against the profile it is
        // the offset, within a ring's rise (8 m) of the median's place in its ring.
        for (x, y) in [(4000.0, 2000.0), (3300.0, 400.0), (5000.0, 3000.0)] {
            let z = height(x, y, radius, slope, offset);
            let p = frames.position(x, y, z).unwrap();
            assert!((p.rho - x.hypot(y) / radius).abs() < 1e-6, "{p:?}");
            assert!(
                (p.relative_height_m - offset).abs() < 8.0,
                "minority unit at ({x}, {y}): {p:?}"
            );
        }
        for (x, y) in [(-4000.0, 2000.0), (1000.0, -3500.0), (-2000.0, -2000.0)] {
            let z = height(x, y, radius, slope, offset);
            let p = frames.position(x, y, z).unwrap();
            assert!(
                p.relative_height_m.abs() < 8.0,
                "majority unit at ({x}, {y}): {p:?}"
            );
        }
    }

    /// The fixture's crater rises `slope` metres per radius from its centre to its crest at ρ 1.2: its relief is
    /// 1.2 × slope over its diameter, within the rise over half a pixel's diagonal at the floor (the cell nearest
    /// the centre lies that far from it). The ratio is the crater's shape, not its size: half the crater at half the depth
    /// reads the same; at half the depth alone, half of it.
    #[test]
    fn relief_to_diameter_is_the_crest_minus_floor_over_the_diameter() {
        let relief = |radius: f64, slope: f64| {
            let (dem, crater) = crater_dem(radius, slope, 0.0);
            let frames = CraterFrames::new(&dem, &[crater], 1000.0).unwrap().0;
            let p = frames.position(0.5 * radius, 0.0, 0.0).unwrap();
            let ratio = p.relief_to_diameter.unwrap();
            let half_diagonal_rise =
                slope * (20.0 * std::f64::consts::SQRT_2 / 2.0) / radius / (2.0 * radius);
            let expected = 1.2 * slope / (2.0 * radius);
            assert!(
                (ratio - expected).abs() <= half_diagonal_rise + 1e-7,
                "radius {radius} m, slope {slope} m: {ratio} against {expected}"
            );
            ratio
        };
        let fresh = relief(6000.0, 1600.0);
        assert!((relief(3000.0, 800.0) - fresh).abs() < 1e-3);
        assert!((relief(6000.0, 800.0) - fresh / 2.0).abs() < 1e-3);
    }

    /// A bowl with a sharp rim, on the fixture's map: −`depth` + (depth + rim) ρ² inside the rim, rim ρ⁻³ past it,
    /// plus `east_offset_m` more than 0.8 radii east of the centre (a unit boundary across the rim). Its relief over
    /// diameter is (depth + rim) / (2 × radius).
    fn sharp_rim_dem(radius_m: f64, depth_m: f64, rim_m: f64, east_offset_m: f64) -> Raster {
        let (mut dem, _) = crater_dem(radius_m, 0.0, 0.0);
        for row in 0..dem.height {
            for col in 0..dem.width {
                let (x, y) = dem.transform.pixel_center(col as f64, row as f64);
                let rho = x.hypot(y) / radius_m;
                let crater = if rho <= 1.0 {
                    -depth_m + (depth_m + rim_m) * rho * rho
                } else {
                    rim_m * rho.powi(-3)
                };
                let unit = if x > 0.8 * radius_m {
                    east_offset_m
                } else {
                    0.0
                };
                dem.data[row * dem.width + col] = (-2000.0 + crater + unit) as f32;
            }
        }
        dem
    }

    /// A catalogue centre off by a tenth of a radius (600 m on a 12 km crater, twice the error the training
    /// publications simulate) still finds the rim on every ray: the relief stays within 3 % of the crater's
    /// (a ring's median at ρ 1 would mix wall and ejecta around the rim and lose about 5 %), as it does with
    /// the exact centre. The slack is the rim's fall within a ray's step (0.01 radii) and the floor rays that
    /// start a tenth of a radius up the bowl.
    #[test]
    fn a_catalogue_centre_a_tenth_of_a_radius_off_still_finds_the_rim() {
        let (radius, depth, rim) = (6000.0, 840.0, 240.0);
        let dem = sharp_rim_dem(radius, depth, rim, 0.0);
        let expected = (depth + rim) / (2.0 * radius);
        for centre in [(0.0, 0.0), (600.0, 0.0), (-420.0, 420.0)] {
            let local = LocalFrame::new(&dem.crs, centre.0, centre.1, 0.0).unwrap();
            let relief = rim_relief_to_diameter(&dem, centre, &local, radius).unwrap();
            assert!(
                (relief / expected - 1.0).abs() < 0.03,
                "centre {centre:?}: {relief} against {expected}"
            );
        }
    }

    /// Mare lies hundreds of metres below highland. A boundary across the crater's east rim (0.8 radii east of the
    /// centre) reaches a minority of the rays, and the median over the rays lets them go: the relief moves by less
    /// than the spread of the other rays. (A boundary through the centre is not claimed: rays on its high side can take their floor from the
    /// low side near the centre.)
    #[test]
    fn a_unit_boundary_across_the_rim_barely_moves_the_relief() {
        let relief = |offset: f64| {
            let dem = sharp_rim_dem(6000.0, 840.0, 240.0, offset);
            let local = LocalFrame::new(&dem.crs, 0.0, 0.0, 0.0).unwrap();
            rim_relief_to_diameter(&dem, (0.0, 0.0), &local, 6000.0).unwrap()
        };
        let (plain, crossed) = (relief(0.0), relief(300.0));
        // Were the offset read as relief it would add 300 m / 12 km = 0.025, 28 % of the relief. Dropping the
        // crossed rays moves the median within the spread of the others: the bowl's rise within one ray step at
        // the rim, 2 (depth + rim) × 0.01 radii, 2 % of the relief.
        assert!(
            (crossed / plain - 1.0).abs() < 0.02,
            "{plain} against {crossed}"
        );
    }

    /// A crater whose floor lies off the DEM has no relief to read, and is counted off the DEM, not framed with
    /// a made-up one.
    #[test]
    fn a_crater_with_its_floor_off_the_dem_is_not_framed() {
        let (dem, crater) = crater_dem(6000.0, 1600.0, 0.0);
        // 14.5 km east of the centre: the DEM's edge (10 km) is within reach (18 km), the floor (3.6 km) is not.
        let (lon_deg, lat_deg) = dem.crs.to_lonlat_deg(14_500.0, 0.0).unwrap();
        let beyond = CatalogueCrater {
            lon_deg,
            lat_deg,
            ..crater
        };
        let report = CraterFrames::new(&dem, &[crater, beyond], 1000.0)
            .unwrap()
            .1;
        assert_eq!((report.framed, report.off_the_dem), (1, 1));
        // One at the DEM's south-east corner: its rays leave through the last row and column, and it is measured
        // from the quarter of them that stay on the DEM (the fixture's plain there is level: no relief).
        let corner = dem.transform.pixel_center(999.0, 999.0);
        let local = LocalFrame::new(&dem.crs, corner.0, corner.1, 0.0).unwrap();
        let relief = rim_relief_to_diameter(&dem, corner, &local, 2000.0).unwrap();
        assert!(relief.abs() < 1e-9, "{relief}");
    }

    #[test]
    fn rings_a_dem_hole_empties_take_the_line_between_their_neighbours() {
        let (radius, slope) = (6000.0, 1600.0);
        let (mut dem, crater) = crater_dem(radius, slope, 0.0);
        // No DEM from ρ 0.70 to 0.72: four rings hold no pixel.
        for row in 0..dem.height {
            for col in 0..dem.width {
                let (x, y) = dem.transform.pixel_center(col as f64, row as f64);
                if (0.70..0.72).contains(&(x.hypot(y) / radius)) {
                    dem.data[row * dem.width + col] = f32::NAN;
                }
            }
        }
        let frames = CraterFrames::new(&dem, &[crater], 10_000.0).unwrap().0;
        // The crater rises linearly there, so the line between the rings either side is its profile.
        let (x, y) = (0.71 * radius * 0.6, 0.71 * radius * -0.8);
        let p = frames
            .position(x, y, height(x, y, radius, slope, 0.0))
            .unwrap();
        assert!(p.relative_height_m.abs() < 8.0, "{p:?}");
    }

    #[test]
    fn the_nearest_crater_in_radii_frames_a_crop_and_past_the_reach_the_last_ring_does() {
        let (dem, crater) = crater_dem(2000.0, 800.0, 0.0);
        let (lon, lat) = dem.crs.to_lonlat_deg(9000.0, 9000.0).unwrap();
        let far = CatalogueCrater {
            lon_deg: lon,
            lat_deg: lat,
            diameter_m: 20_000.0,
        };
        let (frames, report) = CraterFrames::new(&dem, &[crater, far], 1000.0).unwrap();
        assert_eq!(report.framed, 2);
        // 3 km from the small crater (ρ 1.5) and 10.8 km from the big one (ρ 1.08): the big one frames it. On
        // the ground, east offsets are the map's times cos(latitude) at the big crater (0.3° north; the map is true
        // to scale at the equator), north ones the map's.
        let p = frames.position(3000.0, 0.0, 0.0).unwrap();
        let east_scale = lat.to_radians().cos();
        assert!(
            (p.rho - (6000.0 * east_scale).hypot(9000.0) / 10_000.0).abs() < 1e-6,
            "{p:?}"
        );
        // Past the reach the height is taken against the profile's last ring: the plain's level.
        let frames = CraterFrames::new(&dem, &[crater], 1000.0).unwrap().0;
        let p = frames
            .position(-9000.0, -9000.0, -2000.0 + 960.0 + 25.0)
            .unwrap();
        assert!(p.rho > PROFILE_RHO_MAX);
        assert!((p.relative_height_m - 25.0).abs() < 1e-3, "{p:?}");
    }

    #[test]
    fn small_and_off_dem_craters_are_counted_and_no_frame_means_no_position() {
        let (dem, crater) = crater_dem(2000.0, 800.0, 0.0);
        let off = CatalogueCrater {
            lon_deg: crater.lon_deg + 5.0,
            ..crater
        };
        let (frames, report) = CraterFrames::new(&dem, &[crater, off], 5000.0).unwrap();
        assert_eq!(
            report,
            FramesReport {
                catalogued: 2,
                too_small: 2,
                ..FramesReport::default()
            }
        );
        assert!(frames.is_empty() && frames.position(0.0, 0.0, 0.0).is_none());
        let report = CraterFrames::new(&dem, &[crater, off], 1000.0).unwrap().1;
        assert_eq!((report.framed, report.off_the_dem), (1, 1));
    }

    #[test]
    fn a_catalogue_file_that_frames_nothing_is_refused_naming_it_and_its_source_is_recorded() {
        let (dem, crater) = crater_dem(2000.0, 800.0, 0.0);
        let dir = tempfile::tempdir().unwrap();
        let write = |name: &str, lon_deg: f64| {
            let path = dir.path().join(name);
            let row = format!(
                "lon_deg,lat_deg,diameter_m\n{lon_deg},{},4000\n",
                crater.lat_deg
            );
            std::fs::write(&path, row).unwrap();
            path
        };
        let on_the_dem = write("here.csv", crater.lon_deg);
        assert!(!CraterFrames::from_catalogue(&dem, &on_the_dem, 1000.0)
            .unwrap()
            .is_empty());
        for (path, min_diameter_m) in [
            (write("elsewhere.csv", crater.lon_deg + 5.0), 1000.0),
            (on_the_dem.clone(), 5000.0),
        ] {
            let err = format!(
                "{:#}",
                CraterFrames::from_catalogue(&dem, &path, min_diameter_m).unwrap_err()
            );
            let name = path.file_name().unwrap().to_str().unwrap();
            assert!(
                err.contains(name) && err.contains("no crater frames the DEM"),
                "{err}"
            );
        }
    }

    #[test]
    fn a_catalogue_reads_in_either_column_set_and_a_bad_row_names_its_line() {
        let dir = tempfile::tempdir().unwrap();
        let ours = dir.path().join("ours.csv");
        std::fs::write(
            &ours,
            "# the complex crater\nlat_deg,lon_deg,diameter_m\n-43.3,348.8,18000\n",
        )
        .unwrap();
        let read = read_catalogue(&ours).unwrap();
        assert_eq!(read.len(), 1);
        assert!((read[0].lon_deg - -11.2).abs() < 1e-9 && read[0].diameter_m == 18_000.0);
        let robbins = dir.path().join("robbins.csv");
        std::fs::write(
            &robbins,
            "CRATER_ID,LAT_CIRC_IMG,LON_CIRC_IMG,DIAM_CIRC_IMG\n00-1-000001,-43.3,-11.2,18.0\n",
        )
        .unwrap();
        let robbins = read_catalogue(&robbins).unwrap();
        assert_eq!(robbins.len(), 1);
        assert!((robbins[0].lon_deg - read[0].lon_deg).abs() < 1e-9);
        assert!(robbins[0].lat_deg == -43.3 && robbins[0].diameter_m == 18_000.0);
        let bad = dir.path().join("bad.csv");
        std::fs::write(&bad, "lon_deg,lat_deg,diameter_m\n1,2,3\n1,x,3\n").unwrap();
        let err = format!("{:#}", read_catalogue(&bad).unwrap_err());
        assert!(err.contains("bad.csv:3") && err.contains("'x'"), "{err}");
        let none = dir.path().join("none.csv");
        std::fs::write(&none, "lon,lat,d\n1,2,3\n").unwrap();
        let err = format!("{:#}", read_catalogue(&none).unwrap_err());
        assert!(
            err.contains("none.csv") && err.contains("lon_deg,lat_deg,diameter_m"),
            "{err}"
        );
    }
}

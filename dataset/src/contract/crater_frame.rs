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
//!
//! A real catalogue's centres are a few hundred metres off and its diameters a few per cent (Robbins 2018), enough
//! to smear the profile's wall across the 300 m by which the units differ. So the frame is first *refined to the
//! rim* the DEM shows, as crater morphometry does before it measures: each azimuth sector's highest point near the
//! catalogued rim, a circle fitted through them ([`RIM_FIT_MAX_RESIDUAL_RADII`] and the other `RIM_` limits), and
//! the profile taken again about that circle. Where no circle fits (a crater the DEM does not show, a catalogue's
//! false entry) the catalogue's centre and diameter stand, and the report counts both.

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
    /// The crater's relief over its diameter ([`RELIEF_CREST_RHO_MAX`]); `None` in shards older than schema 1.4.
    pub relief_to_diameter: Option<f64>,
}

/// The crest of a crater's relief is its rim's height: where the frame is refined to the rim, the median height of
/// the rim points on the fitted circle ([`RIM_MIN_POINTS`]); elsewhere the median, over [`RELIEF_CREST_SECTORS`]
/// azimuth sectors about the catalogued centre, of each sector's highest DEM height from [`RELIEF_CREST_RHO_MIN`]
/// to this many radii (past the rim, so a catalogue diameter a few per cent small still finds it). Its floor is
/// the median profile's lowest ring within one radius.
///
/// Why: crest minus floor over diameter is the depth/diameter ratio by which crater morphometry dates a
/// crater's wear; a fresh crater is deeper for its size and its wall and ejecta are brighter, fresh material
/// not yet darkened by space weathering. It is read from the DEM and the catalogue's centre and diameter alone,
/// so a new site gives it as the training worlds do. Each sector's highest point is on the rim wherever the
/// centre is, so a catalogue centre a few hundred metres off reads the same crest; the median of a ring, taken
/// about an offset centre, straddles the rim and reads it low (schema 1.4 did so: its relief read a crater
/// framed by a real catalogue's errors lower than the same crater framed exactly). A flat floor's lowest ring
/// keeps its height under such an offset.
pub const RELIEF_CREST_RHO_MAX: f64 = 1.5;

/// The crest's sectors start this many radii out ([`RELIEF_CREST_RHO_MAX`]): a complex crater's central peak can
/// stand above its rim, and inside this it would be the highest point of the sectors it reaches (seen on a
/// synthetic fresh 1.1 km crater: a third of them). 0.6 leaves a catalogue diameter 25 % large room to find its rim.
pub const RELIEF_CREST_RHO_MIN: f64 = 0.6;

/// Azimuth sectors of the crest ([`RELIEF_CREST_RHO_MAX`]): 5° each, a few hundred metres of rim on the craters
/// the frames are for (8 km and more), so each holds DEM posts even at 100 m a post; sectors with none (off the
/// DEM, a hole) are left out of the median.
pub const RELIEF_CREST_SECTORS: usize = 72;

/// A sector's highest point is a rim point for the circle fit only if it lies inside this many catalogued radii:
/// one at the edge of the crest's reach ([`RELIEF_CREST_RHO_MAX`]) is the terrain rising past the crater, not its
/// rim. 1.4 leaves a catalogue diameter 25 % small room to find its rim.
pub const RIM_POINT_RHO_MAX: f64 = 1.4;
/// A rim is a circle through the highest points of at least a third of the sectors ([`RIM_FIT_MAX_RESIDUAL_RADII`]):
/// on the many-craters worlds' craters 29 to 36 of 72 lie on the rim, the others on terrain past it.
pub const RIM_MIN_POINTS: usize = RELIEF_CREST_SECTORS / 3;
/// A point is on the fitted circle if it lies within this many of its radii. 2 %: the synthetic complex craters'
/// rim points lie within 0.7 % of their circle; a worn one at the DEM's edge, catalogued 6 % of a radius off,
/// had its points 4.6 % from a circle 6 % of a radius from its rim, a frame worse than the catalogue's.
pub const RIM_FIT_MAX_RESIDUAL_RADII: f64 = 0.02;
/// Rounds of the trimmed circle fit ([`fit_rim`]): each moves the circle toward the rim points' ring, from a
/// catalogue's circle a tenth of a radius off in two or three.
pub const RIM_FIT_ROUNDS: usize = 5;
/// The fitted centre moves at most this many catalogued radii (a real catalogue's error is under a tenth)...
pub const RIM_MAX_CENTRE_SHIFT_RADII: f64 = 0.3;
/// ... and the fitted radius stays within this factor of the catalogued one, either way.
pub const RIM_MAX_RADIUS_FACTOR: f64 = 1.25;

/// One crater's frame on the map.
#[derive(Debug, Clone)]
struct Frame {
    centre: (f64, f64),
    /// Map offset → ground east/north metres at the centre.
    map_to_en: [[f64; 2]; 2],
    radius_m: f64,
    /// Median height of each ring, metres; ring `i` spans `i..i+1` × [`PROFILE_BIN_RHO`].
    profile_m: Vec<f64>,
    /// The sectors' crest minus the profile's floor, over the diameter ([`RELIEF_CREST_RHO_MAX`]).
    relief_to_diameter: f64,
}

impl Frame {
    fn rho(&self, x: f64, y: f64) -> f64 {
        let (e, n) = self.east_north(x, y);
        e.hypot(n) / self.radius_m
    }

    /// Ground east and north metres of map `(x, y)` from the centre.
    fn east_north(&self, x: f64, y: f64) -> (f64, f64) {
        let (dx, dy) = (x - self.centre.0, y - self.centre.1);
        let m = self.map_to_en;
        (m[0][0] * dx + m[0][1] * dy, m[1][0] * dx + m[1][1] * dy)
    }

    /// The map point `en` ground metres east and north of the centre.
    fn map_from_en(&self, en: [f64; 2]) -> (f64, f64) {
        let m = self.map_to_en;
        let det = m[0][0] * m[1][1] - m[0][1] * m[1][0];
        let dx = (m[1][1] * en[0] - m[0][1] * en[1]) / det;
        let dy = (-m[1][0] * en[0] + m[0][0] * en[1]) / det;
        (self.centre.0 + dx, self.centre.1 + dy)
    }

    /// The azimuth sector ([`RELIEF_CREST_SECTORS`]) of a point `e`, `n` ground metres east and north of the
    /// centre.
    fn sector(e: f64, n: f64) -> usize {
        let turns = n.atan2(e) / std::f64::consts::TAU + 0.5;
        ((turns * RELIEF_CREST_SECTORS as f64) as usize).min(RELIEF_CREST_SECTORS - 1)
    }

    /// `crest_m` minus the profile's floor (its lowest ring within one radius, rings taken by their centres)
    /// over the diameter ([`RELIEF_CREST_RHO_MAX`]).
    fn relief_to_diameter(&self, crest_m: f64) -> f64 {
        let floor = self
            .profile_m
            .iter()
            .enumerate()
            .filter(|&(i, _)| (i as f64 + 0.5) * PROFILE_BIN_RHO < 1.0)
            .map(|(_, &z)| z)
            .fold(f64::INFINITY, f64::min);
        (crest_m - floor) / (2.0 * self.radius_m)
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
    /// At least the minimum diameter, but with no DEM within [`PROFILE_RHO_MAX`] radii.
    pub off_the_dem: usize,
    pub framed: usize,
    /// Of the framed, those whose centre and diameter were refined to the rim the DEM shows; the others keep the
    /// catalogue's (no circle fits their sectors' highest points).
    pub refined_to_rim: usize,
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
            match profile(dem, (x, y), local.map_to_en, crater.diameter_m / 2.0) {
                Some((catalogued, rim_points)) => {
                    let refined = fit_rim(&rim_points, catalogued.radius_m).and_then(|rim| {
                        let centre = catalogued.map_from_en(rim.centre_en);
                        let (mut frame, _) = profile(dem, centre, local.map_to_en, rim.radius_m)?;
                        frame.relief_to_diameter = frame.relief_to_diameter(rim.crest_m);
                        Some(frame)
                    });
                    report.refined_to_rim += usize::from(refined.is_some());
                    frames.push(refined.unwrap_or(catalogued));
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
            refined_to_rim = report.refined_to_rim,
            "crater frames"
        );
        if frames.is_empty() {
            bail!(
                "{}: no crater frames the DEM ({} catalogued, {} under the minimum diameter of {min_diameter_m} m, {} \
                 with no DEM within {PROFILE_RHO_MAX} radii): lower the minimum diameter (project.crater_frame_min_diameter_m, \
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

/// The azimuthal median profile around `centre` (map metres), or `None` when no DEM lies within its reach; with
/// it, each sector's highest point inside [`RIM_POINT_RHO_MAX`] radii: ground metres east and north of `centre`,
/// and its height.
fn profile(
    dem: &Raster,
    centre: (f64, f64),
    map_to_en: [[f64; 2]; 2],
    radius_m: f64,
) -> Option<(Frame, Vec<[f64; 3]>)> {
    let mut frame = Frame {
        centre,
        map_to_en,
        radius_m,
        profile_m: Vec::new(),
        relief_to_diameter: f64::NAN,
    };
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
    // The posts within the profile's reach: height, ρ, east and north metres.
    let mut posts: Vec<(f32, f64, [f64; 2])> = Vec::new();
    for row in rows.step_by(stride) {
        for col in cols.clone().step_by(stride) {
            let z = dem.get(col, row);
            if !z.is_finite() {
                continue;
            }
            let (x, y) = t.pixel_center(col as f64, row as f64);
            let rho = frame.rho(x, y);
            if rho < PROFILE_RHO_MAX {
                let (e, n) = frame.east_north(x, y);
                posts.push((z, rho, [e, n]));
            }
        }
    }
    frame.profile_m = ring_profile(&posts)?;
    // Each sector's highest point within the crest's reach, and where it is (ρ, east, north).
    let mut sector_crests = [(f64::NEG_INFINITY, 0.0, [0.0; 2]); RELIEF_CREST_SECTORS];
    for &(z, rho, en) in posts
        .iter()
        .filter(|p| (RELIEF_CREST_RHO_MIN..RELIEF_CREST_RHO_MAX).contains(&p.1))
    {
        // Of equal heights the innermost: on a flat top the rim is where the rise ends.
        let (best, best_rho, _) = &mut sector_crests[Frame::sector(en[0], en[1])];
        let z = f64::from(z);
        if z > *best || (z == *best && rho < *best_rho) {
            sector_crests[Frame::sector(en[0], en[1])] = (z, rho, en);
        }
    }
    // With no DEM within the crest's reach (a crater centred well off the DEM's edge) the crest is the profile's
    // highest ring there, which its nearest known rings set.
    let mut crests: Vec<f32> = sector_crests
        .iter()
        .filter(|c| c.0.is_finite())
        .map(|c| c.0 as f32)
        .collect();
    let crest = median(&mut crests).unwrap_or_else(|| {
        let reach = (RELIEF_CREST_RHO_MAX / PROFILE_BIN_RHO) as usize;
        frame.profile_m[..reach]
            .iter()
            .copied()
            .fold(f64::NEG_INFINITY, f64::max)
    });
    frame.relief_to_diameter = frame.relief_to_diameter(crest);
    let rim = sector_crests
        .iter()
        .filter(|c| c.0.is_finite() && c.1 < RIM_POINT_RHO_MAX)
        .map(|c| [c.2[0], c.2[1], c.0])
        .collect();
    Some((frame, rim))
}

/// The median height of each ring, a ring with none (near the centre, or where the DEM has a hole) taking the line
/// between its neighbours, or the nearest one's height past either end; `None` without posts.
fn ring_profile(posts: &[(f32, f64, [f64; 2])]) -> Option<Vec<f64>> {
    let bins = (PROFILE_RHO_MAX / PROFILE_BIN_RHO).round() as usize;
    let mut rings: Vec<Vec<f32>> = vec![Vec::new(); bins];
    for &(z, rho, _) in posts {
        let ring = (rho / PROFILE_BIN_RHO) as usize;
        if ring < bins {
            rings[ring].push(z);
        }
    }
    let known: Vec<(usize, f64)> = rings
        .iter_mut()
        .enumerate()
        .filter_map(|(i, ring)| median(ring).map(|m| (i, m)))
        .collect();
    if known.is_empty() {
        return None;
    }
    Some(
        (0..bins)
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
            .collect(),
    )
}

/// A rim fitted to the DEM: its centre in ground metres east and north of the catalogued one, its radius, and its
/// crest, the median height of the rim points on it.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Rim {
    centre_en: [f64; 2],
    radius_m: f64,
    crest_m: f64,
}

/// The circle through a crater's rim points (ground metres east and north of its catalogued centre, and height),
/// or `None` where too few lie on any circle within the `RIM_` limits. Beyond the rim the terrain often stands
/// higher than it (the many-craters worlds' ejecta and hills hold a third to a half of the sectors' highest
/// points), so the fit is trimmed: from the catalogue's circle, [`RIM_FIT_ROUNDS`] times an algebraic (Kåsa)
/// least-squares circle through the half of the points nearest the last one; then the circle through the points
/// within [`RIM_FIT_MAX_RESIDUAL_RADII`] of it, if they are at least [`RIM_MIN_POINTS`]. Fitted in catalogued
/// radii, for conditioning.
fn fit_rim(rim: &[[f64; 3]], catalogued_radius_m: f64) -> Option<Rim> {
    if rim.len() < RIM_MIN_POINTS {
        return None;
    }
    let points: Vec<[f64; 2]> = rim
        .iter()
        .map(|p| [p[0] / catalogued_radius_m, p[1] / catalogued_radius_m])
        .collect();
    let circle = |points: &[[f64; 2]]| -> ([f64; 2], f64) {
        // e² + n² + a e + b n + c = 0: least squares in (a, b, c) through the normal equations.
        let mut ata = vec![vec![0.0; 3]; 3];
        let mut atb = vec![0.0; 3];
        for p in points {
            let row = [p[0], p[1], 1.0];
            let target = -(p[0] * p[0] + p[1] * p[1]);
            for i in 0..3 {
                atb[i] += row[i] * target;
                for j in 0..3 {
                    ata[i][j] += row[i] * row[j];
                }
            }
        }
        let abc = crate::science::least_squares::solve_small_system(ata, atb);
        let centre = [-abc[0] / 2.0, -abc[1] / 2.0];
        (
            centre,
            (centre[0].powi(2) + centre[1].powi(2) - abc[2])
                .max(0.0)
                .sqrt(),
        )
    };
    let distance = |(centre, radius): ([f64; 2], f64), p: &[f64; 2]| {
        ((p[0] - centre[0]).hypot(p[1] - centre[1]) - radius).abs()
    };
    let mut fitted = ([0.0; 2], 1.0);
    for _ in 0..RIM_FIT_ROUNDS {
        let mut nearest = points.clone();
        nearest.sort_by(|p, q| distance(fitted, p).total_cmp(&distance(fitted, q)));
        nearest.truncate(points.len().div_ceil(2));
        fitted = circle(&nearest);
    }
    let on_rim = |fitted: ([f64; 2], f64)| -> Vec<usize> {
        (0..points.len())
            .filter(|&i| distance(fitted, &points[i]) <= RIM_FIT_MAX_RESIDUAL_RADII * fitted.1)
            .collect()
    };
    let inliers = on_rim(fitted);
    if inliers.len() < RIM_MIN_POINTS {
        return None;
    }
    let (centre, radius) = circle(&inliers.iter().map(|&i| points[i]).collect::<Vec<_>>());
    let mut heights: Vec<f32> = on_rim((centre, radius))
        .iter()
        .map(|&i| rim[i][2] as f32)
        .collect();
    let fits = radius.is_finite()
        && heights.len() >= RIM_MIN_POINTS
        && centre[0].hypot(centre[1]) <= RIM_MAX_CENTRE_SHIFT_RADII
        && (1.0 / RIM_MAX_RADIUS_FACTOR..=RIM_MAX_RADIUS_FACTOR).contains(&radius);
    fits.then(|| Rim {
        centre_en: [
            centre[0] * catalogued_radius_m,
            centre[1] * catalogued_radius_m,
        ],
        radius_m: radius * catalogued_radius_m,
        crest_m: median(&mut heights).expect("at least RIM_MIN_POINTS heights"),
    })
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
                refined_to_rim: 1,
                ..FramesReport::default()
            }
        );
        // The frame is refined to the DEM's crest, 1.2 catalogued radii out, within a post (20 m).
        let refined_m = frames.frames[0].radius_m;
        assert!((refined_m - 1.2 * radius).abs() < 20.0, "{refined_m}");
        // On the wall the crater's rise (1,600 m per radius) swamps the 300 m offset; against the profile it is
        // the offset, within a ring's rise (8 m) of the median's place in its ring.
        for (x, y) in [(4000.0, 2000.0), (3300.0, 400.0), (5000.0, 3000.0)] {
            let z = height(x, y, radius, slope, offset);
            let p = frames.position(x, y, z).unwrap();
            // The refined centre lies within a metre of the crater's: ρ within 1e-4.
            assert!((p.rho - x.hypot(y) / refined_m).abs() < 1e-4, "{p:?}");
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

    /// The fixture's crater rises `slope` metres per radius from its centre to its crest at ρ 1.2, to which the
    /// frame is refined: its relief is 1.2 × slope over the crest's diameter, 2.4 radii, within a ring's rise at
    /// the floor (the centre ring's median sits a few metres up its slope) and a post's place of the crest (20 m
    /// in 14.4 km). The ratio is the crater's shape, not its size: half the crater at half the depth reads the
    /// same; at half the depth alone, half of it.
    #[test]
    fn relief_to_diameter_is_the_profiles_crest_minus_floor_over_the_diameter() {
        let relief = |radius: f64, slope: f64| {
            let (dem, crater) = crater_dem(radius, slope, 0.0);
            let frames = CraterFrames::new(&dem, &[crater], 1000.0).unwrap().0;
            let p = frames.position(0.5 * radius, 0.0, 0.0).unwrap();
            let ratio = p.relief_to_diameter.unwrap();
            let ring_rise = slope * PROFILE_BIN_RHO / (2.0 * radius);
            let expected = 1.2 * slope / (2.0 * 1.2 * radius);
            assert!(
                (ratio - expected).abs() < ring_rise + expected * 20.0 / (2.4 * radius),
                "radius {radius} m, slope {slope} m: {ratio} against {expected}"
            );
            ratio
        };
        let fresh = relief(6000.0, 1600.0);
        assert!((relief(3000.0, 800.0) - fresh).abs() < 1e-3);
        assert!((relief(6000.0, 800.0) - fresh / 2.0).abs() < 1e-3);
    }

    /// A crater with a flat floor to ρ 0.4, a central cone `peak_m` high within ρ 0.15, a wall rising `relief_m`
    /// to its rim crest at ρ 1 and ejecta falling as ρ⁻³ past it, on a 24 km DEM at 20 m; its catalogue entry is
    /// `offset_m` east of its centre.
    fn rimmed_crater(
        radius_m: f64,
        relief_m: f64,
        peak_m: f64,
        offset_m: f64,
    ) -> (Raster, CatalogueCrater) {
        let crs = LunarCrs::equirectangular(0.0, 0.0);
        let (px, n) = (20.0, 1200);
        let transform = GeoTransform::north_up(-12_000.0, 12_000.0, px);
        let mut dem = Raster::new(n, n, transform, crs.clone(), 0.0);
        for row in 0..n {
            for col in 0..n {
                let (x, y) = transform.pixel_center(col as f64, row as f64);
                let rho = x.hypot(y) / radius_m;
                let z = if rho <= 1.0 {
                    relief_m * ((rho - 0.4) / 0.6).max(0.0) + peak_m * (1.0 - rho / 0.15).max(0.0)
                } else {
                    relief_m * rho.powi(-3)
                };
                dem.data[row * n + col] = (z - 1500.0) as f32;
            }
        }
        let (lon_deg, lat_deg) = crs.to_lonlat_deg(offset_m, 0.0).unwrap();
        let crater = CatalogueCrater {
            lon_deg,
            lat_deg,
            diameter_m: 2.0 * radius_m,
        };
        (dem, crater)
    }

    /// About a centre 10 % of a radius off (a real catalogue's 300 m on a 6 km radius, or more) the relief reads as
    /// about the exact one, within 1 %, even before the frame is refined to the rim: every sector still holds the
    /// rim's crest, and the flat floor's lowest ring is still floor. The ring medians about the offset centre
    /// straddle the rim, and their highest reads it more than 5 % low: the test tells the two crests apart.
    #[test]
    fn a_catalogue_centre_off_by_a_tenth_of_a_radius_reads_the_same_relief() {
        let (radius, relief_m) = (6000.0, 700.0);
        let expected = relief_m / (2.0 * radius);
        // The frame about the catalogued centre, before any refinement to the rim.
        let read = |offset_m: f64| {
            let (dem, _) = rimmed_crater(radius, relief_m, 0.0, 0.0);
            let local = LocalFrame::new(&dem.crs, offset_m, 0.0, 0.0).unwrap();
            let (frame, _) = profile(&dem, (offset_m, 0.0), local.map_to_en, radius).unwrap();
            (frame.relief_to_diameter, frame)
        };
        let (exact, _) = read(0.0);
        assert!(
            (exact - expected).abs() < 0.01 * expected,
            "{exact} against {expected}"
        );
        let (offset, frame) = read(0.1 * radius);
        assert!(
            (offset - expected).abs() < 0.01 * expected,
            "{offset} against {expected}"
        );
        let ring_crest = frame
            .profile_m
            .iter()
            .copied()
            .fold(f64::NEG_INFINITY, f64::max);
        let ring_relief = frame.relief_to_diameter(ring_crest);
        assert!(
            ring_relief < 0.95 * expected,
            "ring medians' crest: {ring_relief} against {expected}"
        );
    }

    /// A catalogue entry 600 m east of the crater (a tenth of its radius) and 5 % wide is refined to the rim the
    /// DEM shows, not to its central peak (which stands 200 m above the rim): centre within 20 m (a post), radius
    /// within 1 %, and a crop's frame then reads as with the exact entry, ρ within 0.005 and its height against the
    /// profile within a ring's rise of the wall (8 m).
    #[test]
    fn a_catalogue_entry_off_centre_and_wide_is_refined_to_the_rim() {
        let (radius, relief_m, peak_m) = (6000.0, 700.0, 900.0);
        let (dem, exact) = rimmed_crater(radius, relief_m, peak_m, 0.0);
        let (_, off) = rimmed_crater(1.05 * radius, relief_m, peak_m, 600.0);
        let frame_of = |crater: CatalogueCrater| {
            let (frames, report) = CraterFrames::new(&dem, &[crater], 1000.0).unwrap();
            assert_eq!((report.framed, report.refined_to_rim), (1, 1), "{report:?}");
            frames
        };
        let (exact, off) = (frame_of(exact), frame_of(off));
        let refined = &off.frames[0];
        assert!(
            refined.centre.0.hypot(refined.centre.1) < 20.0,
            "{refined:?}"
        );
        assert!(
            (refined.radius_m / radius - 1.0).abs() < 0.01,
            "{}",
            refined.radius_m
        );
        for (x, y, z) in [
            (3000.0, 1000.0, 0.0),
            (-4500.0, 2000.0, 300.0),
            (0.0, -7000.0, 250.0),
        ] {
            let (a, b) = (
                exact.position(x, y, z).unwrap(),
                off.position(x, y, z).unwrap(),
            );
            assert!((a.rho - b.rho).abs() < 0.005, "{a:?} {b:?}");
            assert!(
                (a.relative_height_m - b.relative_height_m).abs() < 8.0,
                "{a:?} {b:?}"
            );
            let relief = (a.relief_to_diameter.unwrap(), b.relief_to_diameter.unwrap());
            assert!((relief.0 - relief.1).abs() < 0.01 * relief.0, "{relief:?}");
        }
    }

    /// Where the DEM shows no crater (a catalogue's false entry on rolling plains) no circle fits the sectors'
    /// highest points, and the catalogue's centre and diameter stand.
    #[test]
    fn an_entry_the_dem_shows_no_crater_for_keeps_the_catalogues_frame() {
        let (mut dem, crater) = rimmed_crater(6000.0, 700.0, 0.0, 0.0);
        for row in 0..dem.height {
            for col in 0..dem.width {
                let (x, y) = dem.transform.pixel_center(col as f64, row as f64);
                dem.data[row * dem.width + col] = (-1500.0
                    + 60.0 * (x / 2300.0).sin() * (y / 1700.0).cos()
                    + 15.0 * (x / 370.0 + y / 530.0).sin())
                    as f32;
            }
        }
        let (frames, report) = CraterFrames::new(&dem, &[crater], 1000.0).unwrap();
        assert_eq!((report.framed, report.refined_to_rim), (1, 0), "{report:?}");
        let frame = &frames.frames[0];
        assert!(
            frame.centre.0.hypot(frame.centre.1) < 1e-6,
            "{:?}",
            frame.centre
        );
        assert_eq!(frame.radius_m, 6000.0);
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

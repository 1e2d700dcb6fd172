//! Per-pixel scene geometry in a local ENU frame: DEM normals, illumination/viewing cosines, Rusinkiewicz angles.
//!
//! All cosines come from dot products of unit vectors (never `acos` then `cos`) and are clamped to [-1, 1], because
//! rounding can push a dot product of unit vectors a hair outside that interval.

use glam::DVec3;

use crate::science::crs::LocalFrame;
use crate::science::raster::GeoTransform;

/// Surface normals (ENU, unit, pointing up) of a `width × height` crop from heights with a 1-pixel apron.
///
/// `heights_with_apron` is row-major `(width + 2) × (height + 2)`, north row first, covering the crop plus one
/// pixel on every side, so central differences at the crop border are as exact as in the interior.
/// `transform` is the georeferencing of the *apron* grid's pixel (0, 0); `frame` the crop's local ENU frame.
/// Heights are turned into ENU points first (Jacobian + sphere curvature), so normals are expressed in `frame`.
pub fn crop_normals_enu(
    heights_with_apron: &[f32],
    width: usize,
    height: usize,
    transform: &GeoTransform,
    frame: &LocalFrame,
) -> Vec<DVec3> {
    let aw = width + 2;
    assert_eq!(
        heights_with_apron.len(),
        aw * (height + 2),
        "heights must carry a 1-pixel apron"
    );
    let enu = |col: usize, row: usize| {
        let (x, y) = transform.pixel_center(col as f64, row as f64);
        frame.map_to_enu(x, y, heights_with_apron[row * aw + col] as f64)
    };
    let mut normals = Vec::with_capacity(width * height);
    for row in 1..=height {
        for col in 1..=width {
            normals.push(central_difference_normal(&enu, col, row));
        }
    }
    normals
}

/// Unit normal at (col, row) from the ENU points of its four neighbours (upward for a north-up grid).
fn central_difference_normal(
    point: &impl Fn(usize, usize) -> DVec3,
    col: usize,
    row: usize,
) -> DVec3 {
    let toward_east = point(col + 1, row) - point(col - 1, row);
    let toward_south = point(col, row + 1) - point(col, row - 1);
    toward_south.cross(toward_east).normalize()
}

/// How a training sample's grid sits in its crop's local ENU frame: what the renderer (scalar here, batched in
/// `train`) needs to turn stored relative heights into ENU points without the map CRS.
///
/// Model: apron-grid cell (col, row) of an `n × n` grid centred on the frame origin has map offset
/// `d = ((col + ½ − n/2)·gsd, −(row + ½ − n/2)·gsd)`; its ground offset at the origin height is `J·d`
/// (J = `map_to_en`), scaled by `(ρ0 + Δh)/ρ0` for a point Δh above the origin (radial lines spread with height),
/// and it sits `|J·d|²/(2ρ0)` below the origin's tangent plane (sphere curvature), ρ0 = R + origin height.
/// Compared with the exact frame ([`crop_normals_enu`] through [`LocalFrame`]) only the Jacobian's variation
/// across the crop is dropped: ≈ d·tan(lat)/R = 1.8e-4 at the edge of a 640 m crop at Tycho's latitude, which
/// moves cos i by ≤ 1.1e-4 on very rough terrain (tested), three orders below the noise of a 5 m stereo DEM.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CropGrid {
    pub gsd_m: f64,
    /// `[de/dx, de/dy, dn/dx, dn/dy]`, map metres → ground metres.
    pub map_to_en: [f64; 4],
    pub origin_height_m: f64,
}

impl CropGrid {
    /// Radius of the frame origin from the body centre, metres.
    pub fn origin_radius_m(&self) -> f64 {
        crate::science::crs::MOON_RADIUS_M + self.origin_height_m
    }

    /// Ground (east, north) at the origin height of apron-grid cell centre (col, row) in an `n`-cell grid.
    pub fn ground_offset(&self, col: usize, row: usize, n: usize) -> (f64, f64) {
        let (dx, dy) = self.map_offset(col, row, n);
        let j = &self.map_to_en;
        (j[0] * dx + j[1] * dy, j[2] * dx + j[3] * dy)
    }

    /// Map offset (dx, dy) in metres of cell (col, row) of an `n × n` crop from the crop centre (pixel centres;
    /// rows run north to south).
    pub fn map_offset(&self, col: usize, row: usize, n: usize) -> (f64, f64) {
        let half = n as f64 / 2.0;
        (
            (col as f64 + 0.5 - half) * self.gsd_m,
            -(row as f64 + 0.5 - half) * self.gsd_m,
        )
    }

    /// ENU point of cell (col, row) whose height is `relative_height_m` above the origin's.
    pub fn enu_point(&self, col: usize, row: usize, n: usize, relative_height_m: f64) -> DVec3 {
        let (e, north) = self.ground_offset(col, row, n);
        let rho0 = self.origin_radius_m();
        let spread = (rho0 + relative_height_m) / rho0;
        let drop = (e * e + north * north) / (2.0 * rho0);
        DVec3::new(e * spread, north * spread, relative_height_m - drop)
    }
}

/// Per-pixel geometry of one crop: what every BRDF of the family needs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelGeometry {
    pub cosines: Cosines,
    pub half_diff: HalfDiffCosines,
}

/// Geometry of every pixel of an `n × n` crop (row-major, north first) from `(n + 2)²` heights with a 1-px apron
/// *relative to the frame origin*, the sun direction and the camera position in the crop's ENU frame.
/// This is the scalar reference the batched renderer layer in `train` is held equal to.
pub fn crop_pixel_geometry(
    relative_heights_with_apron: &[f64],
    n: usize,
    grid: &CropGrid,
    sun_dir_enu: DVec3,
    camera_pos_enu: DVec3,
) -> Vec<PixelGeometry> {
    crop_pixel_frames(relative_heights_with_apron, n, grid, camera_pos_enu)
        .map(|(normal, view_dir)| PixelGeometry {
            cosines: Cosines::new(normal, sun_dir_enu, view_dir),
            half_diff: HalfDiffCosines::new(normal, sun_dir_enu, view_dir),
        })
        .collect()
}

/// The unit normal and the unit view direction (surface → camera) of every pixel of an `n × n` crop, row-major,
/// from `(n + 2)²` apron heights: what [`crop_pixel_geometry`] builds its cosines from, for callers that need
/// only some of them. Each ENU point is computed once (the normals' central differences share them).
pub fn crop_pixel_frames<'a>(
    relative_heights_with_apron: &'a [f64],
    n: usize,
    grid: &'a CropGrid,
    camera_pos_enu: DVec3,
) -> impl Iterator<Item = (DVec3, DVec3)> + 'a {
    let an = n + 2;
    assert_eq!(
        relative_heights_with_apron.len(),
        an * an,
        "heights must carry a 1-pixel apron"
    );
    let points: std::sync::Arc<[DVec3]> = (0..an * an)
        .map(|k| grid.enu_point(k % an, k / an, an, relative_heights_with_apron[k]))
        .collect();
    (1..=n).flat_map(move |row| {
        let points = std::sync::Arc::clone(&points);
        (1..=n).map(move |col| {
            let point = |c: usize, r: usize| points[r * an + c];
            let normal = central_difference_normal(&point, col, row);
            (normal, (camera_pos_enu - point(col, row)).normalize())
        })
    })
}

/// Angle between two directions, radians, in the atan2 form: accurate for tiny and near-π angles, where acos of
/// a dot product loses half the digits.
pub fn angle_between(a: DVec3, b: DVec3) -> f64 {
    a.cross(b).length().atan2(a.dot(b))
}

/// Unit normal of a plane z = a·east + b·north: the one home of "normal from two slopes" (the synthetic world's
/// ortho renderer, inference's parameter maps, the novel-view ray caster, evaluation's mean slope, analytic
/// tests). Crops take theirs from ENU points instead ([`crop_normals_enu`]), which carry the sphere's curvature exactly.
pub fn plane_normal(dz_deast: f64, dz_dnorth: f64) -> DVec3 {
    DVec3::new(-dz_deast, -dz_dnorth, 1.0).normalize()
}

/// The three cosines every model needs, from unit vectors.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Cosines {
    /// cos of incidence i = n·s.
    pub cos_i: f64,
    /// cos of emission e = n·v.
    pub cos_e: f64,
    /// cos of phase g = s·v.
    pub cos_g: f64,
}

#[inline]
pub fn clamp_unit(x: f64) -> f64 {
    x.clamp(-1.0, 1.0)
}

impl Cosines {
    /// `normal`, `sun_dir` and `view_dir` must be unit vectors; `view_dir` points from the surface to the camera.
    #[inline]
    pub fn new(normal: DVec3, sun_dir: DVec3, view_dir: DVec3) -> Self {
        Self {
            cos_i: clamp_unit(normal.dot(sun_dir)),
            cos_e: clamp_unit(normal.dot(view_dir)),
            cos_g: clamp_unit(sun_dir.dot(view_dir)),
        }
    }
}

/// Rusinkiewicz (1998) half/difference parametrisation as cosines, for the M6 model.
///
/// The tangent reference for the azimuths is local east projected onto the tangent plane (north if the normal is
/// horizontal-east). Azimuths are undefined when the half vector is along the normal (θh = 0) or the sun is along
/// the half vector (θd = 0, i.e. g = 0); they are defined by continuity there as cos φ = 1, never a 0/0.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HalfDiffCosines {
    pub cos_theta_h: f64,
    pub cos_theta_d: f64,
    pub cos_phi_h: f64,
    pub cos_phi_d: f64,
}

const DEGENERATE: f64 = 1e-12;

impl HalfDiffCosines {
    pub fn new(normal: DVec3, sun_dir: DVec3, view_dir: DVec3) -> Self {
        let sum = sun_dir + view_dir;
        // s = -v (g = 180°) has no half vector; the normal is the continuous choice for lunar geometries.
        let half = if sum.length_squared() > DEGENERATE {
            sum.normalize()
        } else {
            normal
        };
        let reference = if DVec3::X.cross(normal).length_squared() > 1e-6 {
            DVec3::X
        } else {
            DVec3::Y
        };
        let tangent = (reference - normal * reference.dot(normal)).normalize();
        let bitangent = normal.cross(tangent);
        let (hx, hy, hz) = (
            half.dot(tangent),
            half.dot(bitangent),
            clamp_unit(half.dot(normal)),
        );
        let h_planar = (hx * hx + hy * hy).sqrt();
        let (cos_phi_h, sin_phi_h) = if h_planar > DEGENERATE {
            (hx / h_planar, hy / h_planar)
        } else {
            (1.0, 0.0)
        };
        let (cos_theta_h, sin_theta_h) = (hz, h_planar.min(1.0));
        // Rotate the sun vector into the frame where the half vector is the pole: by -φh about n, then -θh about b.
        let (sx, sy, sz) = (
            sun_dir.dot(tangent),
            sun_dir.dot(bitangent),
            sun_dir.dot(normal),
        );
        let (x1, y1) = (
            cos_phi_h * sx + sin_phi_h * sy,
            -sin_phi_h * sx + cos_phi_h * sy,
        );
        let dx = cos_theta_h * x1 - sin_theta_h * sz;
        let d_planar = (dx * dx + y1 * y1).sqrt();
        let cos_phi_d = if d_planar > DEGENERATE {
            clamp_unit(dx / d_planar)
        } else {
            1.0
        };
        Self {
            cos_theta_h,
            cos_theta_d: clamp_unit(sun_dir.dot(half)),
            cos_phi_h: clamp_unit(cos_phi_h),
            cos_phi_d,
        }
    }
}

/// Spacecraft position at along-track fraction `t` ∈ [0, 1] between the strip's start and stop positions
/// (body-fixed). Interpolates on a circular arc (slerp of the direction, linear radius): exact for a circular orbit,
/// where a straight chord would sag by L²/8r (≈ 7 m for a 10 km strip at 50 km altitude).
pub fn spacecraft_position_at(start_body: DVec3, stop_body: DVec3, t: f64) -> DVec3 {
    let (r0, r1) = (start_body.length(), stop_body.length());
    let (u0, u1) = (start_body / r0, stop_body / r1);
    let omega = clamp_unit(u0.dot(u1)).acos();
    let dir = if omega < 1e-12 {
        u0
    } else {
        (u0 * ((1.0 - t) * omega).sin() + u1 * (t * omega).sin()) / omega.sin()
    };
    dir.normalize() * (r0 + (r1 - r0) * t)
}

/// Along-track fraction `t` at which a pushbroom camera on a circular orbit from `start_body` to `stop_body` images
/// `ground_body` (zero pitch: the point is seen when it lies in the plane through the spacecraft perpendicular to
/// the velocity). `t` is the angle of the ground point's projection on the orbit plane over the arc angle; it may
/// fall slightly outside [0, 1] at the strip ends.
pub fn imaging_fraction(ground_body: DVec3, start_body: DVec3, stop_body: DVec3) -> f64 {
    let u0 = start_body.normalize();
    // Start and stop in the same direction (a zero-length strip, up to rounding): everything is imaged at t = 0.
    let perpendicular = stop_body - u0 * stop_body.dot(u0);
    if perpendicular.length() <= 1e-9 * stop_body.length() {
        return 0.0;
    }
    let along = perpendicular.normalize();
    let omega = stop_body
        .normalize()
        .dot(along)
        .atan2(stop_body.normalize().dot(u0));
    let theta = ground_body.dot(along).atan2(ground_body.dot(u0));
    if omega.abs() < 1e-15 {
        0.0
    } else {
        theta / omega
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::science::crs::LunarCrs;

    #[test]
    fn imaging_fraction_inverts_spacecraft_position() {
        let r = crate::science::crs::MOON_RADIUS_M + 50_000.0;
        let a = DVec3::new(r, 0.0, 0.0);
        let b = DVec3::new(
            r * deg(0.4).cos(),
            r * deg(0.4).sin() * 0.6,
            r * deg(0.4).sin() * 0.8,
        );
        for t in [0.0, 0.25, 0.5, 0.9] {
            // A ground point below the spacecraft, displaced cross-track (as a slewed camera sees it).
            let sc = spacecraft_position_at(a, b, t);
            let cross = a.cross(b).normalize();
            let ground = sc.normalize() * crate::science::crs::MOON_RADIUS_M + cross * 8_000.0;
            let got = imaging_fraction(ground, a, b);
            // 1e-9 of a 12 km arc is 12 µm: f64 rounding of 1.7e6 m vectors, far below any pixel.
            assert!((got - t).abs() < 1e-9, "t={t}: {got}");
        }
        assert_eq!(
            imaging_fraction(a * 0.5, a, a * 1.0001),
            0.0,
            "degenerate strip gives t = 0, not NaN"
        );
    }

    fn deg(x: f64) -> f64 {
        x.to_radians()
    }

    #[test]
    fn tilted_plane_normals_match_hand_computation() {
        // A plane rising 0.1 m per m toward east and falling 0.05 m per m toward north, sampled at 5 m.
        let crs = LunarCrs::equirectangular(0.0, 0.0);
        let gsd = 5.0;
        let (w, h) = (4, 3);
        let transform = GeoTransform::north_up(
            -(w as f64 + 2.0) * gsd / 2.0,
            (h as f64 + 2.0) * gsd / 2.0,
            gsd,
        );
        let frame = LocalFrame::new(&crs, 0.0, 0.0, 100.0).unwrap();
        let mut heights = Vec::new();
        for row in 0..h + 2 {
            for col in 0..w + 2 {
                let (x, y) = transform.pixel_center(col as f64, row as f64);
                // Heights are above the sphere; the normal is relative to the local vertical at the crop centre.
                let e = frame.map_to_enu(x, y, 0.0);
                heights.push((100.0 + 0.1 * e.x - 0.05 * e.y) as f32);
            }
        }
        let normals = crop_normals_enu(&heights, w, h, &transform, &frame);
        let expected = plane_normal(0.1, -0.05);
        for n in normals {
            // Each cell's own curvature drop is folded in, so a plane of heights reads as a plane within ~1e-5.
            assert!((n - expected).length() < 2e-5, "{n:?} vs {expected:?}");
        }
    }

    #[test]
    fn crop_grid_normals_match_the_exact_frame_at_tycho() {
        // A rough synthetic crop at Tycho's latitude in an equirectangular CRS whose true-scale latitude is 2° away
        // (east scale 0.97): the sample-level model (centre Jacobian + spread + curvature) against the exact route.
        let crs = LunarCrs::equirectangular(-41.3, -11.36);
        let (x0, y0) = crs.from_lonlat_deg(-11.36, -43.31).unwrap();
        let (n, gsd, h0) = (128usize, 5.0, -1200.0);
        let an = n + 2;
        let transform =
            GeoTransform::north_up(x0 - an as f64 / 2.0 * gsd, y0 + an as f64 / 2.0 * gsd, gsd);
        let frame = LocalFrame::new(&crs, x0, y0, h0).unwrap();
        // Slopes up to ~75° (300 m waves of 85 m wavelength) on a tilted plane.
        let heights: Vec<f32> = (0..an * an)
            .map(|k| {
                let (c, r) = ((k % an) as f64, (k / an) as f64);
                (h0 + 300.0 * (c / 17.0).sin() * (r / 23.0).cos() + 2.0 * c - 1.5 * r) as f32
            })
            .collect();
        let exact = crop_normals_enu(&heights, n, n, &transform, &frame);
        let grid = CropGrid {
            gsd_m: gsd,
            map_to_en: [
                frame.map_to_en[0][0],
                frame.map_to_en[0][1],
                frame.map_to_en[1][0],
                frame.map_to_en[1][1],
            ],
            origin_height_m: h0,
        };
        let relative: Vec<f64> = heights.iter().map(|&h| h as f64 - h0).collect();
        let sun = DVec3::new(0.5, 0.1, 0.8).normalize();
        let model = crop_pixel_geometry(&relative, n, &grid, sun, DVec3::new(0.0, 0.0, 50_000.0));
        let worst = exact
            .iter()
            .zip(&model)
            .map(|(e, m)| (e.dot(sun) - m.cosines.cos_i).abs())
            .fold(0.0, f64::max);
        // Dropped: the Jacobian's change across the crop, ε ≈ d·tan(lat)/R = 1.8e-4 at the edge, both as a scale
        // change and as a rotation of the grid lines; each tilts a normal by ≤ ε·|∇h|/(1+|∇h|²) ≤ ε/2, so
        // |Δ cos i| ≤ ε = 1.8e-4 (measured 6.3e-5 on the plane alone, 1.1e-4 with the waves). A sign or axis
        // error in the model shows up at 1e-2.
        assert!(worst < 1.8e-4, "cos i differs by {worst}");
    }

    #[test]
    fn cosines_of_known_sun_and_camera() {
        // Sun 60° from zenith toward east, camera at nadir: flat ground gives i = 60°, e = 0, g = 60°.
        let n = DVec3::Z;
        let s = DVec3::new(deg(60.0).sin(), 0.0, deg(60.0).cos());
        let c = Cosines::new(n, s, DVec3::Z);
        assert!((c.cos_i - 0.5).abs() < 1e-15 && c.cos_e == 1.0 && (c.cos_g - 0.5).abs() < 1e-15);
        // A 20° east-facing slope: i = 40°, e = 20°, g unchanged.
        let n = DVec3::new(deg(20.0).sin(), 0.0, deg(20.0).cos());
        let c = Cosines::new(n, s, DVec3::Z);
        assert!((c.cos_i - deg(40.0).cos()).abs() < 1e-14);
        assert!((c.cos_e - deg(20.0).cos()).abs() < 1e-14);
    }

    #[test]
    fn sun_and_camera_vectors_from_body_fixed_positions() {
        // A crop at Tycho; the sun placed 1 AU away at incidence 60° toward local east, the spacecraft 50 km
        // above a point 5 km north: expect i = 60° on flat ground and a view vector tilted 5.7° toward north.
        let crs = LunarCrs::equirectangular(-43.31, -11.36);
        let (x, y) = crs.from_lonlat_deg(-11.36, -43.31).unwrap();
        let frame = LocalFrame::new(&crs, x, y, -1200.0).unwrap();
        let toward_sun = DVec3::new(deg(60.0).sin(), 0.0, deg(60.0).cos());
        let sun_body = frame.origin_body + frame.body_to_enu.transpose() * toward_sun * 1.496e11;
        let s = frame.sun_dir_enu(sun_body);
        assert!((s - toward_sun).length() < 1e-9);
        let camera_body = crs.body_fixed(x, y + 5000.0, -1200.0 + 50_000.0).unwrap();
        let v = frame.body_point_to_enu(camera_body).normalize();
        let c = Cosines::new(DVec3::Z, s, v);
        assert!((c.cos_i - 0.5).abs() < 1e-9);
        // Exact on the sphere: the equirectangular y offset of 5 km is an arc θ = 5000/R; the camera sits at radius
        // Rc = R − 1200 + 50 000 above it, the crop at R0 = R − 1200. (Flat-Earth atan(0.1) would be 0.16° off.)
        let theta = 5000.0 / crate::science::crs::MOON_RADIUS_M;
        let (rc, r0) = (
            crate::science::crs::MOON_RADIUS_M + 48_800.0,
            crate::science::crs::MOON_RADIUS_M - 1200.0,
        );
        let expected = (rc * theta.sin()).atan2(rc * theta.cos() - r0);
        assert!(
            (c.cos_e - expected.cos()).abs() < 1e-9,
            "cos e {} vs {}",
            c.cos_e,
            expected.cos()
        );
        assert!(v.y > 0.0 && v.x.abs() < 1e-6, "camera is due north: {v:?}");
    }

    #[test]
    fn half_diff_angles_reduce_correctly() {
        // Specular configuration: s and v mirror each other about n → θh = 0, θd = i.
        let n = DVec3::Z;
        let s = DVec3::new(deg(30.0).sin(), 0.0, deg(30.0).cos());
        let v = DVec3::new(-deg(30.0).sin(), 0.0, deg(30.0).cos());
        let hd = HalfDiffCosines::new(n, s, v);
        assert!((hd.cos_theta_h - 1.0).abs() < 1e-15);
        assert!((hd.cos_theta_d - deg(30.0).cos()).abs() < 1e-14);
        assert_eq!(hd.cos_phi_h, 1.0, "φh is defined by continuity at θh = 0");
        // Nadir camera and zenith sun: everything aligned; all azimuths by continuity, no NaN.
        let hd = HalfDiffCosines::new(n, n, n);
        assert_eq!(
            (hd.cos_theta_h, hd.cos_theta_d, hd.cos_phi_h, hd.cos_phi_d),
            (1.0, 1.0, 1.0, 1.0)
        );
        // Retro-reflection (g = 0) off-normal: θd = 0 so φd is by continuity, θh = i.
        let hd = HalfDiffCosines::new(n, s, s);
        assert!((hd.cos_theta_h - deg(30.0).cos()).abs() < 1e-14 && hd.cos_phi_d == 1.0);
    }

    #[test]
    fn half_diff_matches_angle_based_formula_generic_case() {
        // Independent route: explicit angles with acos/atan2 and rotation matrices, valid away from degeneracies.
        let n = DVec3::Z;
        let s = DVec3::new(0.3, 0.2, 0.9).normalize();
        let v = DVec3::new(-0.1, 0.4, 0.8).normalize();
        let h = (s + v).normalize();
        let theta_h = h.z.acos();
        let phi_h = h.y.atan2(h.x);
        let rot_z = |a: f64, p: DVec3| {
            DVec3::new(
                a.cos() * p.x - a.sin() * p.y,
                a.sin() * p.x + a.cos() * p.y,
                p.z,
            )
        };
        let rot_y = |a: f64, p: DVec3| {
            DVec3::new(
                a.cos() * p.x + a.sin() * p.z,
                p.y,
                -a.sin() * p.x + a.cos() * p.z,
            )
        };
        let d = rot_y(-theta_h, rot_z(-phi_h, s));
        let phi_d = d.y.atan2(d.x);
        let hd = HalfDiffCosines::new(n, s, v);
        assert!((hd.cos_theta_h - theta_h.cos()).abs() < 1e-12);
        assert!((hd.cos_phi_h - phi_h.cos()).abs() < 1e-12);
        assert!((hd.cos_theta_d - d.z).abs() < 1e-12);
        assert!((hd.cos_phi_d - phi_d.cos()).abs() < 1e-12);
    }

    #[test]
    fn spacecraft_interpolation_stays_on_the_orbit() {
        let r = crate::science::crs::MOON_RADIUS_M + 50_000.0;
        let a = DVec3::new(r, 0.0, 0.0);
        let b = DVec3::new(r * deg(1.0).cos(), 0.0, r * deg(1.0).sin());
        let mid = spacecraft_position_at(a, b, 0.5);
        assert!((mid.length() - r).abs() < 1e-6);
        assert!((mid.z.atan2(mid.x) - deg(0.5)).abs() < 1e-12);
    }
}

//! Synthetic crops with a known answer: a bowl-shaped crater on a plain, rendered under drawn sun and camera
//! geometry. `bench` measures on them (no dataset needed), and the tests build their fixtures from them.

use dataset::contract::crater_frame::CraterPosition;
use dataset::contract::schema::{ContextWindow, Sample, Split, CONTEXT_PX, CROP_PX, DEM_PX};
use dataset::science::brdf::{render_crop, BrdfModel};
use dataset::science::geometry::{crop_pixel_geometry, CropGrid};
use rand::Rng;

use crate::data::{HostBatch, InputNormalisation};

/// A DEM GeoTIFF-ready raster for inference tests: `width × height` cells of 5 m in the Tycho region's
/// equirectangular CRS, a gently undulating plain at `base_height_m` with one parabolic bowl in its middle (radius
/// a quarter of the shorter side, depth a fifth of the radius).
pub fn bowl_dem(
    width: usize,
    height: usize,
    base_height_m: f64,
) -> dataset::science::raster::Raster {
    use dataset::science::crs::LunarCrs;
    use dataset::science::raster::{GeoTransform, Raster};
    let gsd = 5.0;
    let mut r = Raster::new(
        width,
        height,
        GeoTransform::north_up(-(width as f64) * gsd / 2.0, -1_309_000.0, gsd),
        LunarCrs::equirectangular(-43.31, -11.36),
        0.0,
    );
    let (cx, cy) = (width as f64 * gsd / 2.0, height as f64 * gsd / 2.0);
    let radius = width.min(height) as f64 * gsd / 4.0;
    for row in 0..height {
        for col in 0..width {
            let (x, y) = (col as f64 * gsd, row as f64 * gsd);
            let d = (x - cx).hypot(y - cy) / radius;
            let bowl = if d < 1.0 {
                -0.2 * radius * (1.0 - d * d)
            } else {
                0.0
            };
            r.data[row * width + col] =
                (base_height_m + 12.0 * (x / 210.0).sin() * (y / 160.0).cos() + bowl) as f32;
        }
    }
    r
}

/// Synthetic samples for benches and tests: smooth random terrain, a sun at 60° incidence from a random azimuth,
/// a camera 50 km up and up to 3 km off-nadir, every 11th pixel invalid, every 13th half lit. The image is
/// rendered by the scalar reference with a smooth "true" M2 parameter field, so a network can fit it exactly.
pub fn synthetic_samples(n: usize, seed: u64) -> Vec<Sample> {
    let mut rng = dataset::contract::rng::keyed_rng(seed, "synthetic-samples", 0);
    let origin_height_m = -1200.0;
    (0..n)
        .map(|i| {
            let (fx, fy, amp): (f64, f64, f64) = (
                rng.random_range(5.0..30.0),
                rng.random_range(5.0..30.0),
                rng.random_range(5.0..60.0),
            );
            let relative: Vec<f64> = (0..DEM_PX * DEM_PX)
                .map(|k| {
                    let (c, r) = ((k % DEM_PX) as f64, (k / DEM_PX) as f64);
                    amp * (c / fx).sin() * (r / fy).cos() + 0.1 * c
                })
                .collect();
            let azimuth: f64 = rng.random_range(0.0..std::f64::consts::TAU);
            let (si, ci) = 60f64.to_radians().sin_cos();
            let sun = [si * azimuth.cos(), si * azimuth.sin(), ci];
            let camera = [
                rng.random_range(-3000.0..3000.0),
                rng.random_range(-3000.0..3000.0),
                50_000.0,
            ];
            let grid = CropGrid {
                gsd_m: 5.0,
                map_to_en: [0.97, 0.01, -0.01, 1.0],
                origin_height_m,
            };
            let geometry =
                crop_pixel_geometry(&relative, CROP_PX, &grid, sun.into(), camera.into());
            let npx = CROP_PX * CROP_PX;
            let truth: Vec<f64> = (0..3 * npx)
                .map(|k| {
                    let p = k % npx;
                    let (c, r) = ((p % CROP_PX) as f64, (p / CROP_PX) as f64);
                    [0.25 + 0.05 * (c / 9.0).sin() * (r / 13.0).cos(), 0.02, 0.01][k / npx]
                })
                .collect();
            let lit: Vec<f64> = (0..npx)
                .map(|k| if k % 13 == 0 { 0.5 } else { 1.0 })
                .collect();
            let valid: Vec<u8> = (0..npx).map(|k| u8::from(k % 11 != 0)).collect();
            let image = render_crop(BrdfModel::M2, &truth, &geometry, &lit, 1.0);
            Sample {
                sample_id: format!("synthetic:{seed}:{i}"),
                split: Split::Train,
                tile_id: "t0".into(),
                ortho_id: "synthetic".into(),
                center_x_m: 0.0,
                center_y_m: 0.0,
                center_lon_deg: 0.0,
                center_lat_deg: 0.0,
                footprint_lonlat_deg: [0.0; 8],
                dem_m: relative
                    .iter()
                    .map(|h| (h + origin_height_m) as f32)
                    .collect(),
                image: image
                    .iter()
                    .zip(&valid)
                    .map(|(&v, &ok)| if ok != 0 { v as f32 } else { 0.0 })
                    .collect(),
                valid,
                sun_lit: lit.iter().map(|&v| v as f32).collect(),
                sun_dir_enu: sun,
                camera_pos_enu_m: camera,
                enu_origin_height_m: origin_height_m,
                map_to_en: grid.map_to_en,
                camera_att: [1.0, 0.0, 0.0, 0.0],
                fov_deg: 2.85,
                gsd_m: 5.0,
                incidence_deg: 60.0,
                emission_deg: 0.0,
                phase_deg: 60.0,
                acq_time: "2026-01-01T00:00:00Z".into(),
                provenance: "synthetic".into(),
                context: Some(ContextWindow {
                    gsd_m: 512.0,
                    heights_m: vec![origin_height_m as f32; CONTEXT_PX * CONTEXT_PX],
                    // Highland on the east of the window, mare on the west, the boundary moving with the sample;
                    // the first row unmapped.
                    highland: Some(
                        (0..CONTEXT_PX * CONTEXT_PX)
                            .map(|k| match (k / CONTEXT_PX, k % CONTEXT_PX) {
                                (0, _) => f32::NAN,
                                (_, col) => {
                                    f32::from(u8::from(col + i % CONTEXT_PX >= CONTEXT_PX / 2))
                                }
                            })
                            .collect(),
                    ),
                }),
                crater: Some(CraterPosition {
                    rho: 0.2 * i as f64,
                    relative_height_m: 30.0 * i as f64 - 60.0,
                    relief_to_diameter: Some(0.04 + 0.01 * i as f64),
                }),
            }
        })
        .collect()
}

/// A host batch of [`synthetic_samples`] (DEM std 20 m).
pub fn synthetic_batch(n: usize, seed: u64) -> HostBatch {
    HostBatch::from_samples(
        &synthetic_samples(n, seed),
        &InputNormalisation::relief(20.0),
    )
}

//! Test and bench fixtures: synthetic samples with a known answer, hard geometric cases, parameter fields, and
//! synthetic datasets on disk. Used by this crate's tests, `bench`, and the workspace tests; never by training.

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
                }),
                crater: Some(CraterPosition {
                    rho: 0.2 * i as f64,
                    relative_height_m: 30.0 * i as f64 - 60.0,
                }),
            }
        })
        .collect()
}

/// The stability suite's hard geometries, one sample each: grazing sun (i = 89.9°, most facets face away),
/// zenith sun with a nadir camera over flat ground (M6's half vector on the normal: azimuths by continuity),
/// retro-reflection (sun behind the camera, g ≈ 0), a fully shadowed crop, and a crop with no valid pixel.
pub fn hard_case_samples() -> Vec<Sample> {
    let base = synthetic_samples(5, 11);
    let flat = |mut s: Sample| {
        s.dem_m = vec![s.enu_origin_height_m as f32; DEM_PX * DEM_PX];
        s.map_to_en = [1.0, 0.0, 0.0, 1.0];
        s
    };
    let (si, ci) = 89.9f64.to_radians().sin_cos();
    let mut grazing = base[0].clone();
    grazing.sun_dir_enu = [si, 0.0, ci];
    let mut nadir = flat(base[1].clone());
    nadir.sun_dir_enu = [0.0, 0.0, 1.0];
    nadir.camera_pos_enu_m = [0.0, 0.0, 50_000.0];
    let mut retro = base[2].clone();
    let cam = glam::DVec3::from(retro.camera_pos_enu_m);
    retro.sun_dir_enu = cam.normalize().into();
    let mut shadowed = base[3].clone();
    shadowed.sun_lit = vec![0.0; CROP_PX * CROP_PX];
    let mut invalid = base[4].clone();
    invalid.valid = vec![0; CROP_PX * CROP_PX];
    invalid.image = vec![0.0; CROP_PX * CROP_PX];
    vec![grazing, nadir, retro, shadowed, invalid]
}

/// Raw parameter maps `N × P × 128²` for tests: smooth, of both signs (LeakyReLU's negative side is exercised),
/// kept ≥ 1e-2 away from the kink at 0 so finite differences (step 1e-3) never straddle it.
pub fn test_params(model: BrdfModel, n: usize, seed: u64) -> Vec<f64> {
    let mut rng = dataset::contract::rng::keyed_rng(seed, "test-params", 0);
    let npx = CROP_PX * CROP_PX;
    (0..n * model.param_count())
        .flat_map(|_| {
            let (a, f): (f64, f64) = (rng.random_range(-0.5..0.5), rng.random_range(3.0..20.0));
            (0..npx).map(move |p| {
                let v = a + 0.2 * ((p % CROP_PX) as f64 / f).sin();
                if v.abs() < 1e-2 {
                    1e-2
                } else {
                    v
                }
            })
        })
        .collect()
}

/// Publish `train` and `val` samples as a dataset directory (one shard each; DEM std 20 m) for tests.
pub fn write_synthetic_dataset(dir: &std::path::Path, train: Vec<Sample>, val: Vec<Sample>) {
    let splits: Vec<(&str, Vec<Vec<Sample>>)> = [(Split::Train, train), (Split::Val, val)]
        .into_iter()
        .map(|(split, mut samples)| {
            samples.iter_mut().for_each(|s| s.split = split);
            (split.name(), vec![samples])
        })
        .collect();
    dataset::testing::write_dataset(dir, "synthetic", &splits, serde_json::Value::Null)
        .expect("writing a synthetic dataset");
}

/// [`write_synthetic_dataset`] of `train_rows` and `val_rows` [`synthetic_samples`] (seeds 5 and 6) into `dir`,
/// opened as a sample source.
pub fn synthetic_source(
    dir: &std::path::Path,
    train_rows: usize,
    val_rows: usize,
) -> std::sync::Arc<dyn crate::data::SampleSource> {
    write_synthetic_dataset(
        dir,
        synthetic_samples(train_rows, 5),
        synthetic_samples(val_rows, 6),
    );
    std::sync::Arc::new(crate::data::LocalSource::open(dir).expect("opening a synthetic dataset"))
}

/// Copy a directory tree (a run directory, to resume one checkpoint two ways).
pub fn copy_dir(from: &std::path::Path, to: &std::path::Path) {
    std::fs::create_dir_all(to).expect("creating a copy");
    for entry in std::fs::read_dir(from).expect("reading a directory to copy") {
        let entry = entry.expect("listing a directory to copy");
        let target = to.join(entry.file_name());
        if entry.file_type().expect("file type").is_dir() {
            copy_dir(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), target).expect("copying a file");
        }
    }
}

/// A host batch of [`synthetic_samples`] (DEM std 20 m).
pub fn synthetic_batch(n: usize, seed: u64) -> HostBatch {
    HostBatch::from_samples(
        &synthetic_samples(n, seed),
        &InputNormalisation::relief(20.0),
    )
}

/// A crater level of one band `rho_min ≤ ρ < rho_max` whose regression predicts the same H1 scale for every crop
/// (`scale`), at `weight`: what the level does is then known in closed form.
pub fn constant_crater_level(
    rho_min: f64,
    rho_max: f64,
    scale: f64,
    weight: f64,
) -> crate::crater_level::CraterLevel {
    use crate::crater_level::{BandLevel, CraterLevel, LevelRegression};
    CraterLevel::from_bands(vec![BandLevel {
        regression: LevelRegression {
            rho_min,
            rho_max,
            step_centre_m: 0.0,
            step_width_m: 50.0,
            coefficients: [scale.ln(), 0.0, 0.0, 0.0],
            train_crops: 100,
            train_rms_log: 0.1,
        },
        weight,
        val_level_oracle_sse_ratio: f64::NAN,
    }])
}

//! Test fixtures (the `testing` feature, which only dev-dependencies turn on): hard geometric cases, parameter
//! fields, synthetic datasets on disk, and the [`crate::synthetic`] crops they are built from. Never in a release
//! build.

pub use crate::synthetic::{bowl_dem, synthetic_batch, synthetic_samples};

use dataset::contract::schema::{Sample, Split, CROP_PX, DEM_PX};
use dataset::science::brdf::BrdfModel;
use rand::Rng;

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

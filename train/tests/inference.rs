//! Seamless large-DEM inference: no visible crop seams at the default overlap (but visible without overlap, so the
//! score can fail), and output pixels exactly on the DEM's grid, checked through GDAL by map coordinates.

use burn::backend::Flex;
use burn::prelude::*;
use dataset::contract::schema::{Sample, CROP_PX};
use dataset::science::brdf::BrdfModel;
use dataset::science::crs::LunarCrs;
use dataset::science::raster::{read_bands, write_raster, GeoTransform, Raster};
use train::augment::Dihedral;
use train::data::HostBatch;
use train::data::{
    ContextNormalisation, ElevationNormalisation, InputNormalisation, CONTEXT_CHANNELS,
};
use train::inference::{
    infer_params, render_maps, seam_score, write_params_geotiff, InferOptions, ParamMaps,
    DEFAULT_OVERLAP,
};
use train::model::{UNet, UNetConfig};
use train::prediction::{predict_images, predict_images_symmetry_mean};
use train::testing::synthetic_samples;

type B = Flex;

/// A smooth cratered DEM, 5 m/px, with a nodata hole; `origin_x` places column 0.
fn dem(width: usize, height: usize, col0: usize) -> Raster {
    let transform = GeoTransform::north_up(-800.0 + col0 as f64 * 5.0, -1_309_000.0, 5.0);
    let mut r = Raster::new(
        width,
        height,
        transform,
        LunarCrs::equirectangular(-43.31, -11.36),
        0.0,
    );
    for row in 0..height {
        for c in 0..width {
            let (x, y) = ((c + col0) as f64 * 5.0, row as f64 * 5.0);
            let bowl = |cx: f64, cy: f64, radius: f64, depth: f64| {
                let d = ((x - cx).powi(2) + (y - cy).powi(2)).sqrt() / radius;
                if d < 1.0 {
                    -depth * (1.0 - d * d)
                } else {
                    0.0
                }
            };
            r.data[row * width + c] = (-1200.0
                + 15.0 * (x / 230.0).sin() * (y / 170.0).cos()
                + 4.0 * (x / 37.0 + y / 53.0).sin()
                + bowl(900.0, 700.0, 260.0, 40.0)
                + bowl(1650.0, 1100.0, 120.0, 18.0)) as f32;
        }
    }
    // A hole the output must carry as nodata.
    for row in 200..206 {
        for c in 300usize.saturating_sub(col0)..(306usize.saturating_sub(col0)) {
            r.data[row * width + c] = f32::NAN;
        }
    }
    r
}

/// A width-4 U-Net with a random head (a zero head would output constants and hide any seam).
fn random_net() -> UNet<B> {
    random_net_with_inputs(1)
}

fn random_net_with_inputs(in_channels: usize) -> UNet<B> {
    random_net_with(in_channels, 0)
}

fn random_net_with(in_channels: usize, context_channels: usize) -> UNet<B> {
    random_net_seeded(in_channels, context_channels, 7)
}

/// The backend RNG is process-wide: every test seeds and initialises its networks under this one lock, so parallel
/// tests cannot draw from each other's stream.
static INIT: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn random_net_seeded(in_channels: usize, context_channels: usize, seed: u64) -> UNet<B> {
    let _guard = INIT.lock().unwrap_or_else(|e| e.into_inner());
    let device = Default::default();
    B::seed(&device, seed);
    let net = UNetConfig::new(BrdfModel::M2.param_count())
        .with_in_channels(in_channels)
        .with_context_channels(context_channels)
        .with_base_width(4)
        .init::<B>(&device);
    let _ = net.num_params(); // Burn initialises lazily: materialise every weight under the lock
    net
}

/// Largest change of any parameter at the pixels `keep` selects (by index); a pixel with a value in one map and
/// NaN (nodata) in the other counts as an infinite change.
fn max_abs_diff_where(a: &ParamMaps, b: &ParamMaps, keep: impl Fn(usize) -> bool) -> f64 {
    a.bands
        .iter()
        .zip(&b.bands)
        .flat_map(|(x, y)| x.iter().zip(y).enumerate())
        .filter(|&(k, (x, y))| keep(k) && !(x.is_nan() && y.is_nan()))
        .map(|(_, (x, y))| {
            if x.is_nan() || y.is_nan() {
                f64::INFINITY
            } else {
                f64::from((x - y).abs())
            }
        })
        .fold(0f64, f64::max)
}

fn infer(net: &UNet<B>, dem: &Raster, overlap: usize) -> ParamMaps {
    infer_with(net, dem, overlap, InputNormalisation::relief(20.0))
}

fn infer_with(net: &UNet<B>, dem: &Raster, overlap: usize, input: InputNormalisation) -> ParamMaps {
    infer_framed(net, dem, overlap, input, None).unwrap()
}

#[test]
fn default_overlap_hides_crop_seams_that_hard_tiles_show() {
    let net = random_net();
    let dem = dem(416, 320, 0);
    let sun = [0.55, 0.25, 0.8];
    let hard = infer(&net, &dem, 0);
    let blended = infer(&net, &dem, DEFAULT_OVERLAP);
    let hard_score = seam_score(&render_maps(&hard, &dem, sun), 416, 320, 0);
    let blended_score = seam_score(&render_maps(&blended, &dem, sun), 416, 320, DEFAULT_OVERLAP);
    eprintln!(
        "seam score: hard tiles {hard_score:.3}, overlap {DEFAULT_OVERLAP}: {blended_score:.3}"
    );
    assert!(
        hard_score > 1.05,
        "the test needs a network whose hard tiles show seams: {hard_score}"
    );
    assert!(
        blended_score <= 1.05,
        "seams visible at the default overlap: {blended_score}"
    );

    // Nodata follows the DEM; everything else is finite.
    for band in &blended.bands {
        assert!(band[200 * 416 + 302].is_nan());
        assert_eq!(band.iter().filter(|v| v.is_nan()).count(), 36);
    }
}

#[test]
fn parameter_geotiff_sits_on_the_dem_grid_to_the_pixel() {
    let net = random_net();
    let dir = tempfile::tempdir().unwrap();
    // The full DEM and the same terrain starting 96 columns (one stride at the default overlap) further east:
    // both tilings then cut identical crops, so identical map points must get identical parameters.
    let (full, east) = (dem(416, 320, 0), dem(320, 320, 96));
    let (full_tif, east_tif) = (dir.path().join("full.tif"), dir.path().join("east.tif"));
    write_raster(&dir.path().join("dem.tif"), &full, &[]).unwrap();
    write_params_geotiff(
        &infer(&net, &full, DEFAULT_OVERLAP),
        &full,
        DEFAULT_OVERLAP,
        &full_tif,
    )
    .unwrap();
    write_params_geotiff(
        &infer(&net, &east, DEFAULT_OVERLAP),
        &east,
        DEFAULT_OVERLAP,
        &east_tif,
    )
    .unwrap();

    let (a, b) = (
        read_bands(&full_tif).unwrap(),
        read_bands(&east_tif).unwrap(),
    );
    let dem_back = read_bands(&dir.path().join("dem.tif")).unwrap().remove(0);
    assert_eq!(a.len(), 3);
    assert_eq!(a[0].transform, dem_back.transform, "output grid = DEM grid");
    assert_eq!((a[0].width, a[0].height), (416, 320));
    assert_eq!(a[0].crs, dem_back.crs);
    assert!(
        a[2].description.contains("coefficient of 1") && a[2].description.contains("LeakyReLU")
    );
    let (mut compared, mut worst_aligned, mut shifted_sq) = (0, 0f32, 0f64);
    for (band_a, band_b) in a.iter().zip(&b) {
        for row in 0..320 {
            // Columns only crops inside both DEMs reach: the east DEM's first crop (starting in its reflect padding,
            // full column 64) differs from the full DEM's crop there and reaches full column 191.
            for c in 192..416 {
                let (x, y) = band_a.transform.pixel_center(c as f64, row as f64);
                let (cb, rb) = band_b.transform.map_to_pixel(x, y);
                assert_eq!(
                    (cb.fract(), rb.fract()),
                    (0.0, 0.0),
                    "pixel centres must coincide"
                );
                let (va, vb) = (band_a.get(c, row), band_b.get(cb as usize, rb as usize));
                // The same map point one pixel east in the other raster: what a georeferencing shift would compare.
                let vs = band_b.get((cb as usize + 1).min(319), rb as usize);
                if va.is_nan() {
                    assert!(vb.is_nan());
                    continue;
                }
                worst_aligned = worst_aligned.max((va - vb).abs());
                if vs.is_finite() {
                    shifted_sq += ((va - vs) as f64).powi(2);
                }
                compared += 1;
            }
        }
    }
    assert!(compared > 3 * 220 * 300);
    let shifted_rms = (shifted_sq / compared as f64).sqrt();
    eprintln!("aligned: max |diff| {worst_aligned:e}; one pixel off: rms diff {shifted_rms:e}");
    assert!(
        worst_aligned <= 1e-6,
        "same map point, different parameters: {worst_aligned}"
    );
    assert!(
        shifted_rms > 20.0 * worst_aligned.max(1e-9) as f64,
        "a one-pixel shift must be visible above the aligned difference ({shifted_rms} vs {worst_aligned})"
    );
}

/// Relief alone is blind to where a crop sits: lifting the whole DEM changes nothing. The elevation plane sees it,
/// so the same lift changes the parameters; and a hole stays nodata either way.
#[test]
fn elevation_plane_makes_parameters_depend_on_absolute_height_and_relief_alone_does_not() {
    let low = dem(320, 240, 0);
    let mut high = low.clone();
    // +64 m keeps every height in the same f32 binade (|h| in 1024..2048), so the lift is exact.
    for z in high.data.iter_mut() {
        *z += 64.0;
    }
    let max_abs_diff = |a: &ParamMaps, b: &ParamMaps| max_abs_diff_where(a, b, |_| true);
    let relief = random_net();
    let (a, b) = (infer(&relief, &low, 32), infer(&relief, &high, 32));
    assert_eq!(
        max_abs_diff(&a, &b),
        0.0,
        "relief input moved with a uniform lift"
    );

    let input = InputNormalisation {
        dem_std_m: 20.0,
        elevation: Some(ElevationNormalisation {
            mean_m: -1200.0,
            std_m: 50.0,
        }),
        context: None,
    };
    let both = random_net_with_inputs(2);
    let (a, b) = (
        infer_with(&both, &low, 32, input),
        infer_with(&both, &high, 32, input),
    );
    let moved = max_abs_diff(&a, &b);
    assert!(
        moved > 1e-3,
        "the elevation plane did not reach the network: max change {moved:e}"
    );
    let hole = 203 * 320 + 302;
    assert!(a
        .bands
        .iter()
        .chain(&b.bands)
        .all(|band| band[hole].is_nan()));
}

/// Relief with a 32 × 60 m context window (1.9 km), and a crater plane over `crater_rms_m` when given.
fn context_input(crater_rms_m: Option<f64>) -> InputNormalisation {
    InputNormalisation {
        dem_std_m: 20.0,
        elevation: None,
        context: Some(ContextNormalisation {
            gsd_m: 60.0,
            std_m: 25.0,
            absolute: false,
            crater_rms_m,
            crater_frame: false,
            crater_relief: None,
            units: false,
        }),
    }
}

/// Terrain beyond a crop but inside its context window reaches a context network's parameters there, and not a
/// network without context: a +30 m mound at columns 180–239 is outside every crop that covers columns 0–63, but
/// inside their 32 × 60 m = 1.9 km context windows.
#[test]
fn context_input_makes_parameters_depend_on_terrain_beyond_the_crop() {
    let plain = dem(320, 240, 0);
    let mut mound = plain.clone();
    for row in 0..100 {
        for col in 180..240 {
            mound.data[row * 320 + col] += 30.0;
        }
    }
    // Pixels the mound's crops never cover: columns 0–63 (crops there span columns −32…95).
    let max_abs_diff_left =
        |a: &ParamMaps, b: &ParamMaps| max_abs_diff_where(a, b, |k| k % 320 < 64);
    let relief = random_net();
    let (a, b) = (infer(&relief, &plain, 32), infer(&relief, &mound, 32));
    assert_eq!(
        max_abs_diff_left(&a, &b),
        0.0,
        "relief input saw beyond its crop"
    );

    let input = context_input(None);
    let with_context = random_net_with(1, CONTEXT_CHANNELS);
    let (a, b) = (
        infer_with(&with_context, &plain, 32, input),
        infer_with(&with_context, &mound, 32, input),
    );
    let moved = max_abs_diff_left(&a, &b);
    assert!(
        moved > 1e-3,
        "the context window did not reach the network: max change {moved:e}"
    );
}

/// Largest absolute difference between two equally long renderings.
fn max_abs_diff(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

/// Every image of a batch turned by `d`.
fn turn_images(images: &[f64], d: Dihedral) -> Vec<f64> {
    images
        .chunks(CROP_PX * CROP_PX)
        .flat_map(|image| d.apply_raster(image, CROP_PX))
        .collect()
}

/// Test-time symmetry averaging is the 8-member ensemble it claims: it equals the mean of the 8 single passes on
/// turned samples, turned back (an independent path through the renderer's own equivariance, M2), and it is
/// equivariant: turning the samples turns its renderings. A single pass of the random network is far from
/// equivariant, so the second check can fail.
#[test]
fn symmetry_mean_is_an_equivariant_ensemble_of_the_eight_views() {
    let samples = synthetic_samples(2, 5);
    let input = InputNormalisation {
        dem_std_m: 20.0,
        elevation: None,
        context: Some(ContextNormalisation {
            gsd_m: 512.0,
            std_m: 150.0,
            absolute: false,
            crater_rms_m: None,
            crater_frame: false,
            crater_relief: None,
            units: false,
        }),
    };
    let net = random_net_with(1, CONTEXT_CHANNELS);
    let device = Default::default();
    let model = BrdfModel::M2;
    let single =
        |s: &[Sample]| predict_images(&net, model, &HostBatch::from_samples(s, &input), &device);
    let averaged = |s: &[Sample]| predict_images_symmetry_mean(&net, model, s, &input, &device);
    let turned = |d: Dihedral| -> Vec<Sample> { samples.iter().map(|s| d.apply(s)).collect() };

    let mean = averaged(&samples);
    let scale = mean.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    assert!(scale > 0.0 && mean.iter().all(|v| v.is_finite()));
    let mut ensemble = vec![0.0; mean.len()];
    for d in Dihedral::all() {
        for (e, b) in ensemble
            .iter_mut()
            .zip(turn_images(&single(&turned(d)), d.inverse()))
        {
            *e += b / 8.0;
        }
    }
    let off = max_abs_diff(&mean, &ensemble);
    assert!(
        off <= 1e-6 * scale,
        "not the 8-view mean: {off:e} of {scale:e}"
    );

    let plain = single(&samples);
    let (mut averaged_worst, mut single_worst) = (0.0f64, 0.0f64);
    for d in Dihedral::all().skip(1) {
        averaged_worst =
            averaged_worst.max(max_abs_diff(&averaged(&turned(d)), &turn_images(&mean, d)));
        single_worst = single_worst.max(max_abs_diff(&single(&turned(d)), &turn_images(&plain, d)));
    }
    eprintln!(
        "ensemble {off:e} averaged {averaged_worst:e} single {single_worst:e} scale {scale:e}"
    );
    assert!(
        averaged_worst <= 1e-6 * scale,
        "averaged predictor not equivariant: {averaged_worst:e} of {scale:e}"
    );
    // The network's own asymmetry must dwarf what the check lets through, or the check proves nothing.
    assert!(
        single_worst > 100.0 * averaged_worst.max(1e-7 * scale),
        "a single pass is about as equivariant ({single_worst:e}) as the averaged one ({averaged_worst:e})"
    );
}

/// `infer --ensemble`: the mean maps render exactly as the mean of the members' renderings (what `eval --ensemble`
/// scores), nodata stays nodata, and runs of different BRDF models are refused.
#[test]
fn ensemble_maps_render_as_the_mean_of_the_members_renderings() {
    let dem = dem(320, 224, 0); // holds the 6 × 6 hole at rows 200.., columns 300..
    let sun = [0.55, 0.25, 0.8];
    let members: Vec<ParamMaps> = [7, 8]
        .into_iter()
        .map(|seed| infer(&random_net_seeded(1, 0, seed), &dem, DEFAULT_OVERLAP))
        .collect();
    let renders: Vec<Vec<f64>> = members.iter().map(|m| render_maps(m, &dem, sun)).collect();
    let spread = max_abs_diff(&renders[0], &renders[1]);
    assert!(spread > 1e-3, "members render alike: {spread:e}");
    let mean = ParamMaps::mean(members).unwrap();
    let rendered = render_maps(&mean, &dem, sun);
    let scale = renders[0]
        .iter()
        .chain(&renders[1])
        .filter(|v| v.is_finite())
        .fold(0f64, |m, v| m.max(v.abs()));
    let mut nodata = 0;
    for (k, r) in rendered.iter().enumerate() {
        let expected = 0.5 * (renders[0][k] + renders[1][k]);
        if !dem.data[k].is_finite() {
            assert!(
                mean.bands.iter().all(|b| b[k].is_nan()),
                "pixel {k} must stay nodata"
            );
            nodata += 1;
        } else if expected.is_finite() {
            // The maps are f32: agreement to f32 rounding of the parameters.
            assert!(
                (r - expected).abs() <= 1e-6 * scale,
                "pixel {k}: {r} vs {expected}"
            );
        }
    }
    assert_eq!(nodata, 36);

    let mut other = infer(&random_net(), &dem, DEFAULT_OVERLAP);
    other.model = BrdfModel::L3;
    let err = ParamMaps::mean(vec![mean, other])
        .err()
        .expect("mixed models refused");
    assert!(err.to_string().contains("one BRDF model"), "{err}");
}

/// `infer_params` with batches of 4 and `frames` as the DEM's crater frames.
fn infer_framed(
    net: &UNet<B>,
    dem: &Raster,
    overlap: usize,
    input: InputNormalisation,
    frames: Option<dataset::contract::crater_frame::CraterFrames>,
) -> anyhow::Result<ParamMaps> {
    let options = InferOptions {
        overlap,
        batch_size: 4,
        input,
        crater_frames: frames.map(std::sync::Arc::new),
        unit_map: None,
        crater_level: None,
        input_range: None,
        clamp_crater_relief: false,
    };
    infer_params(
        net,
        BrdfModel::M2,
        dem,
        &options,
        &Default::default(),
        |_, _| {},
    )
}

/// The frames of one catalogued crater `diameter_m` across, centred `east_m` east and `south_m` south of the test
/// DEM's grid corner (the DEM spans 1.6 × 1.2 km at 5 m).
fn one_crater(
    dem: &Raster,
    east_m: f64,
    south_m: f64,
    diameter_m: f64,
) -> dataset::contract::crater_frame::CraterFrames {
    use dataset::contract::crater_frame::{CatalogueCrater, CraterFrames};
    let (lon_deg, lat_deg) = dem
        .crs
        .to_lonlat_deg(-800.0 + east_m, -1_309_000.0 - south_m)
        .unwrap();
    let crater = CatalogueCrater {
        lon_deg,
        lat_deg,
        diameter_m,
    };
    let (frames, report) = CraterFrames::new(dem, &[crater], 10.0).unwrap();
    assert_eq!(report.framed, 1);
    frames
}

/// A run that feeds the crater input refuses a DEM without crater frames, naming the flag, and with them its
/// maps follow where the catalogue puts the crater: the same DEM with the crater's catalogued centre moved by
/// 100 m gives other parameters (the crops' heights against the crater's profile change, nothing else does).
#[test]
fn a_crater_input_needs_the_catalogue_and_follows_where_it_puts_the_crater() {
    let dem = dem(320, 240, 0);
    let input = context_input(Some(20.0));
    let net = random_net_with(1, CONTEXT_CHANNELS + 1);
    let err = infer_framed(&net, &dem, 32, input, None)
        .err()
        .expect("refused without crater frames")
        .to_string();
    assert!(err.contains("--crater-catalogue"), "{err}");
    // The DEM's larger bowl: 260 m across its radius, centred 900 m east and 700 m south of the grid's corner.
    let run = |east_m: f64| {
        infer_framed(
            &net,
            &dem,
            32,
            input,
            Some(one_crater(&dem, 900.0 + east_m, 700.0, 520.0)),
        )
        .unwrap()
    };
    let change = max_abs_diff_where(&run(0.0), &run(100.0), |_| true);
    assert!(
        change > 1e-3 && change.is_finite(),
        "the crater plane did not reach the network: max change {change:e}"
    );
}

/// A run that feeds the crater input as a frame runs without a catalogue, every crop unframed, and a catalogue
/// whose crater lies past the frame's reach (3 radii) from every crop gives exactly those maps; one in reach gives
/// others.
#[test]
fn a_crater_frame_input_runs_without_a_catalogue_as_with_craters_out_of_reach() {
    let dem = dem(320, 240, 0);
    let mut input = context_input(Some(20.0));
    input.context.as_mut().unwrap().crater_frame = true;
    assert_eq!(input.context_channels(), CONTEXT_CHANNELS + 3);
    let net = random_net_with(1, CONTEXT_CHANNELS + 3);
    let run = |frames| infer_framed(&net, &dem, 32, input, frames).unwrap();
    let without = run(None);
    // A 60 m crater midway between four crop centres: each centre lies 113 m, 3.8 radii, from it.
    let small = one_crater(&dem, 880.0, 560.0, 60.0);
    let starts = |len: usize| train::inference::crop_starts(len, 32);
    for r0 in starts(dem.height) {
        for c0 in starts(dem.width) {
            let (x, y) = dem.transform.pixel_edge(c0 as f64 + 32.0, r0 as f64 + 32.0);
            let at = small.position(x, y, 0.0).unwrap();
            assert!(
                at.rho > 3.0,
                "a crop centre {} radii from the crater",
                at.rho
            );
        }
    }
    assert_eq!(
        max_abs_diff_where(&without, &run(Some(small)), |_| true),
        0.0
    );
    let in_reach = run(Some(one_crater(&dem, 900.0, 700.0, 520.0)));
    let change = max_abs_diff_where(&without, &in_reach, |_| true);
    assert!(
        change > 1e-3 && change.is_finite(),
        "the frame planes did not reach the network: max change {change:e}"
    );
}

/// Two crops' worth of rolling terrain (without the shared DEM's hole), the frames of a 1 km crater centred on
/// column 40, row 64 (crop 0's centre, column 64, lies 120 m east of it), and an H1 network started as `fit`
/// starts it, at a uniform scale of 1, so its level is known and positive.
fn two_crops_beside_a_crater() -> (
    Raster,
    std::sync::Arc<dataset::contract::crater_frame::CraterFrames>,
    UNet<B>,
) {
    use dataset::contract::crater_frame::{CatalogueCrater, CraterFrames};
    let dem = {
        let mut r = Raster::new(
            256,
            128,
            GeoTransform::north_up(-800.0, -1_309_000.0, 5.0),
            LunarCrs::equirectangular(-43.31, -11.36),
            0.0,
        );
        for (k, z) in r.data.iter_mut().enumerate() {
            let (x, y) = ((k % 256) as f64 * 5.0, (k / 256) as f64 * 5.0);
            *z = (-1200.0
                + 15.0 * (x / 230.0).sin() * (y / 170.0).cos()
                + 4.0 * (x / 37.0 + y / 53.0).sin()) as f32;
        }
        r
    };
    let net = {
        let _guard = INIT.lock().unwrap_or_else(|e| e.into_inner());
        let device = Default::default();
        B::seed(&device, 11);
        UNetConfig::new(BrdfModel::H1.param_count())
            .with_base_width(4)
            .init::<B>(&device)
            .with_uniform_head(&[1.0], &device)
    };
    let (lon_deg, lat_deg) = dem
        .crs
        .to_lonlat_deg(-800.0 + 40.0 * 5.0, -1_309_000.0 - 64.0 * 5.0)
        .unwrap();
    let crater = CatalogueCrater {
        lon_deg,
        lat_deg,
        diameter_m: 1000.0,
    };
    let (frames, report) = CraterFrames::new(&dem, &[crater], 100.0).unwrap();
    assert_eq!(report.framed, 1);
    (dem, std::sync::Arc::new(frames), net)
}

/// A run's crater level sets the level of the crops in its band and leaves the others as the network made them.
/// Two side-by-side crops at overlap 0 (so no blending: each pixel is one crop's): the crop centred 0.24 radii
/// from a catalogued crater is in the band ρ < 1, the one 1.5 radii away is not. At weight 1 the near crop's mean
/// H1 scale becomes the regression's (0.4), at weight ½ the geometric mean of that and the network's, and the far
/// crop is untouched; without crater frames nothing is applied and the maps say so.
#[test]
fn a_crater_level_sets_the_level_of_the_crops_in_its_band_only() {
    use dataset::contract::crater_frame::CraterFrames;
    use train::crater_level::CraterLevel;
    let (dem, frames, net) = two_crops_beside_a_crater();
    let level = |weight: f64| train::testing::constant_crater_level(0.0, 1.0, 0.4, weight);
    let run = |frames: Option<std::sync::Arc<CraterFrames>>, level: Option<CraterLevel>| {
        let options = InferOptions {
            overlap: 0,
            batch_size: 4,
            input: InputNormalisation::relief(20.0),
            crater_frames: frames,
            unit_map: None,
            crater_level: level,
            input_range: None,
            clamp_crater_relief: false,
        };
        infer_params(
            &net,
            BrdfModel::H1,
            &dem,
            &options,
            &Default::default(),
            |_, _| {},
        )
        .unwrap()
    };
    let block_mean = |maps: &ParamMaps, crop: usize| {
        let (sum, n) = (0..128 * 128)
            .map(|k| maps.bands[0][(k / 128) * 256 + crop * 128 + k % 128] as f64)
            .fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
        sum / n as f64
    };
    let network = run(None, None);
    assert_eq!(network.crater_level_crops, None);
    let without_frames = run(None, Some(level(1.0)));
    assert_eq!(
        without_frames.crater_level_crops, None,
        "nothing to place the crops with"
    );
    assert_eq!(max_abs_diff_where(&network, &without_frames, |_| true), 0.0);

    let full = run(Some(frames.clone()), Some(level(1.0)));
    assert_eq!(full.crater_level_crops, Some(1));
    let m = block_mean(&network, 0);
    assert!(
        m > 0.0 && (m - 0.4).abs() > 1e-3,
        "the network's own level {m}"
    );
    assert!(
        (block_mean(&full, 0) - 0.4).abs() < 1e-6,
        "{}",
        block_mean(&full, 0)
    );
    let far = |k: usize| k % 256 >= 128;
    assert_eq!(
        max_abs_diff_where(&network, &full, far),
        0.0,
        "the far crop is left alone"
    );

    let half = run(Some(frames), Some(level(0.5)));
    let expected = (0.4 * m).sqrt();
    assert!((block_mean(&half, 0) - expected).abs() < 1e-6 * expected);
}

/// `report`'s overlap rows run the network as `infer` runs it: with the catalogue's frames, the run's crater level
/// sets the crops `infer` sets, at each overlap; without frames it is left out, and the rows say so.
#[test]
fn report_overlap_rows_apply_the_crater_level_as_infer_does() {
    let (dem, frames, net) = two_crops_beside_a_crater();
    let options = |frames| InferOptions {
        overlap: 0,
        batch_size: 4,
        input: InputNormalisation::relief(20.0),
        crater_frames: frames,
        unit_map: None,
        crater_level: Some(train::testing::constant_crater_level(0.0, 1.0, 0.4, 1.0)),
        input_range: None,
        clamp_crater_relief: false,
    };
    let device = Default::default();
    let overlaps = [0, 16];
    let rows = train::report::overlap_rows::<B>(
        &net,
        BrdfModel::H1,
        &dem,
        &options(Some(frames.clone())),
        &overlaps,
        &device,
    )
    .unwrap();
    for (row, overlap) in rows.iter().zip(overlaps) {
        let infer = InferOptions {
            overlap,
            ..options(Some(frames.clone()))
        };
        let maps = infer_params(&net, BrdfModel::H1, &dem, &infer, &device, |_, _| {}).unwrap();
        assert_eq!(row.crops, maps.crops, "overlap {overlap}");
        assert!(
            matches!(row.crater_level_crops, Some(n) if n >= 1),
            "{row:?}"
        );
        assert_eq!(
            row.crater_level_crops, maps.crater_level_crops,
            "overlap {overlap}"
        );
    }
    let without = train::report::overlap_rows::<B>(
        &net,
        BrdfModel::H1,
        &dem,
        &options(None),
        &overlaps,
        &device,
    )
    .unwrap();
    assert!(without.iter().all(|r| r.crater_level_crops.is_none()));
}

/// `infer` frames a new DEM's craters as the run's training crops were framed: the minimum diameter defaults to
/// the one its `normalisation.json` records (its dataset manifest's crater frame), another one is refused naming
/// the flag, and a run with no record takes the pipeline's default (15 km), which refuses the catalogue's 520 m
/// crater, while the flag's 100 m frames it.
#[test]
fn infer_frames_craters_with_the_minimum_diameter_the_run_was_trained_with() {
    use dataset::contract::manifest::CraterFrameSource;
    use train::inference::crater_frames_for_runs;
    use train::run_dir::RunNormalisation;
    let dem = dem(320, 240, 0);
    let dir = tempfile::tempdir().unwrap();
    let catalogue = dir.path().join("craters.csv");
    let (lon_deg, lat_deg) = dem.crs.to_lonlat_deg(-800.0 + 900.0, -1_309_700.0).unwrap();
    std::fs::write(
        &catalogue,
        format!("lon_deg,lat_deg,diameter_m\n{lon_deg},{lat_deg},520\n"),
    )
    .unwrap();
    let run_with = |name: &str, min_diameter_m: Option<f64>| {
        let run = dir.path().join(name);
        std::fs::create_dir_all(&run).unwrap();
        let record = RunNormalisation {
            input: context_input(Some(20.0)),
            dataset: "test".into(),
            crater_frame: min_diameter_m.map(|min_diameter_m| CraterFrameSource {
                catalogue: "craters.csv".into(),
                catalogue_blake3: dataset::files::hash_file(&catalogue).unwrap(),
                min_diameter_m,
                catalogue_error: None,
            }),
        };
        dataset::files::write_json_atomic(&run.join("normalisation.json"), &record).unwrap();
        run
    };
    let framed = run_with("framed", Some(300.0));
    let frames = crater_frames_for_runs(&[&framed], &dem, &catalogue, None).unwrap();
    assert!(!frames.is_empty());
    crater_frames_for_runs(&[&framed], &dem, &catalogue, Some(300.0)).unwrap();
    let Err(err) = crater_frames_for_runs(&[&framed], &dem, &catalogue, Some(100.0)) else {
        panic!("another minimum diameter is refused");
    };
    let err = err.to_string();
    assert!(
        err.contains("--crater-frame-min-diameter-m 100") && err.contains("300"),
        "{err}"
    );
    let other = run_with("other", Some(100.0));
    let Err(err) = crater_frames_for_runs(&[&framed, &other], &dem, &catalogue, None) else {
        panic!("an ensemble framed two ways is refused");
    };
    let err = err.to_string();
    assert!(err.contains("ensemble"), "{err}");
    let unrecorded = run_with("unrecorded", None);
    let Err(err) = crater_frames_for_runs(&[&unrecorded], &dem, &catalogue, None) else {
        panic!("the 15 km default frames no 520 m crater");
    };
    let err = err.to_string();
    assert!(err.contains("15000"), "{err}");
    let frames = crater_frames_for_runs(&[&unrecorded], &dem, &catalogue, Some(100.0)).unwrap();
    assert!(!frames.is_empty());
}

/// A unit-input network reads the unit map `infer` is given: two maps give two outputs, and a map that has no
/// unit anywhere gives exactly what no map gives (every crop fed as unmapped, as the network was trained to).
#[test]
fn a_unit_map_reaches_a_unit_input_network_and_an_unmapped_site_reads_as_no_map() {
    let dem = dem(320, 240, 0);
    let input = InputNormalisation {
        context: context_input(None)
            .context
            .map(|c| ContextNormalisation { units: true, ..c }),
        ..context_input(None)
    };
    assert_eq!(input.context_channels(), CONTEXT_CHANNELS + 2);
    let net = random_net_with(1, CONTEXT_CHANNELS + 2);
    // 10 m cells over the DEM's extent, on its CRS: highland everywhere, east of the middle only, or unmapped.
    let map = |unit: &dyn Fn(usize) -> f32| {
        let mut r = Raster::new(
            160,
            120,
            GeoTransform::north_up(-800.0, -1_309_000.0, 10.0),
            dem.crs.clone(),
            -1.0,
        );
        for (k, v) in r.data.iter_mut().enumerate() {
            *v = unit(k % 160);
        }
        std::sync::Arc::new(r)
    };
    let run = |unit_map: Option<std::sync::Arc<Raster>>| {
        let options = InferOptions {
            overlap: 16,
            batch_size: 4,
            input,
            crater_frames: None,
            unit_map,
            crater_level: None,
            input_range: None,
            clamp_crater_relief: false,
        };
        infer_params(
            &net,
            BrdfModel::M2,
            &dem,
            &options,
            &Default::default(),
            |_, _| {},
        )
        .unwrap()
    };
    let none = run(None);
    let unmapped = run(Some(map(&|_| f32::NAN)));
    assert_eq!(max_abs_diff_where(&none, &unmapped, |_| true), 0.0);
    let highland = run(Some(map(&|_| 1.0)));
    let east = run(Some(map(&|col| f32::from(u8::from(col >= 80)))));
    for (a, b, what) in [
        (&none, &highland, "no map and a highland map"),
        (&highland, &east, "two maps"),
    ] {
        let moved = max_abs_diff_where(a, b, |_| true);
        assert!(
            moved > 1e-3 && moved.is_finite(),
            "{what}: max change {moved:e}"
        );
    }
}

/// `infer` counts every crop once against the run's training range: with overlap 0 on a DEM of whole crops, the crops
/// are the DEM's 128-px tiles, and those whose height std lies above the range are the ones counted above it.
#[test]
fn infer_counts_the_crops_whose_inputs_lie_outside_the_training_range() {
    use train::data::{InputRange, Interval};
    let dem = dem(3 * CROP_PX, 2 * CROP_PX, 0);
    // Each tile's height std over its finite heights, computed here from the DEM.
    let mut stds: Vec<f64> = (0..2)
        .flat_map(|tr| (0..3).map(move |tc| (tc, tr)))
        .map(|(tc, tr)| {
            let heights: Vec<f64> = (0..CROP_PX * CROP_PX)
                .map(|k| {
                    let (c, r) = (tc * CROP_PX + k % CROP_PX, tr * CROP_PX + k / CROP_PX);
                    f64::from(dem.data[r * dem.width + c])
                })
                .filter(|z| z.is_finite()) // the DEM's holes
                .collect();
            let mean = heights.iter().sum::<f64>() / heights.len() as f64;
            (heights.iter().map(|z| (z - mean).powi(2)).sum::<f64>() / heights.len() as f64).sqrt()
        })
        .collect();
    stds.sort_by(f64::total_cmp);
    assert!(stds[2] < stds[3], "tiles of distinct roughness: {stds:?}");
    let range = InputRange {
        crops: 1,
        datasets: vec!["synthetic".into()],
        inputs: [(
            "crop_height_std_m".to_string(),
            Interval {
                min: 0.0,
                max: (stds[2] + stds[3]) / 2.0,
            },
        )]
        .into(),
    };
    let options = InferOptions {
        overlap: 0,
        batch_size: 4,
        input: InputNormalisation::relief(20.0),
        crater_frames: None,
        unit_map: None,
        crater_level: None,
        input_range: Some(range),
        clamp_crater_relief: false,
    };
    let net = random_net();
    let maps = infer_params(
        &net,
        BrdfModel::M2,
        &dem,
        &options,
        &Default::default(),
        |_, _| {},
    )
    .unwrap();
    assert_eq!(maps.crops, 6);
    let report = maps.inputs_outside_training_range.unwrap();
    assert_eq!((report.crops, report.outside_any), (6, 3));
    let count = report.inputs["crop_height_std_m"];
    assert_eq!((count.crops, count.below, count.above), (6, 0, 3));
    assert!(
        (count.seen.max - stds[5]).abs() <= 1e-9 * stds[5],
        "{count:?} against {stds:?}"
    );
    assert!(
        (count.seen.min - stds[0]).abs() <= 1e-9 * stds[0],
        "{count:?} against {stds:?}"
    );
    // Clamping a relief needs a run that feeds one.
    let err = infer_params(
        &net,
        BrdfModel::M2,
        &dem,
        &InferOptions {
            clamp_crater_relief: true,
            ..options
        },
        &Default::default(),
        |_, _| {},
    )
    .err()
    .expect("a relief-only run has no relief to clamp");
    assert!(err.to_string().contains("--crater-relief-input"), "{err}");
}

//! `eval` agrees with the pieces it is made of: the learned row equals training validation on the same split,
//! the paper-normalised Hapke row equals the baseline computed directly, the honest scale is the least-squares
//! one, and the report files (JSON, Markdown, PNG panels) are written.

use burn::backend::Flex;
use burn::module::Module;
use burn::prelude::Backend;
use dataset::contract::schema::{Split, CROP_PX};
use dataset::science::brdf::BrdfModel;
use dataset::science::hapke::HapkeParams;
use train::baseline::{hapke_render, normalise_like_paper};
use train::data::{HostBatch, InputNormalisation, LocalSource, SampleSource, StreamConfig};
use train::evaluation::{evaluate, panel_png, write_report, EvalOptions};
use train::fit_config::FitConfig;
use train::metrics::image_metrics;
use train::model::UNetConfig;
use train::prediction::predict_images;
use train::run_dir::TrainedRun;
use train::testing::{synthetic_samples, write_synthetic_dataset};
use train::training::validate;
use train::uniform_fit::calibrate;

/// The FitConfig of the small untrained M2 networks these tests evaluate.
fn m2_config() -> FitConfig {
    FitConfig {
        version: train::fit_config::FIT_CONFIG_VERSION,
        model: BrdfModel::M2,
        epochs: 1,
        learning_rate: 1e-3,
        base_width: 4,
        dropout: true,
        stream: StreamConfig {
            seed: 1,
            batch_size: 2,
            window_groups: 1,
            augment: false,
            max_samples: None,
        },
        max_val_samples: None,
        lr_schedule: train::fit_config::LrSchedule::Constant,
        elevation_input: false,
        context_input: false,
        ema_decay: None,
        steep_weight: 1.0,
        head_hidden: 0,
        crop_level: false,
        film: false,
        nonnegative_start: false,
        log_coefficients: false,
        weight_decay: None,
        also_train_on: Vec::new(),
        also_validate_on: Vec::new(),
        context_absolute: false,
        crater_input: false,
        crater_frame_input: false,
        crater_relief_input: false,
        unit_input: false,
    }
}

#[test]
fn eval_rows_equal_validation_and_direct_baselines() {
    let dir = tempfile::tempdir().unwrap();
    let val = synthetic_samples(5, 2);
    write_synthetic_dataset(dir.path(), synthetic_samples(6, 1), val.clone());
    let source = LocalSource::open(dir.path()).unwrap();
    let device = Default::default();
    Flex::seed(&device, 3);
    let net = UNetConfig::new(BrdfModel::M2.param_count())
        .with_base_width(4)
        .init::<Flex>(&device);
    let _ = net.num_params();
    let config = m2_config();
    let options = EvalOptions {
        split: Split::Val,
        max_samples: None,
        batch_size: 2,
        calibration_samples: 6,
        panels: 2,
        symmetry_mean: false,
        without_crater_frames: false,
        clamp_crater_relief: false,
    };
    let input = InputNormalisation::relief(source.manifest().dem_std_m);
    let calibration = calibrate(&source, 6, BrdfModel::M2).unwrap();
    // The honest scale is Σxt / Σx² over the train crops' valid pixels.
    let (mut xt, mut xx) = (0.0, 0.0);
    for s in synthetic_samples(6, 1) {
        for ((x, &t), &v) in hapke_render(&s, &HapkeParams::lunar_typical())
            .iter()
            .zip(&s.image)
            .zip(&s.valid)
        {
            if v != 0 {
                xt += x * t as f64;
                xx += x * x;
            }
        }
    }
    assert!((calibration.hapke_scale - xt / xx).abs() <= 1e-12 * (xt / xx).abs());

    let panels = dir.path().join("panels");
    std::fs::create_dir_all(&panels).unwrap();
    let runs = [TrainedRun {
        config,
        input,
        net: net.clone(),
        checkpoint: "best/model.mpk".into(),
        crater_level: None,
        input_range: None,
    }];
    let report = evaluate(
        &runs,
        &source,
        &options,
        calibration,
        None,
        &device,
        |i, sample, renderings| {
            if i < options.panels {
                panel_png(sample, renderings, &panels.join(format!("{i}.png")))?;
            }
            Ok(())
        },
    )
    .unwrap();
    assert_eq!(report.images, 5);
    let names: Vec<&str> = report.methods.iter().map(|m| m.name.as_str()).collect();
    assert_eq!(
        names,
        [
            "learned",
            "learned_paper_norm",
            "model_uniform",
            "hapke_paper",
            "hapke_scaled",
            "lunar_lambert"
        ]
    );

    let matched: Vec<&str> = report.feature_matching.keys().map(String::as_str).collect();
    let expected = [
        "hapke_paper",
        "hapke_scaled",
        "learned",
        "learned_paper_norm",
        "lunar_lambert",
        "model_uniform",
    ];
    assert_eq!(matched, expected);
    assert_eq!(
        matched,
        [
            "hapke_paper",
            "hapke_scaled",
            "learned",
            "learned_paper_norm",
            "lunar_lambert",
            "model_uniform"
        ]
    );
    let validation = validate(&net, BrdfModel::M2, &input, &source, None, 2, &device).unwrap();
    assert_eq!(
        report.methods[0].aggregate, validation,
        "learned row = validation"
    );

    let s = &val[0];
    let truth: Vec<f64> = s.image.iter().map(|&v| v as f64).collect();
    let valid: Vec<bool> = s.valid.iter().map(|&v| v != 0).collect();
    let paper = normalise_like_paper(
        &hapke_render(s, &HapkeParams::lunar_typical()),
        &truth,
        &valid,
    );
    let direct = image_metrics(&paper, &truth, &valid, CROP_PX).unwrap();
    assert_eq!(report.per_image[0].metrics["hapke_paper"], direct);
    assert!(report.hapke_to_oracle_gap_closed.is_none());
    let sse = |name: &str| {
        report
            .methods
            .iter()
            .find(|m| m.name == name)
            .unwrap()
            .aggregate
            .sse
    };
    let ratio = sse("learned") / sse("hapke_paper");
    assert!((report.learned_over_hapke_paper_sse - ratio).abs() < 1e-12);
    let both = sse("learned_paper_norm") / sse("hapke_paper");
    assert!((report.learned_over_hapke_both_paper_norm_sse - both).abs() < 1e-12);
    // learned_paper_norm is the learned rendering put through the paper's normalisation, nothing else.
    let learned = predict_images(
        &net,
        BrdfModel::M2,
        &HostBatch::from_samples(
            &val[..1],
            &InputNormalisation::relief(source.manifest().dem_std_m),
        ),
        &device,
    );
    let direct = image_metrics(
        &normalise_like_paper(&learned, &truth, &valid),
        &truth,
        &valid,
        CROP_PX,
    )
    .unwrap();
    let reported = &report.per_image[0].metrics["learned_paper_norm"];
    assert!(
        (reported.mse - direct.mse).abs() <= 1e-6 * direct.mse,
        "{reported:?} vs {direct:?}"
    );

    let out = dir.path().join("eval");
    write_report(&report, &out).unwrap();
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(json["per_image"].as_array().unwrap().len(), 5);
    let md = std::fs::read_to_string(out.join("metrics.md")).unwrap();
    assert!(
        md.contains("| learned |") && md.contains("No oracle"),
        "{md}"
    );
    let panel = image::open(panels.join("0.png")).unwrap();
    // GT, six methods, |learned − GT|: eight 128-px tiles with 4-px gaps, a label strip above, a scale below.
    assert_eq!(
        (panel.width(), panel.height()),
        (
            8 * 132 - 4,
            train::evaluation::PANEL_HEADER_PX + 128 + train::evaluation::PANEL_FOOTER_PX
        )
    );
    // The tiles' pixels sit below the label strip: the GT tile's first row is the panel's row PANEL_HEADER_PX.
    let panel = panel.to_rgb8();
    let top = train::evaluation::PANEL_HEADER_PX;
    assert!(
        (0..128).any(|x| panel.get_pixel(x, top).0 != [255, 255, 255]),
        "the GT tile does not start below the label strip"
    );
    // With a font (CI installs DejaVu), the strips hold ink: column names above, the scale below.
    if dataset::plot::system_font().is_some() {
        let inked = |rows: std::ops::Range<u32>| {
            rows.flat_map(|y| (0..panel.width()).map(move |x| (x, y)))
                .filter(|&(x, y)| panel.get_pixel(x, y).0[0] < 128)
                .count()
        };
        assert!(inked(0..top) > 100, "no column names");
        assert!(inked(top + 128..panel.height()) > 100, "no scale line");
    }
    assert!(!panels.join("2.png").exists());
}

/// `--ensemble`: "learned" is the pixelwise mean of the members' own renderings (each with its own network), and
/// by convexity no image's squared error exceeds the members' mean.
#[test]
fn ensemble_learned_is_the_mean_of_its_members_renderings() {
    let dir = tempfile::tempdir().unwrap();
    let val = synthetic_samples(4, 2);
    write_synthetic_dataset(dir.path(), synthetic_samples(6, 1), val.clone());
    let source = LocalSource::open(dir.path()).unwrap();
    let device = Default::default();
    let input = InputNormalisation::relief(source.manifest().dem_std_m);
    let runs: Vec<TrainedRun<Flex>> = [5, 6]
        .into_iter()
        .map(|seed| {
            Flex::seed(&device, seed);
            TrainedRun {
                config: m2_config(),
                input,
                net: UNetConfig::new(BrdfModel::M2.param_count())
                    .with_base_width(4)
                    .init::<Flex>(&device),
                checkpoint: format!("seed-{seed}"),
                crater_level: None,
                input_range: None,
            }
        })
        .collect();
    let options = EvalOptions {
        split: Split::Val,
        max_samples: None,
        batch_size: 4,
        calibration_samples: 6,
        panels: 0,
        symmetry_mean: false,
        without_crater_frames: false,
        clamp_crater_relief: false,
    };
    let members: Vec<Vec<f64>> = runs
        .iter()
        .map(|r| {
            predict_images(
                &r.net,
                BrdfModel::M2,
                &HostBatch::from_samples(&val, &input),
                &device,
            )
        })
        .collect();
    let npx = CROP_PX * CROP_PX;
    // The two untrained networks must render differently, or the mean would not be tested.
    let spread = members[0]
        .iter()
        .zip(&members[1])
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    assert!(
        spread > 1e-4,
        "members render alike: max difference {spread:e}"
    );
    let mut seen = 0;
    let report = evaluate(
        &runs,
        &source,
        &options,
        calibrate(&source, 6, BrdfModel::M2).unwrap(),
        None,
        &device,
        |i, sample, renderings| {
            let learned = &renderings.iter().find(|(n, _)| *n == "learned").unwrap().1;
            let range = i * npx..(i + 1) * npx;
            for (k, (&a, &b)) in members[0][range.clone()]
                .iter()
                .zip(&members[1][range])
                .enumerate()
            {
                let mean = 0.5 * (a + b);
                assert!(
                    (learned[k] - mean).abs() <= 1e-12 * mean.abs().max(1e-3),
                    "image {i} pixel {k}"
                );
            }
            let truth: Vec<f64> = sample.image.iter().map(|&v| v as f64).collect();
            let valid: Vec<bool> = sample.valid.iter().map(|&v| v != 0).collect();
            let sse = |r: &[f64]| -> f64 {
                r.iter()
                    .zip(&truth)
                    .zip(&valid)
                    .filter(|(_, &v)| v)
                    .map(|((x, t), _)| (x - t).powi(2))
                    .sum()
            };
            let members_mean = 0.5
                * (sse(&members[0][i * npx..(i + 1) * npx])
                    + sse(&members[1][i * npx..(i + 1) * npx]));
            assert!(sse(learned) <= members_mean * (1.0 + 1e-12), "image {i}");
            seen += 1;
            Ok(())
        },
    )
    .unwrap();
    assert_eq!(
        (seen, report.images, report.learned_ensemble_runs),
        (4, 4, 2)
    );
    let md = train::evaluation::markdown(&report);
    assert!(md.contains("mean of 2 trained runs"), "{md}");
    // The note sits above the table, whose header is followed directly by its rule and rows.
    assert!(
        md.contains("| what it is |\n|---|---|---|---|---|---|\n| learned |"),
        "{md}"
    );
}

#[test]
fn uniform_model_fit_recovers_the_coefficients_that_rendered_the_images() {
    let dir = tempfile::tempdir().unwrap();
    let truth = [0.021, 0.008, 0.004];
    let mut train = synthetic_samples(4, 5);
    for s in &mut train {
        let rendered = train::uniform_fit::model_uniform_render(s, BrdfModel::M2, &truth);
        s.image = rendered.iter().map(|&v| v as f32).collect();
    }
    write_synthetic_dataset(dir.path(), train, synthetic_samples(2, 6));
    let source = LocalSource::open(dir.path()).unwrap();
    let fitted = calibrate(&source, 4, BrdfModel::M2).unwrap().model_uniform;
    for (f, t) in fitted.iter().zip(truth) {
        // Images are stored as f32: agreement to f32 precision of I/F ≈ 0.03.
        assert!((f - t).abs() < 1e-6, "{fitted:?} vs {truth:?}");
    }
}

/// `report` on a tiny dataset: every BRDF model gets a row, H1's uniform fit is exactly the honest scaled Hapke (its
/// one term *is* the Moon-wide Hapke I/F), and the Markdown links a PNG plot that was written.
#[test]
fn report_rows_cover_every_model_and_the_plot_is_written() {
    let dir = tempfile::tempdir().unwrap();
    write_synthetic_dataset(dir.path(), synthetic_samples(6, 1), synthetic_samples(3, 2));
    let source = LocalSource::open(dir.path()).unwrap();
    let (rows, images, pixels, geometry_ns) =
        train::report::brdf_model_rows(&source, Split::Val, None, 6).unwrap();
    assert_eq!(images, 3);
    let names: Vec<&str> = rows.iter().map(|r| r.name.as_str()).collect();
    for model in BrdfModel::ALL {
        assert!(
            names.contains(&format!("{} uniform", model.name()).as_str()),
            "{names:?}"
        );
    }
    let mse = |name: &str| rows.iter().find(|r| r.name == name).unwrap().pixel_mse;
    let (h1, hapke) = (mse("h1 uniform"), mse("Hapke (uniform, scaled)"));
    assert!((h1 - hapke).abs() <= 1e-9 * hapke, "{h1:e} vs {hapke:e}");
    let report = train::report::Report {
        split: Split::Val,
        images,
        pixels,
        calibration_samples: 6,
        geometry_ns_per_pixel: geometry_ns,
        brdf_models: rows,
        inference_overlap: Vec::new(),
        inference_crater_level_left_out: false,
        renderer: Vec::new(),
        resampling: Vec::new(),
    };
    let out = dir.path().join("report");
    train::report::write(&report, &out).unwrap();
    let md = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(md.contains("](brdf_models.png)"), "{md}");
    let png = image::open(out.join("brdf_models.png")).unwrap();
    assert_eq!((png.width(), png.height()), (900, 600));
    assert!(
        !out.join("renderer.png").exists(),
        "no plot for a section that was not measured"
    );
}

#[test]
fn report_resampling_section_measures_point_kernels_against_the_area_average() {
    use dataset::science::crs::LunarCrs;
    use dataset::science::raster::{GeoTransform, Raster};
    // A 2 m ortho with fine texture (a 2 m checkerboard over a ramp) and a 5 m grid offset from it by 3 m / 1 m.
    let crs = LunarCrs::equirectangular(0.0, 0.0);
    let mut ortho = Raster::new(700, 400, GeoTransform::north_up(0.0, 0.0, 2.0), crs, 0.0);
    for r in 0..400 {
        for c in 0..700 {
            ortho.data[r * 700 + c] = 0.1 + 0.0001 * c as f32 + 0.05 * ((r + c) % 2) as f32;
        }
    }
    let dem = GeoTransform::north_up(-3.0, 1.0, 5.0);
    let rows = train::report::resampling_rows(&ortho, &dem, 3);
    let names: Vec<&str> = rows.iter().map(|r| r.kernel.as_str()).collect();
    assert_eq!(names, ["area", "bilinear", "nearest"]);
    // 1,400 m × 800 m of ortho holds two 640 m crops across and one down.
    assert!(rows.iter().all(|r| r.crops == 2), "{rows:?}");
    assert_eq!((rows[0].rms_vs_area, rows[0].valid_ratio), (0.0, 1.0));
    // Nearest keeps the ±0.025 checkerboard the area average removes; bilinear at a cell centre between pixel
    // centres blends it partly.
    assert!(
        rows[2].rms_vs_area > 0.015 && rows[2].max_abs_vs_area <= 0.05 + 1e-3,
        "{rows:?}"
    );
    assert!(
        rows[1].rms_vs_area > 0.0 && rows[1].rms_vs_area < rows[2].rms_vs_area,
        "{rows:?}"
    );
    let dir = tempfile::tempdir().unwrap();
    write_synthetic_dataset(dir.path(), synthetic_samples(4, 1), synthetic_samples(3, 2));
    let source = LocalSource::open(dir.path()).unwrap();
    let (brdf_models, images, pixels, geometry_ns) =
        train::report::brdf_model_rows(&source, Split::Val, None, 4).unwrap();
    let report = train::report::Report {
        split: Split::Val,
        images,
        pixels,
        calibration_samples: 4,
        geometry_ns_per_pixel: geometry_ns,
        brdf_models,
        inference_overlap: Vec::new(),
        inference_crater_level_left_out: false,
        renderer: Vec::new(),
        resampling: rows,
    };
    let out = dir.path().join("report");
    train::report::write(&report, &out).unwrap();
    let md = std::fs::read_to_string(out.join("report.md")).unwrap();
    assert!(
        md.contains("| nearest |") && md.contains("](resampling.png)"),
        "{md}"
    );
}

/// A run's crater level sets "learned"'s level on the crops in its band, and "learned_network" keeps the network's
/// rendering beside it: in the band the learned rendering shows the regression's scale (0.4, at weight 1) and is
/// the network's times one factor; outside it, and without a crater frame, the two are the same bits.
#[test]
fn a_crater_level_sets_learned_in_its_band_and_keeps_the_network_beside_it() {
    use dataset::contract::crater_frame::CraterPosition;
    use train::crater_level::rendered_scale;
    let dir = tempfile::tempdir().unwrap();
    let mut val = synthetic_samples(4, 2);
    let places = [Some(0.6), Some(0.9), Some(2.0), None];
    for (sample, rho) in val.iter_mut().zip(places) {
        sample.crater = rho.map(|rho| CraterPosition {
            rho,
            relative_height_m: 40.0,
            relief_to_diameter: Some(0.07),
        });
    }
    write_synthetic_dataset(dir.path(), synthetic_samples(6, 1), val);
    let source = LocalSource::open(dir.path()).unwrap();
    let device = Default::default();
    // Started as `fit` starts it, at a uniform scale: the network's level (0.8) is known and positive whatever the
    // backend's random stream gave the other weights.
    let net = UNetConfig::new(BrdfModel::H1.param_count())
        .with_base_width(4)
        .init::<Flex>(&device)
        .with_uniform_head(&[0.8], &device);
    let level = train::testing::constant_crater_level(0.45, 1.0, 0.4, 1.0);
    let runs = [TrainedRun {
        config: FitConfig {
            model: BrdfModel::H1,
            ..m2_config()
        },
        input: InputNormalisation::relief(source.manifest().dem_std_m),
        net,
        checkpoint: "last/model.mpk".into(),
        crater_level: Some(level),
        input_range: None,
    }];
    let options = EvalOptions {
        split: Split::Val,
        max_samples: None,
        batch_size: 4,
        calibration_samples: 6,
        panels: 0,
        symmetry_mean: false,
        without_crater_frames: false,
        clamp_crater_relief: false,
    };
    let calibration = calibrate(&source, 6, BrdfModel::H1).unwrap();
    let mut seen = Vec::new();
    let report = evaluate(
        &runs,
        &source,
        &options,
        calibration,
        None,
        &device,
        |_, sample, renderings| {
            let get = |name: &str| &renderings.iter().find(|(n, _)| *n == name).unwrap().1;
            let hapke = hapke_render(sample, &HapkeParams::lunar_typical());
            let (learned, network) = (get("learned"), get("learned_network"));
            let in_band = sample.crater.is_some_and(|c| c.rho < 1.0);
            if in_band {
                let shown = rendered_scale(learned, &hapke).unwrap();
                assert!((shown - 0.4).abs() < 1e-9, "{}: {shown}", sample.sample_id);
                let k = learned[100] / network[100];
                for (l, n) in learned.iter().zip(network) {
                    assert!((l - k * n).abs() <= 1e-12 * n.abs().max(1e-3));
                }
            } else {
                assert_eq!(learned, network, "{}", sample.sample_id);
            }
            seen.push(in_band);
            Ok(())
        },
    )
    .unwrap();
    assert_eq!(seen, [true, true, false, false]);
    let names: Vec<&str> = report.methods.iter().map(|m| m.name.as_str()).collect();
    assert_eq!(
        &names[..3],
        ["learned", "learned_network", "learned_paper_norm"]
    );
    let used = report.crater_level.as_ref().expect("reported");
    assert_eq!((used.crops_with_frame, used.crops_in_band), (3, 2));
}

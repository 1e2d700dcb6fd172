//! `g2r-train` bad inputs: one line on stderr naming the file (or flag) and the fix, a non-zero exit, and no
//! finished-looking output.

use std::path::Path;
use std::process::Command;

fn train_cli(args: &[&str]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_g2r-train"))
        .args(args)
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// A synthetic dataset of `train` and `val` crops written to `d/data`, and the run directory `d/run`: their paths.
fn data_and_run(
    d: &Path,
    train: Vec<dataset::contract::schema::Sample>,
    val: Vec<dataset::contract::schema::Sample>,
) -> (String, String) {
    train::testing::write_synthetic_dataset(&d.join("data"), train, val);
    (
        d.join("data").to_string_lossy().into_owned(),
        d.join("run").to_string_lossy().into_owned(),
    )
}

fn error_line(stderr: &str) -> &str {
    stderr
        .lines()
        .find(|l| l.starts_with("error"))
        .unwrap_or("")
}

#[test]
fn help_lists_every_command() {
    let out = Command::new(env!("CARGO_BIN_EXE_g2r-train"))
        .arg("--help")
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    for command in [
        "fit",
        "compare-models",
        "eval",
        "infer",
        "report",
        "render",
        "bench",
        "models",
        "model-choice",
        "compare-evals",
        "crater-level",
    ] {
        assert!(
            text.contains(command),
            "{command} missing from --help:\n{text}"
        );
    }
}

#[test]
fn bad_inputs_fail_with_one_line_naming_the_file_and_the_fix() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let path = |name: &str| d.join(name).to_string_lossy().into_owned();
    std::fs::write(
        d.join("bad.csv"),
        "lon,lat,alt,yaw,pitch,roll\n0,95,1000,0,0,0\n",
    )
    .unwrap();
    std::fs::write(d.join("not-a-dem.tif"), b"not a tiff").unwrap();
    let dem = dataset::science::raster::Raster::new(
        4,
        4,
        dataset::science::raster::GeoTransform::north_up(0.0, 0.0, 5.0),
        dataset::science::crs::LunarCrs::equirectangular(-43.31, -11.36),
        -1200.0,
    );
    dataset::science::raster::write_raster(&d.join("dem.tif"), &dem, &[]).unwrap();
    train::testing::write_synthetic_dataset(
        &d.join("data"),
        train::testing::synthetic_samples(2, 1),
        train::testing::synthetic_samples(2, 2),
    );
    let cases: Vec<(Vec<String>, Vec<&str>)> = vec![
        (
            vec![
                "eval".into(),
                "--run".into(),
                path("no-run"),
                "--data".into(),
                path("no-data"),
            ],
            vec!["no-data", "manifest.json"],
        ),
        (
            vec![
                "eval".into(),
                "--run".into(),
                path("no-run"),
                "--data".into(),
                path("data"),
                "--split".into(),
                "val".into(),
            ],
            vec!["no-run", "config.json", "--ensemble", "g2r-train fit --out"],
        ),
        (
            vec![
                "infer".into(),
                "--run".into(),
                path("no-run"),
                "--dem".into(),
                path("dem.tif"),
                "--out".into(),
                path("p.tif"),
            ],
            vec!["no-run", "config.json", "g2r-train fit --out"],
        ),
        (
            vec![
                "report".into(),
                "--data".into(),
                path("data"),
                "--out".into(),
                path("report"),
                "--crater-catalogue".into(),
                path("craters.csv"),
            ],
            vec!["--crater-catalogue", "--run"],
        ),
        (
            vec![
                "fit".into(),
                "--data".into(),
                path("data"),
                "--out".into(),
                path("run"),
                "--crater-level".into(),
            ],
            vec!["--crater-level", "m2", "--model h1"],
        ),
        (
            vec![
                "crater-level".into(),
                "--run".into(),
                path("no-run"),
                "--data".into(),
                path("data"),
            ],
            vec!["no-run", "config.json", "g2r-train fit --out"],
        ),
        (
            vec![
                "infer".into(),
                "--run".into(),
                path("no-run"),
                "--dem".into(),
                path("not-a-dem.tif"),
                "--out".into(),
                path("p.tif"),
                "--dem-std-m".into(),
                "20".into(),
            ],
            vec!["not-a-dem.tif"],
        ),
        (
            vec![
                "render".into(),
                "--dem".into(),
                path("not-a-dem.tif"),
                "--trajectory".into(),
                path("bad.csv"),
                "--sun=1e11,0,0".into(),
                "--out".into(),
                path("views"),
            ],
            vec!["bad.csv", "line 2", "latitude 95"],
        ),
        (
            vec![
                "render".into(),
                "--dem".into(),
                path("not-a-dem.tif"),
                "--trajectory".into(),
                path("bad.csv"),
                "--sun=1e11,0".into(),
                "--out".into(),
                path("views"),
            ],
            vec!["--sun", "expected three", "X,Y,Z"],
        ),
        (
            vec![
                "fit".into(),
                "--data".into(),
                "http://127.0.0.1:9".into(),
                "--out".into(),
                path("run"),
            ],
            vec!["http://127.0.0.1:9", "g2r-dataset serve"],
        ),
        (
            vec![
                "fit".into(),
                "--data".into(),
                path("no-dataset"),
                "--out".into(),
                path("run"),
                "--ema".into(),
                "1.5".into(),
            ],
            vec!["--ema", "outside [0, 1)"],
        ),
        (
            vec![
                "fit".into(),
                "--data".into(),
                path("no-dataset"),
                "--out".into(),
                path("run"),
                "--weight-decay".into(),
                "0".into(),
            ],
            vec![
                "--weight-decay",
                "not a positive decay",
                "leave the flag out",
            ],
        ),
        (
            vec![
                "fit".into(),
                "--data".into(),
                path("data"),
                "--out".into(),
                path("run"),
                "--also-train-on".into(),
                path("data"),
            ],
            vec![
                "data",
                "\"synthetic\" is already in the pool",
                "--also-train-on",
            ],
        ),
        (
            vec![
                "model-choice".into(),
                "--data".into(),
                path("data"),
                "--world".into(),
                path("no-world"),
                "--out".into(),
                path("choice"),
            ],
            vec!["no-world", "hapke_params.tif", "g2r-pipeline synth"],
        ),
    ];
    for (args, needles) in cases {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let (ok, stderr) = train_cli(&args);
        assert!(!ok, "{args:?} succeeded");
        let line = error_line(&stderr);
        for needle in needles {
            assert!(
                line.contains(needle),
                "{args:?}: `{needle}` not in `{line}`\n{stderr}"
            );
        }
    }
    // Nothing finished-looking was left behind.
    for name in ["p.tif", "views", "run/best", "no-run", "choice", "report"] {
        assert!(!Path::new(&path(name)).exists(), "{name} exists");
    }
}

/// A resume with other flags than the run started with is refused by one line that names each setting that
/// differs, saved and given, and leaves the run's checkpoint as it was.
#[test]
fn a_resume_with_other_flags_names_each_setting_that_differs() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (data, run) = data_and_run(
        d,
        train::testing::synthetic_samples(4, 1),
        train::testing::synthetic_samples(2, 2),
    );
    let fit = |lr: &str, seed: &str, resume: bool| {
        let mut args = vec![
            "fit",
            "--data",
            &data,
            "--out",
            &run,
            "--model",
            "m2",
            "--width",
            "4",
            "--batch",
            "2",
            "--epochs",
            "1",
            "--window",
            "1",
            "--no-dropout",
            "--lr",
            lr,
            "--seed",
            seed,
        ];
        if resume {
            args.push("--resume");
        }
        train_cli(&args)
    };
    let (ok, stderr) = fit("1e-3", "5", false);
    assert!(ok, "{stderr}");
    let checkpoint = std::fs::read(d.join("run/last/model.mpk")).unwrap();
    let (ok, stderr) = fit("2e-3", "6", true);
    assert!(!ok, "a resume with another --lr and --seed succeeded");
    let line = error_line(&stderr);
    for needle in [
        "config.json",
        "learning_rate: 0.001 → 0.002",
        "stream.seed: 5 → 6",
        "use a new --out",
    ] {
        assert!(line.contains(needle), "`{needle}` not in `{line}`");
    }
    assert!(!line.contains("epochs"), "{line}");
    assert_eq!(
        std::fs::read(d.join("run/last/model.mpk")).unwrap(),
        checkpoint
    );
}

/// `compare-evals` on two `metrics.json` of the same crops writes its comparison; on crops that differ it fails
/// with one line naming both files and the fix, and writes nothing.
#[test]
fn compare_evals_pairs_the_same_crops_and_refuses_others() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let metrics = |ids: &[&str], learned: f64| {
        let images: Vec<String> = ids
            .iter()
            .enumerate()
            .map(|(k, id)| {
                format!(
                    r#"{{"sample_id":"{id}","ortho_id":"M{}","metrics":{{"learned":{{"sse":{learned}}},"hapke_paper":{{"sse":2.0}}}}}}"#,
                    k % 2
                )
            })
            .collect();
        format!(r#"{{"split":"val","per_image":[{}]}}"#, images.join(","))
    };
    for (name, ids, learned) in [
        ("base", &["a", "b", "c", "d"][..], 1.0),
        ("better", &["d", "c", "b", "a"][..], 0.5),
        ("other", &["a", "b", "c", "e"][..], 0.5),
    ] {
        std::fs::create_dir(d.join(name)).unwrap();
        std::fs::write(d.join(name).join("metrics.json"), metrics(ids, learned)).unwrap();
    }
    let path = |name: &str| d.join(name).to_string_lossy().into_owned();
    let out = path("cmp");
    let (ok, stderr) = train_cli(&[
        "compare-evals",
        &path("base"),
        &path("better"),
        "--out",
        &out,
    ]);
    assert!(ok, "{stderr}");
    let written: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("cmp/comparison.json")).unwrap())
            .unwrap();
    assert_eq!(written["candidate_over_base"], 0.5);
    assert_eq!(written["base_over_hapke_paper"], 0.5);
    assert!(std::fs::read_to_string(d.join("cmp/comparison.md"))
        .unwrap()
        .contains("the candidate is better"));
    assert!(d.join("cmp/provenance.json").exists());

    // Into a reader that has already gone (`| head` after its lines): the files are still written whole, and the
    // command ends with success and no panic, as a Unix tool does.
    let piped = path("piped");
    let (reader, writer) = std::io::pipe().unwrap();
    drop(reader);
    let closed = Command::new(env!("CARGO_BIN_EXE_g2r-train"))
        .args([
            "compare-evals",
            &path("base"),
            &path("better"),
            "--out",
            &piped,
        ])
        .stdout(writer)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&closed.stderr);
    assert!(closed.status.success(), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert_eq!(
        std::fs::read(d.join("piped/comparison.json")).unwrap(),
        std::fs::read(d.join("cmp/comparison.json")).unwrap()
    );

    let refused = path("refused");
    let (ok, stderr) = train_cli(&[
        "compare-evals",
        &path("base"),
        &path("other"),
        "--out",
        &refused,
    ]);
    let line = error_line(&stderr);
    assert!(!ok);
    assert!(
        line.contains(&path("base")) && line.contains(&path("other")),
        "{stderr}"
    );
    assert!(line.contains("--max-samples"), "{stderr}");
    assert!(!d.join("refused").exists());
}

/// `fit --crater-level` trains and then fits the run's crater level in one command: on a dataset whose crops
/// carry crater frames it leaves `crater_level.json` in the run directory, which the run then loads with.
#[test]
fn fit_with_crater_level_leaves_a_crater_level_the_run_loads_with() {
    use dataset::contract::crater_frame::CraterPosition;
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let framed = |n: usize, seed: u64| {
        let mut samples = train::testing::synthetic_samples(n, seed);
        for (i, s) in samples.iter_mut().enumerate() {
            s.crater = Some(CraterPosition {
                rho: 0.5 + 0.4 * (i as f64 / n as f64),
                relative_height_m: -150.0 + 300.0 * ((i * 7) % n) as f64 / n as f64,
                relief_to_diameter: Some(0.05 + 0.04 * ((i * 3) % n) as f64 / n as f64),
            });
        }
        samples
    };
    let train_crops = train::crater_level::MIN_ZONE_TRAIN_CROPS;
    let (data, run) = data_and_run(d, framed(train_crops, 1), framed(4, 2));
    let (ok, stderr) = train_cli(&[
        "fit",
        "--data",
        &data,
        "--out",
        &run,
        "--model",
        "h1",
        "--width",
        "4",
        "--batch",
        "4",
        "--epochs",
        "1",
        "--max-train-samples",
        "8",
        "--crater-level",
    ]);
    assert!(ok, "{stderr}");
    let trained = train::run_dir::load_trained::<burn::backend::Flex>(
        &d.join("run"),
        train::run_dir::Checkpoint::Auto,
        &Default::default(),
    )
    .unwrap();
    let level = trained
        .crater_level
        .expect("crater_level.json written and loaded");
    // The fewest crops a zone is fitted on, all within the frame's reach: one zone over all of them, which no
    // split could halve.
    assert_eq!(level.bands.len(), 1);
    assert_eq!(level.bands[0].regression.train_crops, train_crops);
    assert_eq!(level.zone_counts.len(), 1);
    assert_eq!(level.val_crops, 4);
    // A ground guard needs the world's terrain classes: a world without them is refused by name, and the level
    // already written stays.
    let written = std::fs::read(d.join("run/crater_level.json")).unwrap();
    let no_world = d.join("no-world").to_string_lossy().into_owned();
    let (ok, stderr) = train_cli(&[
        "crater-level",
        "--run",
        &run,
        "--data",
        &data,
        "--world",
        &no_world,
    ]);
    assert!(!ok);
    let line = error_line(&stderr);
    assert!(
        line.contains("terrain_class.tif") && line.contains("--world"),
        "{stderr}"
    );
    assert_eq!(
        std::fs::read(d.join("run/crater_level.json")).unwrap(),
        written
    );
}

/// `eval` off a terminal writes progress lines while it works (stderr, never stdout), and on a terminal (a pty
/// from `script`) draws a bar instead of lines ([`dataset::progress`]).
#[test]
fn eval_reports_progress_as_lines_off_a_terminal_and_as_a_bar_on_one() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (data, run) = data_and_run(
        d,
        train::testing::synthetic_samples(4, 1),
        train::testing::synthetic_samples(12, 2),
    );
    let (ok, stderr) = train_cli(&[
        "fit", "--data", &data, "--out", &run, "--model", "m2", "--width", "4", "--batch", "2",
        "--epochs", "1",
    ]);
    assert!(ok, "{stderr}");
    let eval = |out: &str| -> Vec<String> {
        [
            "eval",
            "--run",
            &run,
            "--data",
            &data,
            "--split",
            "val",
            "--batch",
            "2",
            "--out",
            out,
            "--calibration-samples",
            "4",
        ]
        .map(String::from)
        .to_vec()
    };

    // Off a terminal: lines every 20 ms (the variable), the eval's with its count before the end and at it.
    let output = Command::new(env!("CARGO_BIN_EXE_g2r-train"))
        .args(eval(&d.join("lines").to_string_lossy()))
        .env("G2R_PROGRESS_SECONDS", "0.02")
        .output()
        .unwrap();
    let (stdout, stderr) = (
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr),
    );
    assert!(output.status.success(), "{stderr}");
    let eval_lines: Vec<&str> = stderr
        .lines()
        .filter(|l| l.contains("task=\"eval\"") && l.contains("total=12"))
        .collect();
    assert!(
        eval_lines
            .iter()
            .any(|l| l.contains(" progress ") && !l.contains("done=12")),
        "no progress line while eval worked:\n{stderr}"
    );
    assert!(
        eval_lines
            .last()
            .is_some_and(|l| l.contains(" finished ") && l.contains("done=12")),
        "no last line with every crop counted:\n{stderr}"
    );
    assert!(
        !stdout.contains("progress") && stdout.contains("wrote"),
        "progress on stdout, or no report:\n{stdout}"
    );

    // On a terminal: a bar, and no lines.
    let command = std::iter::once(env!("CARGO_BIN_EXE_g2r-train").to_string())
        .chain(eval(&d.join("bar").to_string_lossy()))
        .collect::<Vec<_>>()
        .join(" ");
    let output = Command::new("script")
        .args(["--quiet", "--return", "--command", &command, "/dev/null"])
        .env("G2R_PROGRESS_SECONDS", "0.02")
        .output()
        .expect("script (util-linux) runs a command on a pty");
    let terminal = String::from_utf8_lossy(&output.stdout);
    assert!(output.status.success(), "{terminal}");
    assert!(
        terminal.contains("eval [") && terminal.contains("crops"),
        "no bar on the terminal:\n{terminal}"
    );
    assert!(
        !terminal.contains("task=\"eval\""),
        "log lines on a terminal:\n{terminal}"
    );
}

/// `render` writes the 16-bit views and beside them `views.png`, a contact sheet: one row per view, one column per
/// method, a label strip above each image and a caption below.
#[test]
fn render_writes_a_labelled_contact_sheet_of_its_views() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // 2 km of gently sloping ground centred on (-43.31°, -11.36°).
    let crs = dataset::science::crs::LunarCrs::equirectangular(-43.31, -11.36);
    let (cx, cy) = crs.from_lonlat_deg(-11.36, -43.31).unwrap();
    let mut dem = dataset::science::raster::Raster::new(
        400,
        400,
        dataset::science::raster::GeoTransform::north_up(cx - 1000.0, cy + 1000.0, 5.0),
        crs,
        -1200.0,
    );
    for (k, h) in dem.data.iter_mut().enumerate() {
        *h = -1200.0 + (k % 400) as f32 * 0.2;
    }
    dataset::science::raster::write_raster(&d.join("dem.tif"), &dem, &[]).unwrap();
    // Two nadir views over the DEM's middle, 2.2 km above the ground (footprints about 780 m wide).
    std::fs::write(
        d.join("views.csv"),
        "lon,lat,alt,yaw,pitch,roll\n-11.36,-43.31,1000,0,0,0\n-11.36,-43.31,1000,30,0,0\n",
    )
    .unwrap();
    let path = |name: &str| d.join(name).to_string_lossy().into_owned();
    let (ok, stderr) = train_cli(&[
        "render",
        "--dem",
        &path("dem.tif"),
        "--trajectory",
        &path("views.csv"),
        "--sun=1.4e11,-5.2e10,-1.2e10",
        "--out",
        &path("views"),
        "--width",
        "32",
        "--height",
        "24",
        "--fov",
        "20",
        "--rays",
        "1",
    ]);
    assert!(ok, "{stderr}");
    let record: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("views/views.json")).unwrap())
            .unwrap();
    let views = record["views"].as_array().unwrap();
    let methods: std::collections::BTreeSet<&str> = views
        .iter()
        .map(|v| v["method"].as_str().unwrap())
        .collect();
    let rows = (views.len() / methods.len()) as u32;
    assert_eq!(rows, 2);
    let sheet = image::open(d.join("views/views.png")).unwrap().to_rgb8();
    // Cells of 32 × 24 px with a 4-px gap, an 18-px label strip above each, an 18-px caption row at the bottom.
    assert_eq!(
        (sheet.width(), sheet.height()),
        (methods.len() as u32 * 36 - 4, rows * (18 + 24 + 4) + 18)
    );
    // Every ray meets the ground, and the first view's image sits under its label strip: lit ground in mid to
    // light grey on the views' shared scale, neither the white background nor black.
    assert!(
        views.iter().all(|v| v["stats"]["hit_fraction"] == 1.0),
        "{record}"
    );
    let grey = sheet.get_pixel(16, 18 + 12).0;
    assert!(
        grey[0] == grey[1] && (100..255).contains(&grey[0]),
        "{grey:?}"
    );
}

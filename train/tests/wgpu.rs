//! The GPU code path executed without a GPU: `g2r-train` built with `--features wgpu` runs `fit`, `eval` and
//! `infer` on Burn's wgpu backend (CubeCL's kernels, the same operations CUDA runs, not the project's CPU
//! kernels) on whatever Vulkan device the machine has: Mesa's software lavapipe in CI (`.ci/setup` installs it).
//! Each result is compared with `--backend flex` on the same weights, and checkpoints cross backends both ways:
//! the common start is written on flex and resumed on wgpu, and the wgpu run is evaluated on flex.
//!
//! Tolerances: both backends compute in f32, but they sum in different orders (tiled GPU reductions and
//! convolutions against gemm's blocked loops), so they agree to f32 rounding, which training then carries and
//! Adam amplifies: a weight whose gradient is near zero moves by about ±lr whatever its size (m/√v ≈ its sign),
//! so rounding that flips such a gradient's sign moves the weight by a full step. Measured on lavapipe (Mesa
//! 22.3.6, debug build), relative: validation of the common start 7.8e-8; after two resumed steps 4.5e-7; after
//! four 3.9e-5 (the amplification, two orders per two steps); eval's pixel MSE 3.3e-9 and the inferred
//! parameters 3.5e-7 of their range (one network, no training). With the CubeCL backends' own convolution
//! gradients (`kernels::cubecl`; Intel Xeon): 1.4e-8, 3.7e-7, 3.0e-6, eval 1.5e-8, infer 2.4e-7. Bounds: 1e-5 up
//! to two resumed steps and for eval and infer, 1e-3 after four: 20-700× the differences measured with either
//! set of kernels, and far below what a wrong kernel does (percent, as the first two-step check shows it would).
#![cfg(feature = "wgpu")]

use std::path::Path;
use std::process::Command;

use dataset::science::raster::read_bands;
use serde_json::Value;
use train::testing::{synthetic_samples, write_synthetic_dataset};

/// Run `g2r-train ARGS`; panics with its stderr when it fails.
fn cli(args: &[&str]) {
    let out = Command::new(env!("CARGO_BIN_EXE_g2r-train"))
        .args(args)
        .output()
        .expect("g2r-train runs");
    assert!(
        out.status.success(),
        "g2r-train {}: {}",
        args.join(" "),
        String::from_utf8_lossy(&out.stderr)
    );
}

fn path(p: &Path) -> &str {
    p.to_str().expect("UTF-8 temp path")
}

/// Relative difference, against the larger magnitude.
fn relative(a: f64, b: f64) -> f64 {
    (a - b).abs() / a.abs().max(b.abs()).max(f64::MIN_POSITIVE)
}

/// Every line of a run's metrics.jsonl.
fn metrics(run: &Path) -> Vec<Value> {
    std::fs::read_to_string(run.join("metrics.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

/// The learned row's pixel MSE in an eval's metrics.json.
fn learned_pixel_mse(eval: &Path) -> f64 {
    let report: Value =
        serde_json::from_str(&std::fs::read_to_string(eval.join("metrics.json")).unwrap()).unwrap();
    report["methods"]
        .as_array()
        .unwrap()
        .iter()
        .find(|m| m["name"] == "learned")
        .expect("a learned row")["aggregate"]["pixel_mse"]
        .as_f64()
        .unwrap()
}

#[test]
fn fit_eval_and_infer_on_wgpu_agree_with_flex() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    write_synthetic_dataset(&data, synthetic_samples(16, 1), synthetic_samples(4, 2));
    // Every layer the network has: relief + elevation planes, the context encoder with its absolute plane,
    // BatchNorm, the weight average. Dropout off and no augmentation: nothing random after the start.
    let fit = |backend: &str, out: &Path, extra: &[&str]| {
        let mut args = vec![
            "fit",
            "--backend",
            backend,
            "--data",
            path(&data),
            "--out",
            path(out),
            "--model",
            "m2",
            "--width",
            "4",
            "--batch",
            "4",
            "--epochs",
            "3",
            "--max-train-samples",
            "8",
            "--max-val-samples",
            "4",
            "--lr",
            "1e-3",
            "--no-dropout",
            "--no-augment",
            "--elevation-input",
            "--context-input",
            "--context-absolute",
            "--ema",
            "0.9",
            "--seed",
            "3",
        ];
        args.extend_from_slice(extra);
        cli(&args);
    };

    // The common start: two steps on flex (epoch 0), then each backend resumes from that checkpoint for the
    // remaining four.
    let start = tmp.path().join("start");
    fit("flex", &start, &["--stop-after-steps", "2"]);
    let (on_flex, on_wgpu) = (tmp.path().join("flex"), tmp.path().join("wgpu"));
    train::testing::copy_dir(&start, &on_flex);
    train::testing::copy_dir(&start, &on_wgpu);
    fit("flex", &on_flex, &["--resume"]);
    fit("wgpu", &on_wgpu, &["--resume"]);
    let (flex_metrics, wgpu_metrics) = (metrics(&on_flex), metrics(&on_wgpu));
    assert_eq!(flex_metrics.len(), 3);
    assert_eq!(wgpu_metrics.len(), 3);
    // Epoch 0's two steps ran on flex before the stop; its validation ran after the resume, on each backend.
    assert_eq!(
        flex_metrics[0]["train_loss"], wgpu_metrics[0]["train_loss"],
        "epoch 0 trained once, on flex"
    );
    // Per epoch, the largest relative difference of its train loss (epochs 1 and 2), validation loss and
    // weight average's validation loss.
    let per_epoch: Vec<f64> = flex_metrics
        .iter()
        .zip(&wgpu_metrics)
        .enumerate()
        .map(|(epoch, (f, w))| {
            let keys: &[&str] = if epoch == 0 {
                &["/val_loss", "/ema_val/loss"]
            } else {
                &["/train_loss", "/val_loss", "/ema_val/loss"]
            };
            keys.iter()
                .map(|key| {
                    let (a, b) = (
                        f.pointer(key).unwrap().as_f64().unwrap(),
                        w.pointer(key).unwrap().as_f64().unwrap(),
                    );
                    assert!(a > 0.0 && b > 0.0, "{key}: {a} {b}");
                    relative(a, b)
                })
                .fold(0.0, f64::max)
        })
        .collect();
    // The resumed steps trained: the loss moved well past the rounding the bound allows.
    let moved = relative(
        flex_metrics[0]["train_loss"].as_f64().unwrap(),
        flex_metrics[2]["train_loss"].as_f64().unwrap(),
    );

    // eval of the wgpu run on both backends (a checkpoint written on wgpu, loaded on flex).
    let eval = |backend: &str, out: &Path| {
        cli(&[
            "eval",
            "--backend",
            backend,
            "--run",
            path(&on_wgpu),
            "--data",
            path(&data),
            "--split",
            "val",
            "--out",
            path(out),
            "--calibration-samples",
            "8",
            "--panels",
            "1",
        ]);
        learned_pixel_mse(out)
    };
    let (eval_flex, eval_wgpu) = (
        eval("flex", &tmp.path().join("eval-flex")),
        eval("wgpu", &tmp.path().join("eval-wgpu")),
    );
    let worst_eval = relative(eval_flex, eval_wgpu);
    // Each eval says how it was produced, beside its metrics.
    let provenance: dataset::provenance::Provenance = serde_json::from_str(
        &std::fs::read_to_string(tmp.path().join("eval-wgpu/provenance.json")).unwrap(),
    )
    .unwrap();
    assert!(
        provenance.command.contains("eval") && provenance.command.contains("wgpu"),
        "{provenance:?}"
    );

    // infer on a DEM GeoTIFF.
    let dem = tmp.path().join("dem.tif");
    write_test_dem(&dem);
    let infer = |backend: &str, out: &Path| {
        cli(&[
            "infer",
            "--backend",
            backend,
            "--run",
            path(&on_wgpu),
            "--dem",
            path(&dem),
            "--out",
            path(out),
        ]);
        read_bands(out).unwrap()
    };
    let (maps_flex, maps_wgpu) = (
        infer("flex", &tmp.path().join("flex.tif")),
        infer("wgpu", &tmp.path().join("wgpu.tif")),
    );
    assert_eq!(maps_flex.len(), maps_wgpu.len());
    let mut worst_map = 0f64;
    for (f, w) in maps_flex.iter().zip(&maps_wgpu) {
        let range = f
            .data
            .iter()
            .filter(|v| v.is_finite())
            .fold(0f64, |m, &v| m.max((v as f64).abs()));
        assert!(range > 0.0);
        for (&a, &b) in f.data.iter().zip(&w.data) {
            assert_eq!(
                a.is_finite(),
                b.is_finite(),
                "nodata where the DEM has none"
            );
            if a.is_finite() {
                worst_map = worst_map.max((a as f64 - b as f64).abs() / range);
            }
        }
    }

    let shown: Vec<String> = per_epoch.iter().map(|v| format!("{v:.2e}")).collect();
    eprintln!(
        "wgpu against flex: losses by epoch {shown:?} relative (training moved them {moved:.2e}), eval \
         pixel MSE {worst_eval:.2e}, inferred parameters {worst_map:.2e} of their range"
    );
    assert!(moved > 1e-2, "four steps moved the train loss by {moved:e}");
    assert!(
        per_epoch[0] < 1e-5 && per_epoch[1] < 1e-5,
        "the start and the first two resumed steps differ by {shown:?}"
    );
    assert!(
        per_epoch[2] < 1e-3,
        "the loss curves part by {:e} after four steps",
        per_epoch[2]
    );
    assert!(
        worst_eval < 1e-5,
        "eval pixel MSE differs by {worst_eval:e}"
    );
    assert!(worst_map < 1e-5, "parameter maps differ by {worst_map:e}");
}

/// A 1 × 0.75 km bowl-cratered DEM with a nodata hole (which `infer` must carry through as nodata).
fn write_test_dem(out: &Path) {
    let mut r = train::testing::bowl_dem(200, 150, -1200.0);
    for row in 60..64 {
        for col in 20..25 {
            r.data[row * r.width + col] = f32::NAN;
        }
    }
    dataset::science::raster::write_raster(out, &r, &[]).unwrap();
}

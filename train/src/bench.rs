//! Throughput of the train step (U-Net + renderer layer, forward + backward + Adam) and of the renderer layer
//! alone (forward + backward w.r.t. the parameter maps), on synthetic crops so no dataset is needed.

use std::time::Instant;

use burn::optim::{AdamConfig, GradientsParams, Optimizer};
use burn::prelude::*;
use burn::tensor::backend::AutodiffBackend;
use dataset::brdf::BrdfModel;
use dataset::schema::{CROP_PX, DEM_PX};
use rand::Rng;

use crate::data::HostBatch;
use crate::model::UNetConfig;
use crate::render::{masked_mse, render, scene_geometry, SceneInputs};
use crate::training::train_loss;

/// A batch of smooth random terrain under a 60° sun and a near-nadir camera (bench and tests).
pub fn synthetic_batch(n: usize, seed: u64) -> HostBatch {
    let mut rng = dataset::rng::keyed_rng(seed, "synthetic-batch", 0);
    let mut b = HostBatch::default();
    for i in 0..n {
        let (fx, fy, amp): (f64, f64, f64) = (
            rng.random_range(5.0..30.0),
            rng.random_range(5.0..30.0),
            rng.random_range(5.0..60.0),
        );
        let heights: Vec<f64> = (0..DEM_PX * DEM_PX)
            .map(|k| {
                let (c, r) = ((k % DEM_PX) as f64, (k / DEM_PX) as f64);
                amp * (c / fx).sin() * (r / fy).cos() + 0.1 * c
            })
            .collect();
        let interior: Vec<f64> = (0..CROP_PX * CROP_PX)
            .map(|k| heights[(k / CROP_PX + 1) * DEM_PX + k % CROP_PX + 1])
            .collect();
        let mean = interior.iter().sum::<f64>() / interior.len() as f64;
        b.sample_ids.push(format!("synthetic:{i}"));
        b.net_input
            .extend(interior.iter().map(|h| (h - mean) / 20.0));
        b.relative_heights_m.extend(&heights);
        b.image
            .extend((0..CROP_PX * CROP_PX).map(|k| 0.1 + 0.02 * ((k % 7) as f64 / 7.0)));
        b.valid
            .extend((0..CROP_PX * CROP_PX).map(|k| f64::from(k % 11 != 0)));
        b.lit
            .extend((0..CROP_PX * CROP_PX).map(|k| if k % 13 == 0 { 0.5 } else { 1.0 }));
        let azimuth: f64 = rng.random_range(0.0..std::f64::consts::TAU);
        let (si, ci) = 60f64.to_radians().sin_cos();
        b.sun_dir_enu
            .extend([si * azimuth.cos(), si * azimuth.sin(), ci]);
        b.camera_pos_enu_m.extend([
            rng.random_range(-3000.0..3000.0),
            rng.random_range(-3000.0..3000.0),
            50_000.0,
        ]);
        b.map_to_en.extend([0.97, 0.01, -0.01, 1.0]);
        b.gsd_m.push(5.0);
        b.origin_height_m.push(-1200.0);
    }
    b
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct BenchReport {
    pub backend: String,
    pub batch: usize,
    pub base_width: usize,
    pub model: String,
    pub train_step_samples_per_s: f64,
    pub train_step_ms: f64,
    pub layer_samples_per_s: f64,
    pub layer_ms: f64,
}

/// Time `iters` steps after one warm-up step.
pub fn bench<B: AutodiffBackend>(
    backend_name: &str,
    model: BrdfModel,
    batch_size: usize,
    base_width: usize,
    iters: usize,
    device: &B::Device,
) -> BenchReport {
    let batch = synthetic_batch(batch_size, 7);
    B::seed(device, 7);
    let config = UNetConfig::new(model.param_count()).with_base_width(base_width);
    let mut net = config.init::<B>(device);
    let mut optim = AdamConfig::new()
        .with_epsilon(1e-8)
        .init::<B, crate::model::UNet<B>>();
    let mut step = |net: crate::model::UNet<B>| {
        let loss = train_loss(&net, model, &batch, device);
        let grads = GradientsParams::from_grads(loss.backward(), &net);
        optim.step(1e-4, net, grads)
    };
    net = step(net);
    let t = Instant::now();
    for _ in 0..iters {
        net = step(net);
    }
    let train_s = t.elapsed().as_secs_f64() / iters as f64;

    // Layer alone: geometry + render + loss, backward to the parameter maps.
    let n = batch.len();
    let params_data = TensorData::new(
        vec![0.1f64; n * model.param_count() * CROP_PX * CROP_PX],
        [n, model.param_count(), CROP_PX, CROP_PX],
    );
    let image = Tensor::<B, 4>::from_data(
        TensorData::new(batch.image.clone(), [n, 1, CROP_PX, CROP_PX]),
        device,
    );
    let layer = || {
        let params = Tensor::<B, 4>::from_data(params_data.clone(), device).require_grad();
        let geometry = scene_geometry(&SceneInputs::<B>::from_host(&batch, device));
        let loss = masked_mse(
            render(model, params.clone(), &geometry),
            image.clone(),
            geometry.valid.clone(),
        );
        let grads = loss.backward();
        params
            .grad(&grads)
            .expect("parameter maps get a gradient")
            .into_data()
    };
    layer();
    let t = Instant::now();
    for _ in 0..iters {
        layer();
    }
    let layer_s = t.elapsed().as_secs_f64() / iters as f64;
    BenchReport {
        backend: backend_name.to_string(),
        batch: batch_size,
        base_width,
        model: model.name().to_string(),
        train_step_samples_per_s: batch_size as f64 / train_s,
        train_step_ms: train_s * 1e3,
        layer_samples_per_s: batch_size as f64 / layer_s,
        layer_ms: layer_s * 1e3,
    }
}

//! Prediction: a trained network's renderings of samples in inference mode, one pass, the mean of its 8 dihedral
//! views, or the mean of several runs (a seed ensemble).

use burn::prelude::*;
use dataset::science::brdf::BrdfModel;

use crate::augment::Dihedral;
use crate::data::{HostBatch, InputNormalisation};
use crate::kernels::TrainOps;
use crate::model::UNet;
use crate::renderer_layer::{render, SceneTerms};
use dataset::contract::schema::{Sample, CONTEXT_PX, CROP_PX};

use crate::run_dir::TrainedRun;

/// The network's raw parameter maps for one host batch: `[N, P, 128, 128]` (the renderer applies the activation).
pub(crate) fn net_outputs<B: TrainOps>(
    net: &UNet<B>,
    batch: &HostBatch,
    device: &B::Device,
) -> Tensor<B, 4> {
    let input = Tensor::<B, 4>::from_data(
        TensorData::new(
            batch.net_input.clone(),
            [batch.len(), batch.input_channels, 128, 128],
        ),
        device,
    );
    let context = (!batch.context_input.is_empty()).then(|| {
        Tensor::<B, 4>::from_data(
            TensorData::new(
                batch.context_input.clone(),
                [batch.len(), batch.context_channels, CONTEXT_PX, CONTEXT_PX],
            ),
            device,
        )
    });
    net.forward(input, context)
}

/// Network → renderer for one host batch: the rendered image `[N, 1, 128, 128]` and the batch's scene terms.
pub(crate) fn render_batch<B: TrainOps>(
    net: &UNet<B>,
    model: BrdfModel,
    batch: &HostBatch,
    device: &B::Device,
) -> (Tensor<B, 4>, SceneTerms<B>) {
    let scene = SceneTerms::<B>::from_host(batch, model, device);
    (render(net_outputs(net, batch, device), &scene), scene)
}

/// Render a batch with the network in inference mode (running BatchNorm stats, no dropout): `N × 128²` f64.
pub fn predict_images<B: TrainOps>(
    net: &UNet<B>,
    model: BrdfModel,
    batch: &HostBatch,
    device: &B::Device,
) -> Vec<f64> {
    render_batch(net, model, batch, device)
        .0
        .into_data()
        .convert::<f64>()
        .into_vec::<f64>()
        .expect("f64 after convert")
}

/// Render samples as the mean of the network's 8 dihedral views (test-time augmentation): the network sees each
/// turn and mirror of the terrain and context (with the geometry turned alike, as in training), its parameter maps
/// are turned back and rendered with the samples' own geometry, and the 8 renderings are averaged. The mean of
/// the renderings (not of the raw maps, which the activation would bend) makes this exactly an 8-member ensemble:
/// its squared error is at most the members' mean squared error, and the averaged predictor is equivariant under
/// the 8 symmetries, which a single pass of a trained network is only approximately. Cost: 8 network passes and 8
/// renders. `N × 128²` f64, as [`predict_images`].
pub fn predict_images_symmetry_mean<B: TrainOps>(
    net: &UNet<B>,
    model: BrdfModel,
    samples: &[Sample],
    input: &InputNormalisation,
    device: &B::Device,
) -> Vec<f64> {
    let batch = HostBatch::from_samples(samples, input);
    let scene = SceneTerms::<B>::from_host(&batch, model, device);
    let npx = CROP_PX * CROP_PX;
    let shape = [samples.len(), model.param_count(), CROP_PX, CROP_PX];
    let mut sum: Option<Tensor<B, 4>> = None;
    for d in Dihedral::all() {
        let turned: Vec<Sample> = samples.iter().map(|s| d.apply(s)).collect();
        let raw = net_outputs(net, &HostBatch::from_samples(&turned, input), device)
            .into_data()
            .convert::<f32>()
            .into_vec::<f32>()
            .expect("f32 after convert");
        let back = d.inverse();
        let raw_back: Vec<f32> = raw
            .chunks(npx)
            .flat_map(|plane| back.apply_raster(plane, CROP_PX))
            .collect();
        let raw_back = Tensor::<B, 4>::from_data(TensorData::new(raw_back, shape), device);
        let rendered = render(raw_back, &scene);
        sum = Some(match sum {
            None => rendered,
            Some(total) => total + rendered,
        });
    }
    (sum.expect("8 symmetries") / 8.0)
        .into_data()
        .convert::<f64>()
        .into_vec::<f64>()
        .expect("f64 after convert")
}

/// One trained run's renderings of `samples` in inference mode (`N × 128²` f64): a single pass, or with
/// `symmetry_mean` the mean of its 8 dihedral views ([`predict_images_symmetry_mean`]). Each run uses its own input
/// normalisation, so runs trained with different input planes can be compared or averaged.
pub fn predict_run<B: TrainOps>(
    run: &TrainedRun<B>,
    samples: &[Sample],
    symmetry_mean: bool,
    device: &B::Device,
) -> Vec<f64> {
    if symmetry_mean {
        predict_images_symmetry_mean(&run.net, run.config.model, samples, &run.input, device)
    } else {
        let batch = HostBatch::from_samples(samples, &run.input);
        predict_images(&run.net, run.config.model, &batch, device)
    }
}

/// The mean of several runs' renderings (a seed ensemble; one run returns its own rendering unchanged). Averaging
/// renderings, not parameters, makes this valid for any mix of BRDF models and input planes, and by convexity its
/// squared error on every image is at most the members' mean squared error. Cost: one network pass and one
/// render per member.
pub fn predict_ensemble<B: TrainOps>(
    runs: &[TrainedRun<B>],
    samples: &[Sample],
    symmetry_mean: bool,
    device: &B::Device,
) -> Vec<f64> {
    let mut runs = runs.iter();
    let first = runs.next().expect("an ensemble has at least one run");
    let mut sum = predict_run(first, samples, symmetry_mean, device);
    let mut members = 1.0;
    for run in runs {
        for (total, x) in sum
            .iter_mut()
            .zip(predict_run(run, samples, symmetry_mean, device))
        {
            *total += x;
        }
        members += 1.0;
    }
    if members > 1.0 {
        sum.iter_mut().for_each(|x| *x /= members);
    }
    sum
}

//! The loss a step minimises, and validation.

use anyhow::Result;
use burn::prelude::*;
use dataset::contract::schema::{Split, CROP_PX};
use dataset::science::brdf::BrdfModel;

use crate::data::{for_each_sample_group, HostBatch, InputNormalisation, SampleSource};
use crate::kernels::{TrainBackend, TrainOps};
use crate::metrics::{AggregateMetrics, MetricsAccumulator};
use crate::model::UNet;
use crate::prediction::{net_outputs, predict_images};
use crate::renderer_layer::{render_loss, HostTerms, SceneTerms};

/// One optimisation step's loss (masked MSE through the renderer layer).
pub fn train_loss<B: TrainBackend>(
    net: &UNet<B>,
    model: BrdfModel,
    batch: &HostBatch,
    device: &B::Device,
) -> Tensor<B, 1> {
    train_loss_with_terms(net, batch, &HostTerms::evaluate(batch, model), device)
}

/// [`train_loss`] with the batch's scene terms evaluated ahead (a fit's loader thread does).
pub fn train_loss_with_terms<B: TrainBackend>(
    net: &UNet<B>,
    batch: &HostBatch,
    terms: &HostTerms,
    device: &B::Device,
) -> Tensor<B, 1> {
    let scene = SceneTerms::<B>::upload(terms, batch, device);
    let image = Tensor::<B, 4>::from_data(
        TensorData::new(batch.image.clone(), [batch.len(), 1, 128, 128]),
        device,
    );
    render_loss(net_outputs(net, batch, device), &scene, image)
}

/// Validation over (up to `max`, spread evenly over the split) val samples, in inference mode, one row group in memory at a time.
pub fn validate<B: TrainOps>(
    net: &UNet<B>,
    model: BrdfModel,
    input: &InputNormalisation,
    source: &dyn SampleSource,
    max: Option<usize>,
    batch_size: usize,
    device: &B::Device,
) -> Result<AggregateMetrics> {
    input.check_dataset(source)?;
    let mut metrics = MetricsAccumulator::default();
    for_each_sample_group(source, Split::Val, max, "validate", |samples| {
        for chunk in samples.chunks(batch_size) {
            let batch = HostBatch::from_samples(chunk, input);
            let rendered = predict_images(net, model, &batch, device);
            let px = CROP_PX * CROP_PX;
            for i in 0..batch.len() {
                let range = i * px..(i + 1) * px;
                let valid: Vec<bool> = batch.valid[range.clone()]
                    .iter()
                    .map(|&v| v > 0.0)
                    .collect();
                metrics.add(
                    &rendered[range.clone()],
                    &batch.image[range],
                    &valid,
                    CROP_PX,
                );
            }
        }
    })?;
    Ok(metrics.finish())
}

//! `train`: the Burn side. Read in data-flow order: [`data`] (shards → host batches, epoch order, prefetch) with
//! [`augment`] → [`model`] (U-Net) → [`render`] (differentiable renderer layer, the batched twin of
//! `dataset::brdf`) → [`metrics`] → [`training`] (fit loop, checkpoints, exact resume; [`averaging`]: the weight average) →
//! [`bench`].

pub mod augment;
pub mod averaging;
pub mod baseline;
pub mod bench;
pub mod data;
pub mod evaluation;
pub mod features;
pub mod inference;
pub mod kernels;
pub mod metrics;
pub mod model;
pub mod plot;
pub mod raycast;
pub mod render;
pub mod render_views;
pub mod report;
pub mod training;
pub mod trajectory;

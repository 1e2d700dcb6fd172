//! The renderer layer in f64 (its own test binary: Burn's default float type is set once per process):
//! equality with the scalar reference, gradients against central finite differences for every model on the
//! hard-case suite, masked pixels with exactly zero gradient, and no NaN/Inf forward or backward.

use burn::backend::{Autodiff, Flex};
use burn::prelude::*;
use burn::tensor::{set_default_dtypes, FloatDType, IntDType};
use dataset::contract::schema::CROP_PX;
use dataset::science::brdf::BrdfModel;
use train::data::{HostBatch, InputNormalisation};
use train::renderer_layer::{reference_render, render, render_loss, SceneTerms};
use train::testing::{hard_case_samples, synthetic_samples, test_params};

type Ad = Autodiff<Flex>;

fn f64_device() -> burn::backend::flex::FlexDevice {
    let device = Default::default();
    // Only the first call in the process succeeds; later ones find F64 already set (or fail loudly below).
    let _ = set_default_dtypes::<Flex>(&device, FloatDType::F64, IntDType::I64);
    device
}

fn to_f64(t: Tensor<impl Backend, 4>) -> Vec<f64> {
    let data = t.into_data();
    assert_eq!(
        data.dtype,
        burn::tensor::DType::F64,
        "tensors must be f64 in this binary"
    );
    data.into_vec::<f64>().unwrap()
}

fn batch() -> HostBatch {
    let mut samples = synthetic_samples(1, 4);
    samples.extend(hard_case_samples());
    HostBatch::from_samples(&samples, &InputNormalisation::relief(20.0))
}

fn params_tensor(model: BrdfModel, values: Vec<f64>, n: usize) -> Tensor<Ad, 4> {
    Tensor::from_data(
        TensorData::new(values, [n, model.param_count(), CROP_PX, CROP_PX]),
        &f64_device(),
    )
}

#[test]
fn batched_layer_equals_scalar_reference_in_f64() {
    let device = f64_device();
    let batch = batch();
    for model in BrdfModel::ALL {
        let scene = SceneTerms::<Flex>::from_host(&batch, model, &device);
        let params = test_params(model, batch.len(), 8);
        let expected = reference_render(model, &batch, &params);
        let tensor = Tensor::<Flex, 4>::from_data(
            TensorData::new(params, [batch.len(), model.param_count(), CROP_PX, CROP_PX]),
            &device,
        );
        let got = to_f64(render(tensor, &scene));
        let scale = expected.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let worst = got
            .iter()
            .zip(&expected)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(
            worst <= 1e-10 * scale,
            "{model:?}: max error {worst:e} (scale {scale})"
        );
    }
}

/// A batch's geometry and image on the autodiff backend (no gradient tracked: only parameters get one).
struct Scene {
    terms: SceneTerms<Ad>,
    image: Tensor<Ad, 4>,
    n: usize,
}

fn scene(batch: &HostBatch, model: BrdfModel) -> Scene {
    let device = f64_device();
    let n = batch.len();
    Scene {
        terms: SceneTerms::<Ad>::from_host(batch, model, &device),
        image: Tensor::from_data(
            TensorData::new(batch.image.clone(), [n, 1, CROP_PX, CROP_PX]),
            &device,
        ),
        n,
    }
}

/// Loss and its gradient w.r.t. the parameter maps, through the train step's fused loss (on f64 tensors, its
/// stock-operation path: `kernels::reference::render_masked_mse`).
fn loss_and_grad(model: BrdfModel, scene: &Scene, params: &[f64]) -> (f64, Vec<f64>) {
    let p = params_tensor(model, params.to_vec(), scene.n).require_grad();
    let loss = render_loss(p.clone(), &scene.terms, scene.image.clone());
    let value = loss.clone().into_data().into_vec::<f64>().unwrap()[0];
    let grads = loss.backward();
    (
        value,
        to_f64(p.grad(&grads).expect("parameters get a gradient")),
    )
}

#[test]
fn gradients_equal_central_differences_on_hard_geometries() {
    let batch = batch();
    let npx = CROP_PX * CROP_PX;
    for model in BrdfModel::ALL {
        let scene = scene(&batch, model);
        let params = test_params(model, batch.len(), 21);
        let (loss, grad) = loss_and_grad(model, &scene, &params);
        assert!(
            loss.is_finite() && grad.iter().all(|g| g.is_finite()),
            "{model:?}"
        );
        // Probe every sample and parameter at pixels of every kind: valid, invalid (k % 11 == 0), half-lit.
        let scale = grad.iter().fold(0.0f64, |m, g| m.max(g.abs()));
        for sample in 0..batch.len() {
            for k in 0..model.param_count() {
                for pixel in [0, 11, 13, 5000, 8256, 12345, npx - 1] {
                    let index = (sample * model.param_count() + k) * npx + pixel;
                    // The loss is quadratic in each parameter away from LeakyReLU's kink (test_params keeps ≥ 1e-2
                    // from it), so central differences have no truncation error and a large step keeps the
                    // rounding error (≈ 1e-16 · loss / h) far below the smallest gradients probed (~1e-9).
                    let h = 1e-3;
                    let (mut plus, mut minus) = (params.clone(), params.clone());
                    plus[index] += h;
                    minus[index] -= h;
                    let fd = (loss_and_grad(model, &scene, &plus).0
                        - loss_and_grad(model, &scene, &minus).0)
                        / (2.0 * h);
                    let g = grad[index];
                    assert!(
                        (g - fd).abs() <= 1e-4 * g.abs().max(1e-3 * scale),
                        "{model:?} sample {sample} param {k} pixel {pixel}: autodiff {g:e} vs FD {fd:e}"
                    );
                    if batch.valid[sample * npx + pixel] == 0.0 {
                        assert_eq!(g, 0.0, "masked pixels get exactly zero gradient");
                    }
                }
            }
        }
    }
}

#[test]
fn all_invalid_batch_gives_finite_zero_loss_and_zero_gradient() {
    let mut batch = batch();
    batch.valid.iter_mut().for_each(|v| *v = 0.0);
    for model in BrdfModel::ALL {
        let scene = scene(&batch, model);
        let params = test_params(model, batch.len(), 2);
        let (loss, grad) = loss_and_grad(model, &scene, &params);
        assert_eq!(loss, 0.0, "{model:?}");
        assert!(
            grad.iter().all(|&g| g == 0.0),
            "{model:?}: gradient must be exactly zero"
        );
    }
}

#[test]
fn forward_and_backward_are_finite_for_extreme_parameters() {
    let batch = batch();
    for model in BrdfModel::ALL {
        let scene = scene(&batch, model);
        for magnitude in [1e-12, 1.0, 1e6] {
            let params: Vec<f64> = test_params(model, batch.len(), 3)
                .into_iter()
                .map(|v| v.signum() * magnitude)
                .collect();
            let (loss, grad) = loss_and_grad(model, &scene, &params);
            assert!(loss.is_finite(), "{model:?} at {magnitude}: loss {loss}");
            assert!(
                grad.iter().all(|g| g.is_finite()),
                "{model:?} at {magnitude}"
            );
        }
    }
}

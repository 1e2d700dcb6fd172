//! The differentiable renderer layer: predicted raw parameter maps and a batch's geometry (DEM crops with apron,
//! per-sample sun direction, camera position and map→ground Jacobian, lit fraction, valid mask) → rendered I/F,
//! `I = E · V_sun · Σ LeakyReLU(p_k) · T_k` with E = 1 (the parameters carry the scale) and f = 0 where the
//! surface faces away from sun or camera, as in [`dataset::science::brdf`].
//!
//! Only the parameter maps carry a gradient; the geometry is a constant of the batch. So the geometric terms
//! `T_k · V_sun` (zero where the surface faces away) are evaluated once per batch on the host, by the scalar f64
//! reference itself ([`dataset::science::geometry::crop_pixel_geometry`], [`BrdfModel::terms`]) as [`HostTerms`]
//! (in a fit, by the loader thread ahead of the step), and uploaded as one `[N, P, 128, 128]` tensor; on the device the layer is one multiply-and-sum forward and
//! one multiply backward. One home for the geometry (the reference), no f32 rounding of near-degenerate
//! geometry (M6's azimuths, Hapke's opposition peak), and no per-pixel vector algebra in tensor operations.

use burn::prelude::*;
use dataset::contract::schema::{CROP_PX, DEM_PX};
use dataset::science::brdf::{BrdfModel, LEAKY_SLOPE};
use rayon::prelude::*;

use crate::data::HostBatch;
use crate::kernels::TrainOps;

/// A batch's constant inputs to the layer, on the device.
#[derive(Clone, Debug)]
pub struct SceneTerms<B: Backend> {
    /// `[N, P, 128, 128]`: the model's geometric terms times the lit fraction, 0 where the surface faces away
    /// from the sun or the camera.
    pub terms: Tensor<B, 4>,
    /// `[N, 1, 128, 128]`: 1 where the photograph is usable, else 0.
    pub valid: Tensor<B, 4>,
}

impl<B: Backend> SceneTerms<B> {
    /// Evaluate `model`'s terms for a host batch (f64 on the host, both cores) and upload them.
    pub fn from_host(batch: &HostBatch, model: BrdfModel, device: &B::Device) -> Self {
        Self::upload(&HostTerms::evaluate(batch, model), batch, device)
    }

    /// Upload terms evaluated ahead ([`HostTerms`]) with the batch's valid mask. The device's float type decides
    /// the stored precision: f64 (tests) as evaluated, else each value rounded once to f32.
    pub fn upload(terms: &HostTerms, batch: &HostBatch, device: &B::Device) -> Self {
        let shape = [batch.len(), terms.model.param_count(), CROP_PX, CROP_PX];
        assert_eq!(
            terms.values.len(),
            shape.iter().product::<usize>(),
            "scene terms evaluated for another batch"
        );
        let terms = match Tensor::<B, 1>::zeros([1], device).dtype() {
            burn::tensor::DType::F64 => TensorData::new(terms.values.clone(), shape),
            _ => TensorData::new(
                terms.values.iter().map(|&t| t as f32).collect::<Vec<f32>>(),
                shape,
            ),
        };
        Self {
            terms: Tensor::from_data(terms, device),
            valid: Tensor::from_data(
                TensorData::new(batch.valid.clone(), [batch.len(), 1, CROP_PX, CROP_PX]),
                device,
            ),
        }
    }
}

/// A batch's geometric terms on the host, f64, `N × P × 128²` (sample, term, pixel): `T_k · V_sun` where the
/// surface faces sun and camera, else 0. Only M6 needs the half-angle frame, so only M6 pays for it.
///
/// A fit evaluates them in its loader thread ([`HostTerms::evaluate_serial`]) while the previous step runs: the
/// step leaves a core idle while it runs single-threaded parts (autodiff bookkeeping, the optimiser), and the
/// terms (transcendental Hapke per pixel) were a twentieth of the step's work. Same function, same values.
#[derive(Clone, Debug, PartialEq)]
pub struct HostTerms {
    pub model: BrdfModel,
    pub values: Vec<f64>,
}

impl HostTerms {
    /// The terms, samples in parallel (rayon).
    pub fn evaluate(batch: &HostBatch, model: BrdfModel) -> Self {
        Self::evaluate_with(batch, model, true)
    }

    /// The terms, one sample after another on the calling thread: for a thread that should not queue work on the
    /// pool the step runs on.
    pub fn evaluate_serial(batch: &HostBatch, model: BrdfModel) -> Self {
        Self::evaluate_with(batch, model, false)
    }

    fn evaluate_with(batch: &HostBatch, model: BrdfModel, parallel: bool) -> Self {
        let (npx, p) = (CROP_PX * CROP_PX, model.param_count());
        let mut values = vec![0.0f64; batch.len() * p * npx];
        let sample_terms = |(i, planes): (usize, &mut [f64])| {
            let (grid, sun, camera) = sample_frame(batch, i);
            let heights = &batch.relative_heights_m[i * DEM_PX * DEM_PX..(i + 1) * DEM_PX * DEM_PX];
            let lit = &batch.lit[i * npx..(i + 1) * npx];
            let frames =
                dataset::science::geometry::crop_pixel_frames(heights, CROP_PX, &grid, camera);
            for (px, (normal, view)) in frames.enumerate() {
                if let Some(terms) = model.pixel_terms(normal, sun, view) {
                    for (k, t) in terms.into_iter().take(p).enumerate() {
                        planes[k * npx + px] = t * lit[px];
                    }
                }
            }
        };
        if parallel {
            values
                .par_chunks_mut(p * npx)
                .enumerate()
                .for_each(sample_terms);
        } else {
            values
                .chunks_mut(p * npx)
                .enumerate()
                .for_each(sample_terms);
        }
        Self { model, values }
    }
}

/// Rendered I/F `[N, 1, 128, 128]` = Σ_k LeakyReLU(p_k) · T_k (E = 1: the parameters carry the scale).
pub fn render<B: Backend>(raw_params: Tensor<B, 4>, scene: &SceneTerms<B>) -> Tensor<B, 4> {
    crate::kernels::stock::render(raw_params, scene.terms.clone(), LEAKY_SLOPE)
}

/// The train step's loss, the mean squared error of [`render`] over the valid pixels of the whole batch (0, with a
/// zero gradient, when none is valid), as one operation ([`crate::kernels::render_masked_mse`]),
/// the same value and gradient (tested) in one pass each way instead of a dozen broadcasting tensor operations.
pub fn render_loss<B: TrainOps>(
    raw_params: Tensor<B, 4>,
    scene: &SceneTerms<B>,
    image: Tensor<B, 4>,
) -> Tensor<B, 1> {
    crate::kernels::render_masked_mse(
        raw_params,
        scene.terms.clone(),
        image,
        scene.valid.clone(),
        LEAKY_SLOPE,
    )
}

/// The scalar f64 reference ([`dataset::science::geometry::crop_pixel_geometry`] + [`dataset::science::brdf::render_crop`]) applied
/// to a host batch, sample by sample: what [`render`] must reproduce. `planar_params` is `N × P × 128²`.
pub fn reference_render(model: BrdfModel, batch: &HostBatch, planar_params: &[f64]) -> Vec<f64> {
    let (npx, p) = (CROP_PX * CROP_PX, model.param_count());
    let mut out = Vec::with_capacity(batch.len() * npx);
    for i in 0..batch.len() {
        out.extend(dataset::science::brdf::render_crop(
            model,
            &planar_params[i * p * npx..(i + 1) * p * npx],
            &host_pixel_geometry(batch, i),
            &batch.lit[i * npx..(i + 1) * npx],
            1.0,
        ));
    }
    out
}

/// The scalar reference geometry ([`dataset::science::geometry::crop_pixel_geometry`]) of sample `i` of a host batch.
pub fn host_pixel_geometry(
    batch: &HostBatch,
    i: usize,
) -> Vec<dataset::science::geometry::PixelGeometry> {
    let (grid, sun, camera) = sample_frame(batch, i);
    dataset::science::geometry::crop_pixel_geometry(
        &batch.relative_heights_m[i * DEM_PX * DEM_PX..(i + 1) * DEM_PX * DEM_PX],
        CROP_PX,
        &grid,
        sun,
        camera,
    )
}

/// Sample `i`'s crop grid, sun direction and camera position.
fn sample_frame(
    batch: &HostBatch,
    i: usize,
) -> (
    dataset::science::geometry::CropGrid,
    glam::DVec3,
    glam::DVec3,
) {
    let grid = dataset::science::geometry::CropGrid {
        gsd_m: batch.gsd_m[i],
        map_to_en: batch.map_to_en[4 * i..4 * i + 4]
            .try_into()
            .expect("4 entries"),
        origin_height_m: batch.origin_height_m[i],
    };
    let v3 = |v: &[f64]| glam::DVec3::new(v[3 * i], v[3 * i + 1], v[3 * i + 2]);
    (grid, v3(&batch.sun_dir_enu), v3(&batch.camera_pos_enu_m))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::InputNormalisation;
    use crate::testing::{hard_case_samples, synthetic_samples, test_params};

    type Cpu = burn::backend::Flex;

    #[test]
    fn terms_evaluated_ahead_on_one_thread_are_the_pool_s_bits() {
        let mut samples = synthetic_samples(3, 11);
        samples.extend(hard_case_samples());
        let batch = HostBatch::from_samples(&samples, &InputNormalisation::relief(20.0));
        for model in BrdfModel::ALL {
            let (pool, serial) = (
                HostTerms::evaluate(&batch, model),
                HostTerms::evaluate_serial(&batch, model),
            );
            assert_eq!(
                pool.values.len(),
                batch.len() * model.param_count() * CROP_PX * CROP_PX
            );
            assert!(
                pool.values.iter().any(|&t| t != 0.0),
                "{model:?}: no lit, visible pixel in the batch"
            );
            let same_bits = pool
                .values
                .iter()
                .zip(&serial.values)
                .all(|(a, b)| a.to_bits() == b.to_bits());
            assert!(same_bits && pool.model == serial.model, "{model:?}");
        }
    }

    #[test]
    fn batched_layer_equals_scalar_reference_in_f32() {
        let device = Default::default();
        let mut samples = synthetic_samples(2, 3);
        samples.extend(hard_case_samples());
        let batch = HostBatch::from_samples(&samples, &InputNormalisation::relief(20.0));
        for model in BrdfModel::ALL {
            let scene = SceneTerms::<Cpu>::from_host(&batch, model, &device);
            let params = test_params(model, batch.len(), 5);
            let expected = reference_render(model, &batch, &params);
            let n = batch.len();
            let tensor = Tensor::<Cpu, 4>::from_data(
                TensorData::new(params, [n, model.param_count(), CROP_PX, CROP_PX]),
                &device,
            );
            let got: Vec<f64> = render(tensor, &scene)
                .into_data()
                .convert::<f64>()
                .into_vec()
                .unwrap();
            let scale = expected.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            // Every pixel, M6's degenerate alignments included: the geometry is the reference's own (f64).
            let worst = (0..got.len())
                .map(|k| (got[k] - expected[k]).abs())
                .fold(0.0, f64::max);
            assert!(
                worst <= 1e-5 * scale,
                "{model:?}: max error {worst:e} vs image scale {scale}"
            );
        }
    }
}

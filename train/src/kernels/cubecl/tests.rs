//! The matrix-product weight gradients against each backend's own (`conv2d_weight_backward`) on Flex and, with
//! the `wgpu` feature, on wgpu (Mesa's lavapipe in CI): the GPU code path these kernels exist for.
//!
//! Tolerance: both sides sum the same products in f32 in different orders (pieces of rows against one long
//! running sum or gemm's blocks), so they agree to rounding: max |Δ| ≤ 1e-5 · max |expected|.

use burn::backend::Flex;
use burn::prelude::*;
use burn::tensor::ops::{ConvOptions, ModuleOps};

use super::super::{primitive, stock, tensor};
use super::conv::{conv2d_weight_grad, upsample_conv2d_weight_grad};

const TOLERANCE: f32 = 1e-5;

/// Uniform values in [−1.7, 1.7) from a keyed host stream (not the backend RNG, which parallel tests share).
fn random<B: Backend, const D: usize>(
    shape: [usize; D],
    seed: u64,
    device: &B::Device,
) -> Tensor<B, D> {
    use rand::Rng;
    let mut rng = dataset::contract::rng::keyed_rng(seed, "cubecl-kernel-tests", 0);
    let values: Vec<f32> = (0..shape.iter().product::<usize>())
        .map(|_| rng.random_range(-1.732f32..1.732))
        .collect();
    Tensor::from_data(TensorData::new(values, shape), device)
}

fn values<B: Backend, const D: usize>(t: Tensor<B, D>) -> Vec<f32> {
    t.into_data().convert::<f32>().into_vec().unwrap()
}

/// The worst |a − b| over max |b|.
fn relative_difference(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    let scale = b.iter().fold(f32::MIN_POSITIVE, |m, v| m.max(v.abs()));
    let worst = a
        .iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0f32, f32::max);
    worst / scale
}

/// One convolution of the cases below: input shape, output channels, kernel, padding.
struct Case {
    x: [usize; 4],
    c_out: usize,
    kernel: [usize; 2],
    padding: [usize; 2],
}

/// The network's convolutions (3 × 3 same, 1 × 1), a valid 3 × 3, an oblong kernel with unequal padding, odd
/// planes, and planes that split into several pieces (64 × 40: 16 rows a piece; 130 × 9: 113 rows, prime).
const CASES: [Case; 6] = [
    Case {
        x: [2, 5, 13, 11],
        c_out: 7,
        kernel: [3, 3],
        padding: [1, 1],
    },
    Case {
        x: [3, 4, 64, 40],
        c_out: 6,
        kernel: [3, 3],
        padding: [1, 1],
    },
    Case {
        x: [2, 6, 9, 10],
        c_out: 3,
        kernel: [1, 1],
        padding: [0, 0],
    },
    Case {
        x: [1, 3, 12, 7],
        c_out: 2,
        kernel: [3, 3],
        padding: [0, 0],
    },
    Case {
        x: [2, 2, 10, 8],
        c_out: 3,
        kernel: [5, 3],
        padding: [2, 1],
    },
    Case {
        x: [1, 2, 113, 130],
        c_out: 2,
        kernel: [3, 3],
        padding: [1, 1],
    },
];

/// For every case: the worst relative difference between [`conv2d_weight_grad`] and `B`'s own weight gradient.
fn weight_grad_differences<B: Backend>(device: &B::Device) -> Vec<f32> {
    CASES
        .iter()
        .enumerate()
        .map(|(i, case)| {
            let [n, c, h, w] = case.x;
            let [kh, kw] = case.kernel;
            let options = ConvOptions::new([1, 1], case.padding, [1, 1], 1);
            let x = random::<B, 4>(case.x, 10 * i as u64, device);
            let weight = random::<B, 4>([case.c_out, c, kh, kw], 10 * i as u64 + 1, device);
            let [h_out, w_out] = [
                h + 2 * case.padding[0] + 1 - kh,
                w + 2 * case.padding[1] + 1 - kw,
            ];
            let dy = random::<B, 4>([n, case.c_out, h_out, w_out], 10 * i as u64 + 2, device);
            let ours = tensor::<B, 4>(conv2d_weight_grad::<B>(
                primitive(x.clone()),
                primitive(weight.clone()),
                primitive(dy.clone()),
                options.clone(),
            ));
            let theirs = tensor::<B, 4>(B::conv2d_weight_backward(
                primitive(x),
                primitive(weight),
                primitive(dy),
                options,
            ));
            assert_eq!(ours.dims(), theirs.dims());
            relative_difference(&values(ours), &values(theirs))
        })
        .collect()
}

/// The up convolution's weight gradient against the stock one (upsample, then the backend's own).
fn upsample_weight_grad_difference<B: Backend>(device: &B::Device) -> f32 {
    let x = random::<B, 4>([2, 6, 9, 7], 70, device);
    let weight = random::<B, 4>([4, 6, 3, 3], 71, device);
    let dy = random::<B, 4>([2, 4, 18, 14], 72, device);
    let ours = tensor::<B, 4>(upsample_conv2d_weight_grad::<B>(
        primitive(x.clone()),
        primitive(weight.clone()),
        primitive(dy.clone()),
    ));
    let theirs = tensor::<B, 4>(stock::upsample_conv2d_weight_grad::<B>(
        primitive(x),
        primitive(weight),
        primitive(dy),
    ));
    relative_difference(&values(ours), &values(theirs))
}

fn assert_within_tolerance(backend: &str, differences: &[f32]) {
    let shown: Vec<String> = differences.iter().map(|d| format!("{d:.1e}")).collect();
    eprintln!("{backend}: relative differences by case {shown:?}");
    for (i, d) in differences.iter().enumerate() {
        assert!(
            *d <= TOLERANCE,
            "{backend}, case {i}: the matmul weight gradient differs from the backend's by {d:e} of its scale"
        );
    }
}

#[test]
fn weight_grads_match_flex_own() {
    let device = Default::default();
    let mut differences = weight_grad_differences::<Flex>(&device);
    differences.push(upsample_weight_grad_difference::<Flex>(&device));
    assert_within_tolerance("flex", &differences);
}

/// A convolution the pieces do not cover (stride 2) is the backend's own, bit for bit.
#[test]
fn other_convolutions_go_to_the_backend_kernel() {
    let device = Default::default();
    let options = ConvOptions::new([2, 2], [1, 1], [1, 1], 1);
    let x = random::<Flex, 4>([2, 3, 9, 9], 80, &device);
    let weight = random::<Flex, 4>([4, 3, 3, 3], 81, &device);
    let dy = random::<Flex, 4>([2, 4, 5, 5], 82, &device);
    let ours = conv2d_weight_grad::<Flex>(
        primitive(x.clone()),
        primitive(weight.clone()),
        primitive(dy.clone()),
        options.clone(),
    );
    let theirs =
        Flex::conv2d_weight_backward(primitive(x), primitive(weight), primitive(dy), options);
    assert_eq!(
        values(tensor::<Flex, 4>(ours)),
        values(tensor::<Flex, 4>(theirs))
    );
}

#[cfg(feature = "wgpu")]
mod wgpu {
    use super::*;
    use burn::backend::Wgpu;

    #[test]
    fn weight_grads_match_wgpu_own() {
        let device = Default::default();
        let mut differences = weight_grad_differences::<Wgpu>(&device);
        differences.push(upsample_weight_grad_difference::<Wgpu>(&device));
        assert_within_tolerance("wgpu", &differences);
    }

    /// The same inputs on wgpu (the matmul path) and on Flex (the backend's own kernel) give the same gradient:
    /// the kernels are right on the GPU path, not only consistent with it.
    #[test]
    fn wgpu_weight_grad_matches_flex() {
        let case = &CASES[1];
        let [n, c, h, w] = case.x;
        let options = ConvOptions::new([1, 1], case.padding, [1, 1], 1);
        let device = Default::default();
        let x = random::<Wgpu, 4>(case.x, 90, &device);
        let weight = random::<Wgpu, 4>([case.c_out, c, 3, 3], 91, &device);
        let dy = random::<Wgpu, 4>([n, case.c_out, h, w], 92, &device);
        let on_wgpu = values(tensor::<Wgpu, 4>(conv2d_weight_grad::<Wgpu>(
            primitive(x),
            primitive(weight),
            primitive(dy),
            options.clone(),
        )));
        let flex_device = Default::default();
        let x = random::<Flex, 4>(case.x, 90, &flex_device);
        let weight = random::<Flex, 4>([case.c_out, c, 3, 3], 91, &flex_device);
        let dy = random::<Flex, 4>([n, case.c_out, h, w], 92, &flex_device);
        let on_flex = values(tensor::<Flex, 4>(Flex::conv2d_weight_backward(
            primitive(x),
            primitive(weight),
            primitive(dy),
            options.clone(),
        )));
        let d = relative_difference(&on_wgpu, &on_flex);
        eprintln!("wgpu (matmul) against flex (own): {d:.1e}");
        assert!(d <= TOLERANCE, "wgpu (matmul) against flex (own): {d:e}");
    }
}

//! The convolution gradients here (weight gradients as matrix products, input gradients as forward convolutions)
//! against each backend's own (`conv2d_weight_backward`, `conv2d_x_backward`) on Flex and, with the `wgpu`
//! feature, on wgpu (Mesa's lavapipe in CI): the GPU code path these kernels exist for.
//!
//! Tolerance: both sides sum the same products in f32 in different orders (pieces of rows against one long
//! running sum or gemm's blocks), so they agree to rounding: max |Δ| ≤ 1e-5 · max |expected|. Measured (Intel
//! Xeon, lavapipe 22.3.6): at most 2.9e-6 (weight gradients, whose reductions are the longest: 7,680 products in
//! case 1) and 3.7e-7 (input gradients); wgpu against Flex's own 1.6e-6 and 2.9e-7.

use burn::backend::Flex;
use burn::prelude::*;
use burn::tensor::ops::{ConvOptions, FloatTensor, ModuleOps};

use super::super::{primitive, stock, tensor};
use super::conv::{
    conv2d_weight_grad, conv2d_x_grad, upsample_conv2d_weight_grad, upsample_conv2d_x_grad,
    weight_grad_by_samples,
};

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
/// planes, and planes that split into several pieces (64 × 40: 16 rows a piece; 113 × 130: a prime row count, one
/// row a piece).
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

/// For every case, the worst relative difference between the gradients here and `B`'s own: weight and input
/// gradients of each convolution, then those of the up convolution against the stock ones (upsample, then the
/// backend's own). Each named for the assertion's message.
fn gradient_differences<B: Backend>(device: &B::Device) -> Vec<(String, f32)> {
    let mut differences = Vec::new();
    for (i, case) in CASES.iter().enumerate() {
        let [n, c, h, w] = case.x;
        let [kh, kw] = case.kernel;
        let options = ConvOptions::new([1, 1], case.padding, [1, 1], 1);
        let seed = 10 * i as u64;
        let x = random::<B, 4>(case.x, seed, device);
        let weight = random::<B, 4>([case.c_out, c, kh, kw], seed + 1, device);
        let [h_out, w_out] = [
            h + 2 * case.padding[0] + 1 - kh,
            w + 2 * case.padding[1] + 1 - kw,
        ];
        let dy = random::<B, 4>([n, case.c_out, h_out, w_out], seed + 2, device);
        let ours = conv2d_weight_grad::<B>(p(&x), p(&weight), p(&dy), options.clone());
        let theirs = B::conv2d_weight_backward(p(&x), p(&weight), p(&dy), options.clone());
        differences.push((format!("case {i} weight"), difference::<B>(ours, theirs)));
        let ours = conv2d_x_grad::<B>(p(&x), p(&weight), p(&dy), options.clone());
        let theirs = B::conv2d_x_backward(p(&x), p(&weight), p(&dy), options);
        differences.push((format!("case {i} input"), difference::<B>(ours, theirs)));
    }
    let x = random::<B, 4>([2, 6, 9, 7], 70, device);
    let weight = random::<B, 4>([4, 6, 3, 3], 71, device);
    let dy = random::<B, 4>([2, 4, 18, 14], 72, device);
    let ours = upsample_conv2d_weight_grad::<B>(p(&x), p(&weight), p(&dy));
    let theirs = stock::upsample_conv2d_weight_grad::<B>(p(&x), p(&weight), p(&dy));
    differences.push(("up weight".into(), difference::<B>(ours, theirs)));
    let ours = upsample_conv2d_x_grad::<B>(p(&weight), p(&dy));
    let theirs = stock::upsample_conv2d_x_grad::<B>(p(&x), p(&weight), p(&dy));
    differences.push(("up input".into(), difference::<B>(ours, theirs)));
    differences
}

fn p<B: Backend>(t: &Tensor<B, 4>) -> FloatTensor<B> {
    primitive(t.clone())
}

fn difference<B: Backend>(ours: FloatTensor<B>, theirs: FloatTensor<B>) -> f32 {
    let (ours, theirs) = (tensor::<B, 4>(ours), tensor::<B, 4>(theirs));
    assert_eq!(ours.dims(), theirs.dims());
    relative_difference(&values(ours), &values(theirs))
}

fn assert_within_tolerance(backend: &str, differences: &[(String, f32)]) {
    let shown: Vec<String> = differences
        .iter()
        .map(|(what, d)| format!("{what} {d:.1e}"))
        .collect();
    eprintln!("{backend}: relative differences: {}", shown.join(", "));
    for (what, d) in differences {
        assert!(
            *d <= TOLERANCE,
            "{backend}, {what}: the gradient here differs from the backend's by {d:e} of its scale"
        );
    }
}

#[test]
fn gradients_match_flex_own() {
    assert_within_tolerance("flex", &gradient_differences::<Flex>(&Default::default()));
}

/// Convolutions the rewrites do not cover (stride 2) get the backend's own gradients, bit for bit.
#[test]
fn other_convolutions_go_to_the_backend_kernels() {
    let device = Default::default();
    let options = ConvOptions::new([2, 2], [1, 1], [1, 1], 1);
    let x = random::<Flex, 4>([2, 3, 9, 9], 80, &device);
    let weight = random::<Flex, 4>([4, 3, 3, 3], 81, &device);
    let dy = random::<Flex, 4>([2, 4, 5, 5], 82, &device);
    let bits = |t: FloatTensor<Flex>| values(tensor::<Flex, 4>(t));
    assert_eq!(
        bits(conv2d_weight_grad::<Flex>(
            p(&x),
            p(&weight),
            p(&dy),
            options.clone()
        )),
        bits(Flex::conv2d_weight_backward(
            p(&x),
            p(&weight),
            p(&dy),
            options.clone()
        ))
    );
    assert_eq!(
        bits(conv2d_x_grad::<Flex>(
            p(&x),
            p(&weight),
            p(&dy),
            options.clone()
        )),
        bits(Flex::conv2d_x_backward(p(&x), p(&weight), p(&dy), options))
    );
}

/// A batch whose im2col matrix passes the byte bound is taken in groups of samples (here one sample, then two,
/// with a remainder) and gives the same gradient as in one piece.
#[test]
fn weight_grad_in_groups_of_samples_matches_the_whole_batch() {
    let device = Default::default();
    let x = random::<Flex, 4>([5, 3, 12, 10], 100, &device);
    let dy = random::<Flex, 4>([5, 4, 12, 10], 101, &device);
    let per_sample = 14 * 12 * 3 * 9 * 4;
    let whole = weight_grad_by_samples(x.clone(), dy.clone(), [3, 3], [1, 1], usize::MAX);
    for samples in [1, 2] {
        let grouped =
            weight_grad_by_samples(x.clone(), dy.clone(), [3, 3], [1, 1], samples * per_sample);
        let d = relative_difference(&values(grouped), &values(whole.clone()));
        assert!(d <= TOLERANCE, "groups of {samples}: {d:e}");
    }
}

#[cfg(feature = "wgpu")]
mod wgpu {
    use super::*;
    use burn::backend::Wgpu;

    #[test]
    fn gradients_match_wgpu_own() {
        assert_within_tolerance("wgpu", &gradient_differences::<Wgpu>(&Default::default()));
    }

    /// `TrainOps` on wgpu runs the rewrites unless switched to stock (no test switches it: the switch is
    /// process-wide): its weight and input gradients are the rewrites' to the bit.
    #[test]
    fn wgpu_train_ops_run_the_rewrites() {
        use super::super::super::TrainOps;
        let device = Default::default();
        let options = ConvOptions::new([1, 1], [1, 1], [1, 1], 1);
        let x = random::<Wgpu, 4>([2, 3, 10, 9], 110, &device);
        let weight = random::<Wgpu, 4>([4, 3, 3, 3], 111, &device);
        let dy = random::<Wgpu, 4>([2, 4, 10, 9], 112, &device);
        let bits = |t: FloatTensor<Wgpu>| values(tensor::<Wgpu, 4>(t));
        assert_eq!(
            bits(Wgpu::train_conv2d_weight_grad(
                p(&x),
                p(&weight),
                p(&dy),
                options.clone()
            )),
            bits(conv2d_weight_grad::<Wgpu>(
                p(&x),
                p(&weight),
                p(&dy),
                options.clone()
            ))
        );
        assert_eq!(
            bits(Wgpu::train_conv2d_x_grad(
                p(&x),
                p(&weight),
                p(&dy),
                options.clone()
            )),
            bits(conv2d_x_grad::<Wgpu>(p(&x), p(&weight), p(&dy), options))
        );
    }

    /// The same inputs on wgpu (the rewrites) and on Flex (its own kernels) give the same gradients: the
    /// rewrites are right on the GPU path, not only consistent with it.
    #[test]
    fn wgpu_gradients_match_flex() {
        let case = &CASES[1];
        let [n, c, h, w] = case.x;
        let options = ConvOptions::new([1, 1], case.padding, [1, 1], 1);
        let on_wgpu = {
            let device = Default::default();
            let x = random::<Wgpu, 4>(case.x, 90, &device);
            let weight = random::<Wgpu, 4>([case.c_out, c, 3, 3], 91, &device);
            let dy = random::<Wgpu, 4>([n, case.c_out, h, w], 92, &device);
            [
                conv2d_weight_grad::<Wgpu>(p(&x), p(&weight), p(&dy), options.clone()),
                conv2d_x_grad::<Wgpu>(p(&x), p(&weight), p(&dy), options.clone()),
            ]
            .map(|g| values(tensor::<Wgpu, 4>(g)))
        };
        let device = Default::default();
        let x = random::<Flex, 4>(case.x, 90, &device);
        let weight = random::<Flex, 4>([case.c_out, c, 3, 3], 91, &device);
        let dy = random::<Flex, 4>([n, case.c_out, h, w], 92, &device);
        let on_flex = [
            Flex::conv2d_weight_backward(p(&x), p(&weight), p(&dy), options.clone()),
            Flex::conv2d_x_backward(p(&x), p(&weight), p(&dy), options),
        ]
        .map(|g| values(tensor::<Flex, 4>(g)));
        for (what, (ours, theirs)) in ["weight", "input"].iter().zip(on_wgpu.iter().zip(&on_flex)) {
            let d = relative_difference(ours, theirs);
            eprintln!("wgpu (rewrites) against flex (own), {what}: {d:.1e}");
            assert!(d <= TOLERANCE, "wgpu against flex, {what}: {d:e}");
        }
    }
}

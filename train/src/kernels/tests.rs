//! Every kernel against Burn's stock operations and autodiff: values, all gradients, running statistics.

use burn::backend::{Autodiff, Flex};
use burn::module::Param;
use burn::nn::conv::Conv2dConfig;
use burn::nn::{BatchNormConfig, PaddingConfig2d};
use burn::prelude::*;
use burn::tensor::activation::leaky_relu;

use super::*;

type Ad = Autodiff<Flex>;

/// Uniform values in [−1.7, 1.7) (unit variance) from a keyed host stream, not the backend RNG, which parallel
/// tests share.
fn random<const D: usize>(shape: [usize; D], seed: u64) -> Tensor<Ad, D> {
    use rand::Rng;
    let mut rng = dataset::contract::rng::keyed_rng(seed, "kernel-tests", 0);
    let values: Vec<f32> = (0..shape.iter().product::<usize>())
        .map(|_| rng.random_range(-1.732f32..1.732))
        .collect();
    Tensor::from_data(TensorData::new(values, shape), &Default::default())
}

fn values<const D: usize, B: Backend>(t: Tensor<B, D>) -> Vec<f32> {
    t.into_data().convert::<f32>().into_vec().unwrap()
}

/// max |a − b| ≤ tol · max |b| (relative to the expected values' own scale, however small).
fn assert_close(what: &str, a: Vec<f32>, b: Vec<f32>, tol: f32) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    let scale = b.iter().fold(f32::MIN_POSITIVE, |m, v| m.max(v.abs()));
    let worst = a
        .iter()
        .zip(&b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0f32, f32::max);
    assert!(
        worst <= tol * scale,
        "{what}: max difference {worst:e} at scale {scale}"
    );
}

/// Fused vs stock BatchNorm + LeakyReLU: forward, ∂x, ∂γ, ∂β (through a random linear loss) and the running
/// statistics after two steps, on a shape whose planes are not a SIMD multiple.
#[test]
fn fused_batch_norm_matches_stock_batch_norm_and_autodiff() {
    let device = Default::default();
    let (shape, slope) = ([3, 5, 7, 9], 0.01);
    let weights = random(shape, 2);
    let run = |fused: bool| {
        let mut norm = BatchNormConfig::new(shape[1]).init::<Ad>(&device);
        norm.gamma = Param::from_tensor((random([shape[1]], 3) * 0.3 + 1.0).detach());
        norm.beta = Param::from_tensor((random([shape[1]], 4) * 0.5).detach());
        let mut grads_out = Vec::new();
        let mut outputs = Vec::new();
        for step in 0..2u64 {
            let x = (random(shape, 10 + step) * 2.0 + 0.7).require_grad();
            let y = if fused {
                batch_norm_leaky_relu(&norm, x.clone(), slope)
            } else {
                leaky_relu(norm.forward(x.clone()), slope)
            };
            let grads = (y.clone() * weights.clone()).sum().backward();
            outputs.push(values(y));
            grads_out.push((
                values(x.grad(&grads).unwrap()),
                values(norm.gamma.grad(&grads).unwrap()),
                values(norm.beta.grad(&grads).unwrap()),
            ));
        }
        let stats = (
            values(norm.running_mean.value()),
            values(norm.running_var.value()),
        );
        (outputs, grads_out, stats)
    };
    let (fused, stock) = (run(true), run(false));
    for step in 0..2 {
        assert_close("output", fused.0[step].clone(), stock.0[step].clone(), 1e-5);
        assert_close("dx", fused.1[step].0.clone(), stock.1[step].0.clone(), 1e-4);
        assert_close(
            "dgamma",
            fused.1[step].1.clone(),
            stock.1[step].1.clone(),
            1e-4,
        );
        assert_close(
            "dbeta",
            fused.1[step].2.clone(),
            stock.1[step].2.clone(),
            1e-5,
        );
    }
    assert_close("running mean", fused.2 .0, stock.2 .0, 1e-6);
    assert_close("running var", fused.2 .1, stock.2 .1, 1e-5);
}

/// Inference-mode BatchNorm + LeakyReLU (running statistics, no autodiff: validation and inference) against
/// Burn's own module: the stock default (what CUDA runs) to the bit, the Flex kernel to f32 rounding.
#[test]
fn inference_batch_norm_matches_burns_module() {
    let device = Default::default();
    let (shape, slope, c) = ([3, 5, 7, 9], 0.01, 5);
    let mut norm = BatchNormConfig::new(c).init::<Flex>(&device);
    norm.gamma = Param::from_tensor(random([c], 3).inner() * 0.3 + 1.0);
    norm.beta = Param::from_tensor(random([c], 4).inner() * 0.5);
    norm.running_mean = burn::module::RunningState::new(random([c], 5).inner() * 0.8);
    norm.running_var = burn::module::RunningState::new(random([c], 6).inner().abs() * 2.0 + 0.05);
    let x = random(shape, 7).inner() * 2.0 + 0.7;
    let burn_module = values(leaky_relu(norm.forward(x.clone()), slope));
    let stock_default = values(tensor::<Flex, 4>(stock::batch_norm_leaky_relu_inference::<
        Flex,
    >(
        primitive(x.clone()),
        primitive(norm.gamma.val()),
        primitive(norm.beta.val()),
        primitive(norm.running_mean.value()),
        primitive(norm.running_var.value()),
        norm.epsilon,
        slope,
    )));
    assert_eq!(
        stock_default, burn_module,
        "the stock default is Burn's module, bit for bit"
    );
    let kernel = values(batch_norm_leaky_relu(&norm, x, slope));
    assert!(
        kernel.iter().any(|&v| v < 0.0) && kernel.iter().any(|&v| v > 0.0),
        "both sides of the LeakyReLU are exercised"
    );
    assert_close("inference output", kernel, burn_module, 1e-6);
}

/// The stock-op defaults (what CUDA runs) against Burn's autodiff of the stock module.
#[test]
fn stock_batch_norm_backward_matches_autodiff() {
    let device = Default::default();
    let (shape, slope, eps) = ([2, 3, 6, 5], 0.01, 1e-5);
    let x = (random(shape, 20) * 1.5 - 0.2).require_grad();
    let weights = random(shape, 21);
    let norm = BatchNormConfig::new(shape[1]).init::<Ad>(&device);
    let y = leaky_relu(norm.forward(x.clone()), slope);
    let grads = (y.clone() * weights.clone()).sum().backward();
    let inner = |t: Tensor<Ad, 4>| primitive(t.inner());
    let out = stock::batch_norm_leaky_relu::<Flex>(
        inner(x.clone()),
        primitive(norm.gamma.val().inner()),
        primitive(norm.beta.val().inner()),
        eps,
        slope,
    );
    assert_close(
        "output",
        values(tensor::<Flex, 4>(out.output.clone())),
        values(y),
        1e-5,
    );
    let g = stock::batch_norm_leaky_relu_backward::<Flex>(
        inner(x.clone()),
        primitive(norm.gamma.val().inner()),
        out.mean,
        out.var,
        out.output,
        inner(weights),
        eps,
        slope,
    );
    assert_close(
        "dx",
        values(tensor::<Flex, 4>(g.x)),
        values(x.grad(&grads).unwrap()),
        1e-4,
    );
    assert_close(
        "dgamma",
        values(tensor::<Flex, 1>(g.gamma)),
        values(norm.gamma.grad(&grads).unwrap()),
        1e-4,
    );
}

/// Conv through [`TrainOps`] against the stock convolution and its autodiff: output, ∂x, ∂W, ∂b, for the
/// network's 3×3 (padding 1) and 1×1 convolutions and a 5×5 with padding 2, on odd plane sizes.
#[test]
fn train_conv2d_matches_stock_conv_and_autodiff() {
    let device = Default::default();
    for (kernel, padding, c_in, c_out, bias) in [
        (3, 1, 4, 6, true),
        (1, 0, 5, 3, true),
        (5, 2, 2, 3, false),
        (3, 1, 1, 8, true),
    ] {
        let shape = [3, c_in, 11, 13];
        let conv = Conv2dConfig::new([c_in, c_out], [kernel, kernel])
            .with_padding(PaddingConfig2d::Explicit(
                padding, padding, padding, padding,
            ))
            .with_bias(bias)
            .init::<Ad>(&device);
        let weights = random([3, c_out, 11, 13], 31);
        let run = |fused: bool| {
            let x = random(shape, 30).require_grad();
            let y = if fused {
                conv2d(&conv, x.clone())
            } else {
                conv.forward(x.clone())
            };
            let grads = (y.clone() * weights.clone()).sum().backward();
            (
                values(y),
                values(x.grad(&grads).unwrap()),
                values(conv.weight.grad(&grads).unwrap()),
                conv.bias.as_ref().map(|b| values(b.grad(&grads).unwrap())),
            )
        };
        let (fused, stock) = (run(true), run(false));
        let what = format!("{kernel}x{kernel} conv");
        assert_close(&format!("{what} output"), fused.0, stock.0, 1e-5);
        assert_close(&format!("{what} dx"), fused.1, stock.1, 1e-5);
        assert_close(&format!("{what} dW"), fused.2, stock.2, 1e-5);
        if let (Some(a), Some(b)) = (fused.3, stock.3) {
            assert_close(&format!("{what} db"), a, b, 1e-5);
        }
    }
}

/// Dropout on Flex: kept elements are scaled by 1/keep and the rest are zero, exactly as the returned mask says,
/// and the gradient goes through the same mask; the kept share matches the probability (±6σ); the mask is a pure
/// function of its seed (same seed, same mask; another seed, another). The seed itself comes from the backend
/// RNG, which parallel tests share, so determinism is checked on the seeded function.
#[test]
fn dropout_masks_scale_and_reproduce() {
    let (shape, prob) = ([2, 3, 100, 100], 0.3);
    let keep = 1.0 - prob;
    let x = (random(shape, 40) + 3.0).require_grad();
    let out = Ad::dropout(primitive(x.clone()), prob);
    let (y, mask) = (tensor::<Ad, 4>(out.output), tensor::<Ad, 4>(out.mask));
    let weights = random(shape, 41);
    let grads = (y.clone() * weights.clone()).sum().backward();
    let (dx, weights) = (values(x.grad(&grads).unwrap()), values(weights));
    let (x, y, mask) = (values(x), values(y), values(mask));
    let n = x.len() as f64;
    let kept = mask.iter().filter(|&&m| m == 1.0).count() as f64;
    assert!(mask.iter().all(|&m| m == 0.0 || m == 1.0), "mask is 0/1");
    let sigma = (keep * prob / n).sqrt();
    assert!(
        (kept / n - keep).abs() <= 6.0 * sigma,
        "kept share {} for keep {keep}",
        kept / n
    );
    for i in 0..x.len() {
        let expected = x[i] * mask[i] / keep as f32;
        assert!(
            (y[i] - expected).abs() <= 1e-6 * expected.abs().max(1.0),
            "output {i}"
        );
        let g = weights[i] * mask[i] / keep as f32;
        assert!((dx[i] - g).abs() <= 1e-6 * g.abs().max(1.0), "gradient {i}");
    }
    let seeded = |seed| super::flex::dropout::dropout_mask(&x, prob, seed).1;
    assert_eq!(seeded(5), seeded(5), "same seed, same mask");
    assert_ne!(seeded(5), seeded(6), "another seed, another mask");
}

/// Training is reproducible bit for bit whatever the thread count: every Flex kernel that sums across samples
/// or positions gives identical bits in a 1-thread and a 3-thread pool.
#[test]
fn kernels_give_the_same_bits_on_any_thread_count() {
    use burn::backend::Flex;
    let x = primitive(random([5, 6, 13, 11], 60).inner());
    let w = primitive(random([7, 6, 3, 3], 61).inner());
    let dy = primitive(random([5, 7, 13, 11], 62).inner());
    let gamma = primitive(random([6], 63).inner());
    let beta = primitive(random([6], 64).inner());
    let options = ConvOptions::new([1, 1], [1, 1], [1, 1], 1);
    let bias = primitive(random([7], 65).inner());
    let up_dy = primitive(random([5, 7, 26, 22], 66).inner());
    let terms = primitive(random([5, 6, 13, 11], 67).inner());
    let image = primitive(random([5, 1, 13, 11], 68).inner());
    let valid = primitive(
        random([5, 1, 13, 11], 69)
            .greater_elem(-0.5)
            .float()
            .inner(),
    );
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let t = |p| values(tensor::<Flex, 4>(p));
            let loss = Flex::render_masked_mse(
                x.clone(),
                terms.clone(),
                image.clone(),
                valid.clone(),
                0.01,
            );
            let norm =
                Flex::batch_norm_leaky_relu(x.clone(), gamma.clone(), beta.clone(), 1e-5, 0.01);
            let grads = Flex::batch_norm_leaky_relu_backward(
                x.clone(),
                gamma.clone(),
                beta.clone(),
                norm.mean.clone(),
                norm.var.clone(),
                norm.output.clone(),
                x.clone(),
                1e-5,
                0.01,
            );
            vec![
                t(Flex::train_conv2d(
                    x.clone(),
                    w.clone(),
                    None,
                    options.clone(),
                )),
                t(Flex::train_conv2d_x_grad(
                    x.clone(),
                    w.clone(),
                    dy.clone(),
                    options.clone(),
                )),
                t(Flex::train_conv2d_weight_grad(
                    x.clone(),
                    w.clone(),
                    dy.clone(),
                    options.clone(),
                )),
                values(tensor::<Flex, 1>(Flex::train_conv2d_bias_grad(dy.clone()))),
                t(norm.output),
                t(grads.x),
                values(tensor::<Flex, 1>(grads.gamma)),
                // The up convolution (coarse input `x`, the fine gradient `up_dy`), the fused loss and its
                // gradient, the skip join's split, and a dropout mask from a fixed seed.
                t(Flex::train_upsample_conv2d(
                    x.clone(),
                    w.clone(),
                    Some(bias.clone()),
                )),
                t(Flex::train_upsample_conv2d_x_grad(
                    x.clone(),
                    w.clone(),
                    up_dy.clone(),
                )),
                t(Flex::train_upsample_conv2d_weight_grad(
                    x.clone(),
                    w.clone(),
                    up_dy.clone(),
                )),
                values(tensor::<Flex, 1>(loss.loss.clone())),
                t(Flex::render_masked_mse_backward(
                    x.clone(),
                    terms.clone(),
                    loss.residual,
                    primitive(Tensor::<Flex, 1>::from_floats([1.0], &Default::default())),
                    0.01,
                )),
                t(Flex::train_join_channels(x.clone(), dy.clone(), 0.01)),
                t(Flex::train_join_channels_backward(x.clone(), dy.clone(), 0.01).0),
                super::flex::dropout::dropout_mask(&values(tensor::<Flex, 4>(x.clone())), 0.3, 9).1,
            ]
        })
    };
    let (one, three) = (run(1), run(3));
    for (k, (a, b)) in one.iter().zip(&three).enumerate() {
        let same = a.iter().zip(b).all(|(a, b)| a.to_bits() == b.to_bits());
        assert!(same, "output {k} differs between 1 and 3 threads");
    }
}

/// The up convolution on the coarse grid against Burn's nearest interpolation then 3×3 convolution, through
/// autodiff: output, ∂x (coarse), ∂W, ∂b, on odd coarse sizes.
#[test]
fn upsample_conv2d_matches_interpolate_then_conv() {
    use burn::tensor::module::interpolate;
    use burn::tensor::ops::{InterpolateMode, InterpolateOptions};
    let device = Default::default();
    let (c_in, c_out) = (5, 4);
    let conv = Conv2dConfig::new([c_in, c_out], [3, 3])
        .with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1))
        .init::<Ad>(&device);
    let weights = random([3, c_out, 14, 10], 71);
    let run = |fused: bool| {
        let x = random([3, c_in, 7, 5], 70).require_grad();
        let y = if fused {
            upsample_conv2d(&conv, x.clone())
        } else {
            let fine = interpolate(
                x.clone(),
                [14, 10],
                InterpolateOptions::new(InterpolateMode::Nearest),
            );
            conv.forward(fine)
        };
        let grads = (y.clone() * weights.clone()).sum().backward();
        (
            values(y),
            values(x.grad(&grads).unwrap()),
            values(conv.weight.grad(&grads).unwrap()),
            values(conv.bias.as_ref().unwrap().grad(&grads).unwrap()),
        )
    };
    let (fused, stock) = (run(true), run(false));
    assert_close("output", fused.0, stock.0, 1e-5);
    assert_close("dx", fused.1.clone(), stock.1.clone(), 1e-5);
    assert_close("dW", fused.2.clone(), stock.2.clone(), 1e-5);
    assert_close("db", fused.3, stock.3, 1e-5);
    // The stock-op defaults give the same gradients.
    let inner = |t: Tensor<Ad, 4>| primitive(t.inner());
    let (x, w, dy) = (
        inner(random([3, c_in, 7, 5], 70)),
        inner(conv.weight.val()),
        inner(weights),
    );
    let dx = stock::upsample_conv2d_x_grad::<Flex>(x.clone(), w.clone(), dy.clone());
    let dw = stock::upsample_conv2d_weight_grad::<Flex>(x, w, dy);
    assert_close("stock dx", values(tensor::<Flex, 4>(dx)), stock.1, 1e-5);
    assert_close("stock dW", values(tensor::<Flex, 4>(dw)), stock.2, 1e-5);
}

/// Planes large enough that the kernels work in several row blocks (`flex::conv::ConvShape::block_rows`: 3 blocks for
/// the 3×3 convolution's 288 taps × 64 columns, forward, weight gradient and the input gradient's adjoint
/// convolution alike; 2 for the up convolution's 128 phase taps and its adjoints'): output and every gradient
/// against the stock operations and autodiff, so a block boundary that dropped or repeated a row fails.
#[test]
fn blocked_convolutions_match_stock_on_planes_larger_than_a_block() {
    use burn::tensor::module::interpolate;
    use burn::tensor::ops::{InterpolateMode, InterpolateOptions};
    let device = Default::default();
    let (c_in, c_out, h, w) = (32, 32, 40, 64);
    let conv = Conv2dConfig::new([c_in, c_out], [3, 3])
        .with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1))
        .init::<Ad>(&device);
    for up in [false, true] {
        let out_hw = if up { [2 * h, 2 * w] } else { [h, w] };
        let weights = random([2, c_out, out_hw[0], out_hw[1]], 81);
        let run = |fused: bool| {
            let x = random([2, c_in, h, w], 80).require_grad();
            let y = match (up, fused) {
                (false, true) => conv2d(&conv, x.clone()),
                (false, false) => conv.forward(x.clone()),
                (true, true) => upsample_conv2d(&conv, x.clone()),
                (true, false) => conv.forward(interpolate(
                    x.clone(),
                    out_hw,
                    InterpolateOptions::new(InterpolateMode::Nearest),
                )),
            };
            let grads = (y.clone() * weights.clone()).sum().backward();
            (
                values(y),
                values(x.grad(&grads).unwrap()),
                values(conv.weight.grad(&grads).unwrap()),
            )
        };
        let (fused, stock) = (run(true), run(false));
        let what = if up { "up conv" } else { "3x3 conv" };
        assert_close(&format!("{what} output"), fused.0, stock.0, 1e-5);
        assert_close(&format!("{what} dx"), fused.1, stock.1, 1e-5);
        assert_close(&format!("{what} dW"), fused.2, stock.2, 1e-5);
    }
}

/// The up path's join against the stock composition (LeakyReLU, then `Tensor::cat`) through autodiff: output and
/// both gradients exactly (values on both sides of the kink), each gradient contiguous; the CPU backward equals
/// the stock-operation default.
#[test]
fn join_channels_matches_leaky_relu_then_cat_and_splits_its_gradient() {
    let weights = random([3, 7, 6, 5], 91);
    let run = |fused: bool| {
        let a = random([3, 4, 6, 5], 92).require_grad();
        let b = random([3, 3, 6, 5], 93).require_grad();
        let y = if fused {
            join_channels(a.clone(), b.clone(), 0.01)
        } else {
            Tensor::cat(vec![leaky_relu(a.clone(), 0.01), b.clone()], 1)
        };
        let grads = (y.clone() * weights.clone()).sum().backward();
        let (ga, gb) = (a.grad(&grads).unwrap(), b.grad(&grads).unwrap());
        if fused {
            for g in [&ga, &gb] {
                assert!(
                    primitive(g.clone()).is_contiguous(),
                    "split gradients are contiguous"
                );
            }
        }
        (values(y), values(ga), values(gb))
    };
    let (fused, stock) = (run(true), run(false));
    assert!(fused.1.iter().any(|&g| g != 0.0) && fused.0.iter().any(|&y| y < 0.0));
    assert_eq!(fused, stock, "the join and its gradient are exact");
    let (a, g) = (
        primitive(random([3, 4, 6, 5], 94).inner()),
        primitive(weights.inner()),
    );
    let (fa, fb) = Flex::train_join_channels_backward(a.clone(), g.clone(), 0.01);
    let (ra, rb) = stock::join_channels_backward::<Flex>(a, g, 0.01);
    assert_eq!(values(tensor::<Flex, 4>(fa)), values(tensor::<Flex, 4>(ra)));
    assert_eq!(values(tensor::<Flex, 4>(fb)), values(tensor::<Flex, 4>(rb)));
}

/// The joined pointwise convolution against the convolution of the materialised join (features repeated as
/// constant planes, then concatenated): the output and every gradient (x, the features, the weight, the bias),
/// through autodiff, with more output channels than one and a plane that is not a SIMD multiple. Only the order
/// of the sums differs, so the two agree to f32 rounding.
#[test]
fn pointwise_conv_of_joined_features_matches_the_materialised_join() {
    let device = Default::default();
    let ([n, c, h, w], k, p) = ([3, 4, 7, 5], 6, 2);
    let weights = random([n, p, h, w], 101);
    let mut conv = Conv2dConfig::new([c + k, p], [1, 1]).init::<Ad>(&device);
    conv.weight = Param::from_tensor(random([p, c + k, 1, 1], 102).detach());
    conv.bias = Some(Param::from_tensor(random([p], 103).detach()));
    let run = |split: bool| {
        let x = random([n, c, h, w], 104).require_grad();
        let f = random([n, k], 105).require_grad();
        let y = if split {
            pointwise_conv2d_joined(&conv, x.clone(), &f)
        } else {
            let planes = f
                .clone()
                .reshape([n, k, 1, 1])
                .repeat_dim(2, h)
                .repeat_dim(3, w);
            conv2d(&conv, Tensor::cat(vec![x.clone(), planes], 1))
        };
        let grads = (y.clone() * weights.clone()).sum().backward();
        let grad = |t: Option<Tensor<Flex, 4>>| values(t.expect("a gradient"));
        (
            values(y),
            grad(x.grad(&grads)),
            values(f.grad(&grads).expect("a gradient")),
            grad(conv.weight.grad(&grads)),
            values(
                conv.bias
                    .as_ref()
                    .unwrap()
                    .grad(&grads)
                    .expect("a gradient"),
            ),
        )
    };
    let (split, joined) = (run(true), run(false));
    assert_close("output", split.0, joined.0, 1e-6);
    assert_close("dx", split.1, joined.1, 1e-6);
    assert_close("dfeatures", split.2, joined.2, 1e-6);
    assert_close("dweight", split.3, joined.3, 1e-6);
    assert_close("dbias", split.4, joined.4, 1e-6);
}

/// The fused render + masked MSE against the stock composition (LeakyReLU, product with the terms, sum over
/// terms, squared error under the mask over the mask's count) through autodiff: the loss and ∂raw, with raw values
/// on both sides of LeakyReLU's kink and a mask with holes; an empty mask gives 0 and a zero gradient, as stock.
#[test]
fn render_masked_mse_matches_the_stock_composition() {
    let slope = 0.01;
    let (n, p, h, w) = (3, 4, 9, 7);
    let terms = random([n, p, h, w], 101).abs();
    let image = random([n, 1, h, w], 102).abs();
    for (what, valid) in [
        (
            "holes",
            random([n, 1, h, w], 103).greater_elem(-0.5).float(),
        ),
        (
            "empty",
            Tensor::<Ad, 4>::zeros([n, 1, h, w], &Default::default()),
        ),
    ] {
        let run = |fused: bool| {
            let raw = random([n, p, h, w], 104).require_grad();
            let loss = if fused {
                render_masked_mse(
                    raw.clone(),
                    terms.clone(),
                    image.clone(),
                    valid.clone(),
                    slope,
                )
            } else {
                let rendered = (leaky_relu(raw.clone(), slope) * terms.clone()).sum_dim(1);
                let count = valid.clone().sum().clamp_min(1.0);
                ((rendered - image.clone()).square() * valid.clone()).sum() / count
            };
            let grads = loss.clone().backward();
            (values(loss), values(raw.grad(&grads).unwrap()))
        };
        let (fused, stock) = (run(true), run(false));
        assert_close(&format!("{what}: loss"), fused.0, stock.0, 1e-6);
        assert_close(&format!("{what}: d raw"), fused.1, stock.1, 1e-6);
    }
    // The stock-op defaults (the CubeCL backends' path) against the CPU kernels.
    let inner = |t: Tensor<Ad, 4>| primitive(t.inner());
    let valid = random([n, 1, h, w], 103).greater_elem(-0.5).float();
    let (raw, t, i, v) = (
        inner(random([n, p, h, w], 104)),
        inner(terms),
        inner(image),
        inner(valid),
    );
    let cpu = Flex::render_masked_mse(raw.clone(), t.clone(), i.clone(), v.clone(), slope);
    let stock = stock::render_masked_mse::<Flex>(raw.clone(), t.clone(), i, v, slope);
    let loss = |l| values(tensor::<Flex, 1>(l));
    assert_close("stock loss", loss(stock.loss), loss(cpu.loss), 1e-6);
    let g = primitive(Tensor::<Flex, 1>::from_floats([0.5], &Default::default()));
    let d_cpu =
        Flex::render_masked_mse_backward(raw.clone(), t.clone(), cpu.residual, g.clone(), slope);
    let d_stock = stock::render_masked_mse_backward::<Flex>(raw, t, stock.residual, g, slope);
    assert_close(
        "stock d raw",
        values(tensor::<Flex, 4>(d_stock)),
        values(tensor::<Flex, 4>(d_cpu)),
        1e-6,
    );
}

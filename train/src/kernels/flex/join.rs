//! `[LeakyReLU(a), b]` along channels (an up stage joined with its skip) and its backward pass.

use super::*;

/// `[LeakyReLU(a), b]` along channels, per sample: the first part activated as it is copied, the second copied.
pub fn join_channels(a: FloatTensor<Flex>, b: FloatTensor<Flex>, slope: f64) -> FloatTensor<Flex> {
    let (Some((ac, a_shape)), Some((bc, b_shape))) = (f32_data(&a), f32_data(&b)) else {
        return stock::join_channels::<Flex>(a, b, slope);
    };
    let (sample_a, sample_b) = (
        a_shape[1..].iter().product::<usize>(),
        b_shape[1..].iter().product::<usize>(),
    );
    if sample_a == 0 || sample_b == 0 {
        return stock::join_channels::<Flex>(a, b, slope);
    }
    let slope = slope as f32;
    let (a, b) = (slice(&ac), slice(&bc));
    let fill = |n: usize, out: &mut [std::mem::MaybeUninit<f32>]| {
        let (out_a, out_b) = out.split_at_mut(sample_a);
        let (a, b) = (
            &a[n * sample_a..][..sample_a],
            &b[n * sample_b..][..sample_b],
        );
        vectorized(
            #[inline(always)]
            || {
                out_a.iter_mut().zip(a).for_each(|(y, &x)| {
                    y.write(leaky_relu(x, slope));
                })
            },
        );
        out_b.iter_mut().zip(b).for_each(|(y, &x)| {
            y.write(x);
        });
    };
    // SAFETY: `fill` writes both parts of its sample, `sample_a + sample_b` elements.
    let out = unsafe {
        par_written(
            a_shape[0] * (sample_a + sample_b),
            sample_a + sample_b,
            fill,
        )
    };
    let mut shape = a_shape;
    shape[1] += b_shape[1];
    from_vec(out, &shape)
}

/// The gradient of [`join_channels`]: per sample the output gradient's first `a` channels times LeakyReLU's
/// slope where `a < 0`, and the rest copied, each into a contiguous tensor.
pub fn join_channels_backward(
    a: FloatTensor<Flex>,
    grad: FloatTensor<Flex>,
    slope: f64,
) -> (FloatTensor<Flex>, FloatTensor<Flex>) {
    let (Some((ac, a_shape)), Some((gc, shape))) = (f32_data(&a), f32_data(&grad)) else {
        return stock::join_channels_backward::<Flex>(a, grad, slope);
    };
    let plane = shape[2..].iter().product::<usize>();
    let (sample, sample_a) = (shape[1] * plane, a_shape[1] * plane);
    let sample_b = sample - sample_a;
    if sample_a == 0 || sample_b == 0 {
        return stock::join_channels_backward::<Flex>(a, grad, slope);
    }
    let slope = slope as f32;
    let (g, a) = (slice(&gc), slice(&ac));
    let fill_a = |n: usize, grad_a: &mut [std::mem::MaybeUninit<f32>]| {
        let (g, a) = (&g[n * sample..][..sample_a], &a[n * sample_a..][..sample_a]);
        vectorized(
            #[inline(always)]
            || {
                grad_a
                    .iter_mut()
                    .zip(g.iter().zip(a))
                    .for_each(|(d, (&g, &a))| {
                        d.write(leaky_relu_grad(a, g, slope));
                    })
            },
        );
    };
    let fill_b = |n: usize, grad_b: &mut [std::mem::MaybeUninit<f32>]| {
        let g = &g[n * sample + sample_a..][..sample_b];
        grad_b.iter_mut().zip(g).for_each(|(d, &g)| {
            d.write(g);
        });
    };
    // SAFETY: each `fill` writes every element of its sample's part.
    let (grad_a, grad_b) = unsafe {
        (
            par_written(shape[0] * sample_a, sample_a, fill_a),
            par_written(shape[0] * sample_b, sample_b, fill_b),
        )
    };
    let mut b_shape = shape;
    b_shape[1] -= a_shape[1];
    (from_vec(grad_a, &a_shape), from_vec(grad_b, &b_shape))
}

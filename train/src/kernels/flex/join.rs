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
    let mut out = vec![0.0f32; a_shape[0] * (sample_a + sample_b)];
    out.par_chunks_mut(sample_a + sample_b)
        .zip(
            slice(&ac)
                .par_chunks(sample_a)
                .zip(slice(&bc).par_chunks(sample_b)),
        )
        .for_each(|(out, (a, b))| {
            let (out_a, out_b) = out.split_at_mut(sample_a);
            vectorized(
                #[inline(always)]
                || {
                    out_a
                        .iter_mut()
                        .zip(a)
                        .for_each(|(y, &x)| *y = leaky_relu(x, slope))
                },
            );
            out_b.copy_from_slice(b);
        });
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
    let (mut grad_a, mut grad_b) = (
        vec![0.0f32; shape[0] * sample_a],
        vec![0.0f32; shape[0] * sample_b],
    );
    grad_a
        .par_chunks_mut(sample_a)
        .zip(grad_b.par_chunks_mut(sample_b))
        .zip(
            slice(&gc)
                .par_chunks(sample)
                .zip(slice(&ac).par_chunks(sample_a)),
        )
        .for_each(|((grad_a, grad_b), (g, a))| {
            vectorized(
                #[inline(always)]
                || {
                    grad_a
                        .iter_mut()
                        .zip(g[..sample_a].iter().zip(a))
                        .for_each(|(d, (&g, &a))| *d = leaky_relu_grad(a, g, slope))
                },
            );
            grad_b.copy_from_slice(&g[sample_a..]);
        });
    let mut b_shape = shape;
    b_shape[1] -= a_shape[1];
    (from_vec(grad_a, &a_shape), from_vec(grad_b, &b_shape))
}

//! BatchNorm fused with the LeakyReLU after it. Training mode: statistics in f64 lanes, then one output pass;
//! the backward pass the same two. Inference mode: the output pass alone, from the running statistics.

use super::*;

/// Per-channel mean and biased variance of contiguous `[N, C, plane]` data: one pass of f64 sums of x and x²
/// (f32 data: the cancellation in E[x²] − μ² costs ~1e-16·(1 + μ²/σ²) relative, far below f32 resolution).
fn channel_stats(values: &[f32], c: usize, plane: usize) -> Vec<(f64, f64)> {
    let count = (values.len() / c) as f64;
    (0..c)
        .into_par_iter()
        .map(|k| {
            let (sum, sum_sq) = values
                .chunks(plane)
                .skip(k)
                .step_by(c)
                .map(|p| {
                    lane_sums(p, p, |x, _| {
                        let x = x as f64;
                        (x, x * x)
                    })
                })
                .fold((0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1));
            let mean = sum / count;
            (mean, (sum_sq / count - mean * mean).max(0.0))
        })
        .collect()
}

/// Per channel `(scale, shift)` with `BN(x) = scale·x + shift`: `scale = γ/√(var + ε)`, `shift = β − μ·scale`,
/// from the statistics as stored (f32), so that the backward pass recomputes the forward's pre-activation bit
/// for bit.
fn norm_affine(
    gamma: &[f32],
    beta: &[f32],
    mean: &[f32],
    var: &[f32],
    epsilon: f64,
) -> Vec<(f32, f32)> {
    (0..gamma.len())
        .map(|k| {
            let scale = gamma[k] as f64 / (var[k] as f64 + epsilon).sqrt();
            (
                scale as f32,
                (beta[k] as f64 - mean[k] as f64 * scale) as f32,
            )
        })
        .collect()
}

pub fn batch_norm_leaky_relu(
    x: FloatTensor<Flex>,
    gamma: FloatTensor<Flex>,
    beta: FloatTensor<Flex>,
    epsilon: f64,
    slope: f64,
) -> NormOutput<Flex> {
    let prepared = (f32_data(&x), f32_data(&gamma), f32_data(&beta));
    let (Some((xc, shape)), Some((gamma_c, _)), Some((beta_c, _))) = prepared else {
        return stock::batch_norm_leaky_relu::<Flex>(x, gamma, beta, epsilon, slope);
    };
    let (c, plane) = (shape[1], shape[2..].iter().product::<usize>());
    let values = slice(&xc);
    let stats = channel_stats(values, c, plane);
    let mean: Vec<f32> = stats.iter().map(|s| s.0 as f32).collect();
    let var: Vec<f32> = stats.iter().map(|s| s.1 as f32).collect();
    let affine = norm_affine(slice(&gamma_c), slice(&beta_c), &mean, &var, epsilon);
    NormOutput {
        output: from_vec(affine_leaky_relu(values, &affine, plane, slope), &shape),
        mean: from_vec(mean, &[c]),
        var: from_vec(var, &[c]),
    }
}

/// `LeakyReLU(scale·x + shift)` with channel `p mod C`'s `(scale, shift)` on plane `p`: BatchNorm's output pass.
fn affine_leaky_relu(values: &[f32], affine: &[(f32, f32)], plane: usize, slope: f64) -> Vec<f32> {
    let slope = slope as f32;
    let fill = |p: usize, y: &mut [std::mem::MaybeUninit<f32>]| {
        let (scale, shift) = affine[p % affine.len()];
        let x = &values[p * plane..][..y.len()];
        vectorized(
            #[inline(always)]
            || {
                y.iter_mut().zip(x).for_each(|(y, &x)| {
                    y.write(leaky_relu(scale * x + shift, slope));
                })
            },
        );
    };
    // SAFETY: `fill` writes every element of its plane.
    unsafe { par_written(values.len(), plane, fill) }
}

/// Inference-mode BatchNorm + LeakyReLU: the running statistics folded into one `(scale, shift)` per channel
/// ([`norm_affine`]), then the same single output pass as training. Stock Burn computes it as four broadcasting
/// operations and an activation, each a strided pass over the activations: half of a validation's time
/// (perf; docs/performance.md).
pub fn batch_norm_leaky_relu_inference(
    x: FloatTensor<Flex>,
    gamma: FloatTensor<Flex>,
    beta: FloatTensor<Flex>,
    mean: FloatTensor<Flex>,
    var: FloatTensor<Flex>,
    epsilon: f64,
    slope: f64,
) -> FloatTensor<Flex> {
    let prepared = [&x, &gamma, &beta, &mean, &var].map(f32_data);
    let [Some((xc, shape)), Some((gamma_c, _)), Some((beta_c, _)), Some((mean_c, _)), Some((var_c, _))] =
        prepared
    else {
        return stock::batch_norm_leaky_relu_inference::<Flex>(
            x, gamma, beta, mean, var, epsilon, slope,
        );
    };
    let plane = shape[2..].iter().product::<usize>();
    let affine = norm_affine(
        slice(&gamma_c),
        slice(&beta_c),
        slice(&mean_c),
        slice(&var_c),
        epsilon,
    );
    from_vec(affine_leaky_relu(slice(&xc), &affine, plane, slope), &shape)
}

/// The backward pass of [`batch_norm_leaky_relu`]. The LeakyReLU's slope applies where the pre-activation
/// `z = scale·x + shift` is negative, recomputed from `x` with the forward's own f32 arithmetic: each pass then
/// reads `x` and `∂Y` only (the forward's output is not read; it is one memory stream fewer per pass).
#[allow(clippy::too_many_arguments)]
pub fn batch_norm_leaky_relu_backward(
    x: FloatTensor<Flex>,
    gamma: FloatTensor<Flex>,
    beta: FloatTensor<Flex>,
    mean: FloatTensor<Flex>,
    var: FloatTensor<Flex>,
    output: FloatTensor<Flex>,
    output_grad: FloatTensor<Flex>,
    epsilon: f64,
    slope: f64,
) -> NormGrads<Flex> {
    let prepared = [&x, &gamma, &beta, &mean, &var, &output_grad].map(f32_data);
    let [Some((xc, shape)), Some((gamma_c, _)), Some((beta_c, _)), Some((mean_c, _)), Some((var_c, _)), Some((dy_c, _))] =
        prepared
    else {
        return stock::batch_norm_leaky_relu_backward::<Flex>(
            x,
            gamma,
            mean,
            var,
            output,
            output_grad,
            epsilon,
            slope,
        );
    };
    let (c, plane) = (shape[1], shape[2..].iter().product::<usize>());
    let (xs, dys) = (slice(&xc), slice(&dy_c));
    let (gamma, mean, var) = (slice(&gamma_c), slice(&mean_c), slice(&var_c));
    let affine = norm_affine(gamma, slice(&beta_c), mean, var, epsilon);
    let inv_std: Vec<f64> = var
        .iter()
        .map(|&v| 1.0 / (v as f64 + epsilon).sqrt())
        .collect();
    let slope = slope as f32;
    // g = ∂L/∂z.
    let dz = move |(scale, shift): (f32, f32), x: f32, dy: f32| {
        leaky_relu_grad(scale * x + shift, dy, slope)
    };
    // Σg and Σg·(x − μ) per channel (× σ⁻¹ below gives Σg·x̂).
    let sums: Vec<(f64, f64)> = (0..c)
        .into_par_iter()
        .map(|k| {
            let (m, ab) = (mean[k], affine[k]);
            let (d_beta, d_gamma) = (k..xs.len() / plane)
                .step_by(c)
                .map(|p| {
                    let r = p * plane..(p + 1) * plane;
                    lane_sums(&xs[r.clone()], &dys[r], |x, dy| {
                        let g = dz(ab, x, dy) as f64;
                        (g, g * (x - m) as f64)
                    })
                })
                .fold((0.0, 0.0), |a, b| (a.0 + b.0, a.1 + b.1));
            (d_beta, d_gamma * inv_std[k])
        })
        .collect();
    let count = (xs.len() / c) as f64;
    let fill = |p: usize, dx: &mut [std::mem::MaybeUninit<f32>]| {
        let k = p % c;
        let r = p * plane..p * plane + dx.len();
        let (d_beta, d_gamma) = sums[k];
        let s = inv_std[k];
        // ∂x = γσ⁻¹ (g − mean(g) − x̂·mean(g·x̂))
        let a = (gamma[k] as f64 * s) as f32;
        let b = (d_beta / count) as f32;
        let e = (d_gamma / count * s) as f32;
        let (m, ab) = (mean[k], affine[k]);
        vectorized(
            #[inline(always)]
            || {
                for (dx, (&x, &dy)) in dx.iter_mut().zip(xs[r.clone()].iter().zip(&dys[r])) {
                    dx.write(a * (dz(ab, x, dy) - b - (x - m) * e));
                }
            },
        );
    };
    // SAFETY: `fill` writes every element of its plane.
    let dx = unsafe { par_written(xs.len(), plane, fill) };
    NormGrads {
        x: from_vec(dx, &shape),
        gamma: from_vec(sums.iter().map(|s| s.1 as f32).collect(), &[c]),
        beta: from_vec(sums.iter().map(|s| s.0 as f32).collect(), &[c]),
    }
}

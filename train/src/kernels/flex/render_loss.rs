//! The renderer layer's masked squared error and its gradient, in one pass per sample.

use super::*;

/// The renderer layer's loss in one pass per sample: rendered `r = Σ_k LeakyReLU(p_k)·T_k`, masked squared error
/// summed in f64 per sample (then in sample order: the same bits on any thread count), and the loss's gradient
/// with respect to `r`, `2·valid·(r − I)/count`, which the backward pass reuses.
pub fn render_masked_mse(
    raw: FloatTensor<Flex>,
    terms: FloatTensor<Flex>,
    image: FloatTensor<Flex>,
    valid: FloatTensor<Flex>,
    slope: f64,
) -> super::RenderLoss<Flex> {
    let prepared = [&raw, &terms, &image, &valid].map(f32_data);
    let [Some((raw_c, shape)), Some((terms_c, terms_shape)), Some((image_c, _)), Some((valid_c, _))] =
        prepared
    else {
        return stock::render_masked_mse::<Flex>(raw, terms, image, valid, slope);
    };
    assert_eq!(
        shape, terms_shape,
        "parameter maps and scene terms differ in shape"
    );
    let (p, plane) = (shape[1], shape[2..].iter().product::<usize>());
    let (raw, terms, image, valid) = (
        slice(&raw_c),
        slice(&terms_c),
        slice(&image_c),
        slice(&valid_c),
    );
    let slope = slope as f32;
    let mut residual = vec![0.0f32; shape[0] * plane];
    // (Σ valid·d², Σ valid) per sample, with d = r − I; `residual` holds valid·d until scaled below.
    let partials: Vec<(f64, f64)> = residual
        .par_chunks_mut(plane)
        .enumerate()
        .map(|(n, resid)| {
            let (raw, terms) = (
                &raw[n * p * plane..(n + 1) * p * plane],
                &terms[n * p * plane..(n + 1) * p * plane],
            );
            let (image, valid) = (
                &image[n * plane..(n + 1) * plane],
                &valid[n * plane..(n + 1) * plane],
            );
            resid.iter_mut().enumerate().for_each(|(px, r)| {
                let rendered: f32 = (0..p)
                    .map(|k| leaky_relu(raw[k * plane + px], slope) * terms[k * plane + px])
                    .sum();
                *r = valid[px] * (rendered - image[px]);
            });
            lane_sums(resid, valid, |d, v| ((d * d) as f64 * v as f64, v as f64))
        })
        .collect();
    let (sum, count) = partials
        .iter()
        .fold((0.0f64, 0.0f64), |a, b| (a.0 + b.0, a.1 + b.1));
    let count = count.max(1.0);
    let scale = (2.0 / count) as f32;
    residual.par_iter_mut().for_each(|r| *r *= scale);
    let mut residual_shape = shape;
    residual_shape[1] = 1;
    super::RenderLoss {
        loss: from_vec(vec![(sum / count) as f32], &[1]),
        residual: from_vec(residual, &residual_shape),
    }
}

/// ∂loss/∂p_k = g · residual · T_k · LeakyReLU′(p_k), `g` the loss's incoming gradient (`[1]`).
pub fn render_masked_mse_backward(
    raw: FloatTensor<Flex>,
    terms: FloatTensor<Flex>,
    residual: FloatTensor<Flex>,
    loss_grad: FloatTensor<Flex>,
    slope: f64,
) -> FloatTensor<Flex> {
    let prepared = [&raw, &terms, &residual, &loss_grad].map(f32_data);
    let [Some((raw_c, shape)), Some((terms_c, _)), Some((resid_c, _)), Some((grad_c, _))] =
        prepared
    else {
        return stock::render_masked_mse_backward::<Flex>(raw, terms, residual, loss_grad, slope);
    };
    let (p, plane) = (shape[1], shape[2..].iter().product::<usize>());
    let (raw, terms, resid) = (slice(&raw_c), slice(&terms_c), slice(&resid_c));
    let (g, slope) = (slice(&grad_c)[0], slope as f32);
    let mut d_raw = vec![0.0f32; raw.len()];
    d_raw.par_chunks_mut(plane).enumerate().for_each(|(i, d)| {
        let n = i / p;
        let (raw, terms) = (
            &raw[i * plane..(i + 1) * plane],
            &terms[i * plane..(i + 1) * plane],
        );
        let resid = &resid[n * plane..(n + 1) * plane];
        for (px, d) in d.iter_mut().enumerate() {
            *d = leaky_relu_grad(raw[px], g * resid[px] * terms[px], slope);
        }
    });
    from_vec(d_raw, &shape)
}

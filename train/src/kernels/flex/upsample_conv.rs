//! The U-Net's up convolution, nearest ×2 then 3×3, as four 2×2 convolutions of the coarse input (one per output
//! phase), and its gradients.

use super::conv::*;
use super::*;

/// Rows (or columns) of a 3×3 kernel that fall on each of the two coarse-grid taps of output phase `a` when the
/// input is first repeated ×2 (nearest): phase 0 reads coarse offsets −1 (kernel row 0) and 0 (rows 1, 2); phase 1
/// reads 0 (rows 0, 1) and +1 (row 2).
const PHASE_TAPS: [[&[usize]; 2]; 2] = [[&[0], &[1, 2]], [&[0, 1], &[2]]];

/// The 2×2 coarse-grid convolution of output phase (a, b): same size as the coarse input, padding 1 − a.
fn phase_shape(s: &ConvShape, a: usize, b: usize) -> ConvShape {
    ConvShape {
        kernel: [2, 2],
        padding: [1 - a, 1 - b],
        ..*s
    }
}

/// `K_ab[o][c][t][u] = Σ W[o][c][ky][kx]` over the kernel rows/columns phase (a, b) folds onto coarse tap (t, u).
fn phase_kernel(w: &[f32], c_out: usize, c_in: usize, a: usize, b: usize) -> Vec<f32> {
    let mut k = vec![0.0f32; c_out * c_in * 4];
    for oc in 0..c_out * c_in {
        for t in 0..2 {
            for u in 0..2 {
                k[oc * 4 + t * 2 + u] = PHASE_TAPS[a][t]
                    .iter()
                    .flat_map(|&ky| PHASE_TAPS[b][u].iter().map(move |&kx| (ky, kx)))
                    .map(|(ky, kx)| w[oc * 9 + ky * 3 + kx])
                    .sum();
            }
        }
    }
    k
}

/// The coarse input and 3×3 weight of a supported up-convolution, as [`conv_operands`] (the coarse shape).
fn upsample_conv_operands(
    x: &FlexTensor,
    weight: &FlexTensor,
    third: Option<&FlexTensor>,
) -> Option<(FlexTensor, FlexTensor, Option<FlexTensor>, ConvShape)> {
    let options = ConvOptions::new([1, 1], [1, 1], [1, 1], 1);
    let (xc, wc, third, s) = conv_operands(x, weight, third, &options)?;
    (s.kernel == [3, 3]).then_some((xc, wc, third, s))
}

/// `conv3×3(nearest×2(x)) + b` computed on the coarse grid: for each of the four output phases a 2×2
/// convolution with the 3×3 kernel's taps summed where they read the same coarse pixel (4/9 of the
/// multiply-adds, and no upsampled copy of the input), in cache-sized row blocks as [`conv2d`].
pub fn upsample_conv2d(
    x: FloatTensor<Flex>,
    weight: FloatTensor<Flex>,
    bias: Option<FloatTensor<Flex>>,
) -> FloatTensor<Flex> {
    let Some((xc, wc, bias_c, s)) = upsample_conv_operands(&x, &weight, bias.as_ref()) else {
        return stock::upsample_conv2d::<Flex>(x, weight, bias);
    };
    let (xs, bias) = (slice(&xc), bias_c.as_ref().map(slice));
    let (h, w, hw) = (s.height, s.width, s.positions());
    let (plane_in, _) = s.planes();
    let kernels: Vec<Vec<f32>> = (0..4)
        .map(|p| phase_kernel(slice(&wc), s.c_out, s.c_in, p / 2, p % 2))
        .collect();
    let block = phase_shape(&s, 0, 0).block_len();
    let mut y = vec![0.0f32; s.batch * s.c_out * 4 * hw];
    y.par_chunks_mut(s.c_out * 4 * hw)
        .zip(xs.par_chunks(plane_in))
        .for_each(|(y, x)| {
            with_scratch([block, s.c_out * hw], |col, y_ab| {
                for (p, k) in kernels.iter().enumerate() {
                    let (a, b) = (p / 2, p % 2);
                    convolve_sample(&phase_shape(&s, a, b), x, k, Dst::Write(y_ab), col);
                    for (o, plane) in y_ab.chunks(hw).enumerate() {
                        let shift = bias.map_or(0.0, |b| b[o]);
                        let out = &mut y[o * 4 * hw..(o + 1) * 4 * hw];
                        for i in 0..h {
                            let row = &mut out[(2 * i + a) * 2 * w..][..2 * w];
                            for j in 0..w {
                                row[2 * j + b] = plane[i * w + j] + shift;
                            }
                        }
                    }
                }
            });
        });
    from_vec(y, &[s.batch, s.c_out, 2 * h, 2 * w])
}

/// Phase (a, b) of one sample's `[c_out, 2h, 2w]` gradient as a contiguous `[c_out, h·w]` block.
fn gather_phase(dy: &[f32], s: &ConvShape, a: usize, b: usize, out: &mut [f32]) {
    let (h, w, hw) = (s.height, s.width, s.positions());
    for (o, plane) in out.chunks_mut(hw).enumerate() {
        let fine = &dy[o * 4 * hw..(o + 1) * 4 * hw];
        for i in 0..h {
            let row = &fine[(2 * i + a) * 2 * w..][..2 * w];
            for j in 0..w {
                plane[i * w + j] = row[2 * j + b];
            }
        }
    }
}

/// ∂X (coarse) of the up convolution: the sum over the four phases of each phase convolution's adjoint, a 2×2
/// convolution of that phase's ∂Y with the phase kernel turned by 180° (padding `a`, `b` where the forward had
/// `1 − a`, `1 − b`), accumulated into ∂X without a scatter.
pub fn upsample_conv2d_x_grad(
    x: FloatTensor<Flex>,
    weight: FloatTensor<Flex>,
    output_grad: FloatTensor<Flex>,
) -> FloatTensor<Flex> {
    let Some((_, wc, Some(dy_c), s)) = upsample_conv_operands(&x, &weight, Some(&output_grad))
    else {
        return stock::upsample_conv2d_x_grad::<Flex>(x, weight, output_grad);
    };
    let dy = slice(&dy_c);
    let hw = s.positions();
    let (plane_in, _) = s.planes();
    let adjoint = |a: usize, b: usize| ConvShape {
        c_in: s.c_out,
        c_out: s.c_in,
        kernel: [2, 2],
        padding: [a, b],
        ..s
    };
    let turned: Vec<Vec<f32>> = (0..4)
        .map(|p| {
            let k = phase_kernel(slice(&wc), s.c_out, s.c_in, p / 2, p % 2);
            turned_kernel(&k, s.c_out, s.c_in, [2, 2])
        })
        .collect();
    let block = adjoint(0, 0).block_len();
    let mut dx = vec![0.0f32; s.batch * plane_in];
    dx.par_chunks_mut(plane_in)
        .zip(dy.par_chunks(s.c_out * 4 * hw))
        .for_each(|(dx, dy)| {
            with_scratch([block, s.c_out * hw], |col, dy_ab| {
                for (p, k) in turned.iter().enumerate() {
                    let (a, b) = (p / 2, p % 2);
                    gather_phase(dy, &s, a, b, dy_ab);
                    convolve_sample(&adjoint(a, b), dy_ab, k, Dst::init(dx, p > 0), col);
                }
            });
        });
    from_vec(dx, &s.input_shape())
}

pub fn upsample_conv2d_weight_grad(
    x: FloatTensor<Flex>,
    weight: FloatTensor<Flex>,
    output_grad: FloatTensor<Flex>,
) -> FloatTensor<Flex> {
    let Some((xc, _, Some(dy_c), s)) = upsample_conv_operands(&x, &weight, Some(&output_grad))
    else {
        return stock::upsample_conv2d_weight_grad::<Flex>(x, weight, output_grad);
    };
    let (xs, dy) = (slice(&xc), slice(&dy_c));
    let hw = s.positions();
    let (plane_in, _) = s.planes();
    let phase_len = 4 * s.c_in * s.c_out;
    let phase = |a: usize, b: usize| phase_shape(&s, a, b);
    let block_positions = phase(0, 0).block_rows() * s.width;
    // One partial per sample of the four phase kernels' gradients ∂K_ab (stored ∂K_abᵀ: taps × c_out), summed
    // in sample order (bit-reproducible, as the plain convolution's); the fold of each coarse tap back onto the
    // 3×3 taps it summed is linear, so it runs once on the sum instead of once per sample (it scatters with a
    // stride of c_in·9 and cost as much as the arithmetic when done per sample).
    let mut partials = vec![0.0f32; s.batch * 4 * phase_len];
    partials
        .par_chunks_mut(4 * phase_len)
        .zip(xs.par_chunks(plane_in).zip(dy.par_chunks(s.c_out * 4 * hw)))
        .for_each(|(dk_t, (x, dy))| {
            let lens = [phase(0, 0).block_len(), s.c_out * (hw + block_positions)];
            with_scratch(lens, |col, buffers| {
                let (dy_ab, dy_t) = buffers.split_at_mut(s.c_out * hw);
                for (p, dk_t) in dk_t.chunks_mut(phase_len).enumerate() {
                    let (a, b) = (p / 2, p % 2);
                    gather_phase(dy, &s, a, b, dy_ab);
                    weight_grad_sample(&phase(a, b), x, dy_ab, dk_t, col, dy_t);
                }
            });
        });
    let dk_t = sum_in_order(&partials, 4 * phase_len);
    // Each coarse tap (t, u) of phase (a, b) spreads back onto the 3×3 taps it summed.
    let mut dw = vec![0.0f32; s.c_out * s.c_in * 9];
    for (p, dk_t) in dk_t.chunks(phase_len).enumerate() {
        let (a, b) = (p / 2, p % 2);
        for c in 0..s.c_in {
            for t in 0..2 {
                for u in 0..2 {
                    let row = &dk_t[((c * 2 + t) * 2 + u) * s.c_out..][..s.c_out];
                    for &ky in PHASE_TAPS[a][t] {
                        for &kx in PHASE_TAPS[b][u] {
                            for (o, &g) in row.iter().enumerate() {
                                dw[(o * s.c_in + c) * 9 + ky * 3 + kx] += g;
                            }
                        }
                    }
                }
            }
        }
    }
    from_vec(dw, &[s.c_out, s.c_in, 3, 3])
}

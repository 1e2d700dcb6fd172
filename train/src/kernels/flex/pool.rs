//! 2 × 2 stride-2 max-pooling with the argmax kept for the backward pass.

use super::*;

/// 2 × 2 stride-2 max-pool of even-sized f32 planes; `argmax` holds, per output, the window position (0–3, row
/// major) of the first maximum, as Burn's pooling picks it. Other inputs take the stock path.
pub fn max_pool2x2(x: FloatTensor<Flex>) -> MaxPoolOutput<Flex> {
    let stock = |x| {
        let out = <Flex as ModuleOps<Flex>>::max_pool2d_with_indices(
            x,
            [2, 2],
            [2, 2],
            [0, 0],
            [1, 1],
            false,
        );
        MaxPoolOutput {
            output: out.output,
            argmax: out.indices,
        }
    };
    let Some((xc, shape)) = f32_data(&x) else {
        return stock(x);
    };
    let (h, w) = (shape[2], shape[3]);
    if h % 2 != 0 || w % 2 != 0 {
        return stock(x);
    }
    let (oh, ow) = (h / 2, w / 2);
    let planes = shape[0] * shape[1];
    let values = slice(&xc);
    let mut out = vec![0.0f32; planes * oh * ow];
    let mut argmax = vec![0u8; planes * oh * ow];
    out.par_chunks_mut(oh * ow)
        .zip(argmax.par_chunks_mut(oh * ow))
        .zip(values.par_chunks(h * w))
        .for_each(|((out, argmax), x)| {
            for i in 0..oh {
                let (top, bottom) = (&x[2 * i * w..][..w], &x[(2 * i + 1) * w..][..w]);
                for j in 0..ow {
                    let window = [top[2 * j], top[2 * j + 1], bottom[2 * j], bottom[2 * j + 1]];
                    let (mut best, mut at) = (window[0], 0u8);
                    for (k, &v) in window.iter().enumerate().skip(1) {
                        if v > best {
                            (best, at) = (v, k as u8);
                        }
                    }
                    out[i * ow + j] = best;
                    argmax[i * ow + j] = at;
                }
            }
        });
    let out_shape = [shape[0], shape[1], oh, ow];
    MaxPoolOutput {
        output: from_vec(out, &out_shape),
        argmax: FlexTensor::from_data(TensorData::new(argmax, out_shape.to_vec())),
    }
}

/// The gradient of [`max_pool2x2`]: each output gradient to its window's recorded maximum, zero elsewhere.
pub fn max_pool2x2_backward(
    x: FloatTensor<Flex>,
    output_grad: FloatTensor<Flex>,
    argmax: IntTensor<Flex>,
) -> FloatTensor<Flex> {
    let prepared = (f32_data(&output_grad), argmax.dtype() == DType::U8);
    let (Some((dy_c, dy_shape)), true) = prepared else {
        return <Flex as ModuleOps<Flex>>::max_pool2d_with_indices_backward(
            x,
            [2, 2],
            [2, 2],
            [0, 0],
            [1, 1],
            false,
            output_grad,
            argmax,
        )
        .x_grad;
    };
    let x_shape = x.shape().to_vec();
    let (w, oh, ow) = (x_shape[3], dy_shape[2], dy_shape[3]);
    let argmax = if argmax.is_contiguous() {
        argmax
    } else {
        argmax.to_contiguous()
    };
    let (dy, at) = (
        slice(&dy_c),
        argmax.as_slice::<u8>().expect("contiguous u8"),
    );
    let mut dx = vec![0.0f32; x_shape.iter().product()];
    dx.par_chunks_mut(x_shape[2] * w)
        .zip(dy.par_chunks(oh * ow).zip(at.par_chunks(oh * ow)))
        .for_each(|(dx, (dy, at))| {
            for i in 0..oh {
                for j in 0..ow {
                    let k = at[i * ow + j] as usize;
                    dx[(2 * i + k / 2) * w + 2 * j + k % 2] = dy[i * ow + j];
                }
            }
        });
    from_vec(dx, &x_shape)
}

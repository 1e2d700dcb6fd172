//! Resampling an orthoimage into DEM cells (both north-up, same CRS): the projection stage's kernel.
//!
//! [`ResampleKernel::Area`] is the exact box integral of the piecewise-constant ortho over each cell: what a 5 m
//! pixel of a camera would record, and what the pipeline uses (0.5–2 m orthos → 5 m cells). The cheaper point
//! kernels sample the cell centre only and alias fine texture; the report measures what they save and cost.

use crate::science::raster::Raster;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ResampleKernel {
    /// Area-weighted mean over every ortho pixel the cell overlaps; invalid if any of them is nodata.
    Area,
    /// Bilinear interpolation of pixel centres at the cell centre; invalid if any of the four taps is nodata.
    Bilinear,
    /// The ortho pixel containing the cell centre.
    Nearest,
}

impl ResampleKernel {
    pub const ALL: [ResampleKernel; 3] = [Self::Area, Self::Bilinear, Self::Nearest];

    pub fn name(self) -> &'static str {
        match self {
            Self::Area => "area",
            Self::Bilinear => "bilinear",
            Self::Nearest => "nearest",
        }
    }
}

/// Resample `ortho` into the `n × n` DEM cells whose top-left cell is (c0, r0) of `dem`'s grid. Returns values
/// (0 where invalid) and a validity mask (1 = valid). A cell reaching outside the ortho is invalid.
pub fn resample_cells(
    ortho: &Raster,
    dem: &crate::science::raster::GeoTransform,
    (c0, r0): (usize, usize),
    n: usize,
    kernel: ResampleKernel,
) -> (Vec<f32>, Vec<u8>) {
    match kernel {
        ResampleKernel::Area => area_average(ortho, dem, (c0, r0), n),
        ResampleKernel::Bilinear | ResampleKernel::Nearest => {
            let (mut image, mut valid) = (vec![0f32; n * n], vec![0u8; n * n]);
            let ot = &ortho.transform;
            for j in 0..n {
                for i in 0..n {
                    // Cell centre in ortho pixel-edge coordinates.
                    let (x, y) = dem.edge_in(ot, (c0 + i) as f64 + 0.5, (r0 + j) as f64 + 0.5);
                    let value = if kernel == ResampleKernel::Nearest {
                        nearest(ortho, x, y)
                    } else {
                        bilinear_strict(ortho, x - 0.5, y - 0.5)
                    };
                    if let Some(v) = value {
                        image[j * n + i] = v;
                        valid[j * n + i] = 1;
                    }
                }
            }
            (image, valid)
        }
    }
}

fn nearest(ortho: &Raster, x: f64, y: f64) -> Option<f32> {
    let (c, r) = (x.floor(), y.floor());
    if c < 0.0 || r < 0.0 || c >= ortho.width as f64 || r >= ortho.height as f64 {
        return None;
    }
    let v = ortho.get(c as usize, r as usize);
    v.is_finite().then_some(v)
}

/// Bilinear at pixel-centre coordinates, `None` outside the centres' hull or on a nodata tap (no clamping:
/// a clamped edge would invent values).
fn bilinear_strict(ortho: &Raster, col: f64, row: f64) -> Option<f32> {
    let (c0, r0) = (col.floor(), row.floor());
    if c0 < 0.0 || r0 < 0.0 || c0 + 1.0 >= ortho.width as f64 || r0 + 1.0 >= ortho.height as f64 {
        return None;
    }
    let (c, r) = (c0 as usize, r0 as usize);
    let (fc, fr) = (col - c0, row - r0);
    let taps = [
        ortho.get(c, r),
        ortho.get(c + 1, r),
        ortho.get(c, r + 1),
        ortho.get(c + 1, r + 1),
    ];
    if taps.iter().any(|v| !v.is_finite()) {
        return None;
    }
    let top = taps[0] as f64 * (1.0 - fc) + taps[1] as f64 * fc;
    let bottom = taps[2] as f64 * (1.0 - fc) + taps[3] as f64 * fc;
    Some((top * (1.0 - fr) + bottom * fr) as f32)
}

/// Exact area average. Both rasters are north-up in the same CRS, so each cell is an axis-aligned rectangle in
/// ortho pixel space and the weights separate into per-column and per-row overlaps.
fn area_average(
    ortho: &Raster,
    dem: &crate::science::raster::GeoTransform,
    (c0, r0): (usize, usize),
    n: usize,
) -> (Vec<f32>, Vec<u8>) {
    let ortho_t = &ortho.transform;
    // Overlaps of [a, b) (in ortho pixel-edge coordinates) with each ortho pixel [k, k+1).
    let overlaps = |a: f64, b: f64, len: usize| -> Option<(usize, Vec<f64>)> {
        let (first, last) = (a.floor(), b.ceil());
        if first < 0.0 || last > len as f64 {
            return None; // the cell reaches outside the ortho
        }
        let weights = (first as usize..last as usize)
            .map(|k| (b.min(k as f64 + 1.0) - a.max(k as f64)).max(0.0))
            .collect();
        Some((first as usize, weights))
    };
    let x_edge = |col: usize| dem.edge_in(ortho_t, col as f64, 0.0).0;
    let y_edge = |row: usize| dem.edge_in(ortho_t, 0.0, row as f64).1;
    let columns: Vec<_> = (0..n)
        .map(|i| overlaps(x_edge(c0 + i), x_edge(c0 + i + 1), ortho.width))
        .collect();
    let (mut image, mut valid) = (vec![0f32; n * n], vec![0u8; n * n]);
    for j in 0..n {
        let Some((row0, wy)) = overlaps(y_edge(r0 + j), y_edge(r0 + j + 1), ortho.height) else {
            continue;
        };
        for (i, column) in columns.iter().enumerate() {
            let Some((col0, wx)) = column else { continue };
            let (mut sum, mut weight) = (0.0f64, 0.0f64);
            let mut all_valid = true;
            for (dy, &w_y) in wy.iter().enumerate() {
                let line = &ortho.data[(row0 + dy) * ortho.width..(row0 + dy + 1) * ortho.width];
                for (dx, &w_x) in wx.iter().enumerate() {
                    let v = line[col0 + dx];
                    if w_x * w_y > 0.0 {
                        all_valid &= v.is_finite();
                        sum += w_x * w_y * v as f64;
                        weight += w_x * w_y;
                    }
                }
            }
            if all_valid && weight > 0.0 {
                image[j * n + i] = (sum / weight) as f32;
                valid[j * n + i] = 1;
            }
        }
    }
    (image, valid)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::science::crs::LunarCrs;
    use crate::science::raster::GeoTransform;

    /// A 2 m ortho holding `f` at pixel centres, and a 5 m grid whose origin is 3 m west / 1 m north of it.
    fn scene(f: impl Fn(f64, f64) -> f64) -> (Raster, GeoTransform) {
        let crs = LunarCrs::equirectangular(0.0, 0.0);
        let mut ortho = Raster::new(200, 200, GeoTransform::north_up(0.0, 0.0, 2.0), crs, 0.0);
        for r in 0..200 {
            for c in 0..200 {
                let (x, y) = ortho.transform.pixel_center(c as f64, r as f64);
                ortho.data[r * 200 + c] = f(x, y) as f32;
            }
        }
        (ortho, GeoTransform::north_up(-3.0, 1.0, 5.0))
    }

    #[test]
    fn kernels_on_a_linear_ramp_return_the_cell_centre_value() {
        // On a linear field every kernel is exact at the cell centre: area because the box weights' centroid is
        // the cell centre (cells aligned to whole 2 m pixels give a mean of the pixel-centre values whose centroid
        // differs by ≤ 0.5 px only at partial overlaps — checked against the exact integral below); bilinear and
        // nearest by construction (nearest only up to the ramp's change across half a pixel).
        let ramp = |x: f64, y: f64| 0.1 + 0.001 * x - 0.0005 * y;
        let (ortho, dem) = scene(ramp);
        for kernel in ResampleKernel::ALL {
            let (image, valid) = resample_cells(&ortho, &dem, (4, 5), 16, kernel);
            assert!(valid.iter().all(|&v| v == 1), "{kernel:?}");
            for j in 0..16 {
                for i in 0..16 {
                    let (x, y) = dem.pixel_center((4 + i) as f64, (5 + j) as f64);
                    let got = image[j * 16 + i] as f64;
                    let tolerance = match kernel {
                        ResampleKernel::Bilinear => 1e-6,
                        // Half a 2 m pixel along x and y: 0.001 + 0.0005 per metre.
                        ResampleKernel::Nearest => 1.0 * 0.001 + 1.0 * 0.0005 + 1e-6,
                        // The box reconstruction's centroid is ≤ 0.1 m off the cell centre: 1.5e-4.
                        ResampleKernel::Area => 1.6e-4,
                    };
                    assert!(
                        (got - ramp(x, y)).abs() <= tolerance,
                        "{kernel:?} at ({i}, {j}): {got} vs {}",
                        ramp(x, y)
                    );
                }
            }
        }
    }

    #[test]
    fn area_is_the_box_integral_and_point_kernels_alias_a_checkerboard() {
        // A 2 m checkerboard (pixel values 0 / 1): each 5 m cell's true mean is its covered-area share of 1s.
        let (ortho, dem) = scene(|x, y| ((x / 2.0).floor() + (y / 2.0).floor()).rem_euclid(2.0));
        let (area, _) = resample_cells(&ortho, &dem, (2, 2), 8, ResampleKernel::Area);
        let (nearest, _) = resample_cells(&ortho, &dem, (2, 2), 8, ResampleKernel::Nearest);
        for j in 0..8 {
            for i in 0..8 {
                // Supersample the cell 50 × 50 (exact to 1/2500 of the cell per sample row).
                let (x0, y0) = (-3.0 + (2 + i) as f64 * 5.0, 1.0 - (2 + j) as f64 * 5.0);
                let mean = (0..2500)
                    .map(|k| {
                        let (x, y) = (
                            x0 + 0.05 + 0.1 * (k % 50) as f64,
                            y0 - 0.05 - 0.1 * (k / 50) as f64,
                        );
                        ((x / 2.0).floor() + (y / 2.0).floor()).rem_euclid(2.0)
                    })
                    .sum::<f64>()
                    / 2500.0;
                assert!(
                    (area[j * 8 + i] as f64 - mean).abs() < 1e-6,
                    "area at ({i}, {j})"
                );
                assert!(nearest[j * 8 + i] == 0.0 || nearest[j * 8 + i] == 1.0);
            }
        }
        let rms = |v: &[f32]| {
            (v.iter()
                .zip(&area)
                .map(|(a, b)| (a - b).powi(2) as f64)
                .sum::<f64>()
                / v.len() as f64)
                .sqrt()
        };
        assert!(
            rms(&nearest) > 0.3,
            "nearest must alias a 2 m checkerboard: rms {}",
            rms(&nearest)
        );
    }

    #[test]
    fn nodata_and_outside_cells_are_invalid_for_every_kernel() {
        let (mut ortho, dem) = scene(|_, _| 0.5);
        // Cell (10, 10) covers x in [47, 52), y in [-54, -49): ortho columns 23..=25, rows 24..=26; its centre
        // (49.5, -51.5) lies in pixel (24, 25), a tap of all three kernels.
        ortho.data[25 * 200 + 24] = f32::NAN;
        for kernel in ResampleKernel::ALL {
            let (_, valid) = resample_cells(&ortho, &dem, (9, 9), 3, kernel);
            assert_eq!(valid[4], 0, "{kernel:?}: the cell over the NaN pixel");
            // The grid origin lies 3 m west of the ortho: cell column 0 reaches outside.
            let (_, valid) = resample_cells(&ortho, &dem, (0, 3), 2, kernel);
            assert_eq!(valid[0], 0, "{kernel:?}: a cell reaching outside the ortho");
        }
    }
}

//! PNG panels: ground truth | each method | |learned − ground truth|.

use std::path::Path;

use anyhow::{Context, Result};
use dataset::contract::schema::{Sample, CROP_PX};

use crate::baseline::truth_and_valid;

/// A PNG panel: GT | each method | |learned − GT|, every tile stretched with the GT's 2–98 % range, invalid red.
pub fn panel_png(
    sample: &Sample,
    renderings: &[(&'static str, Vec<f64>)],
    path: &Path,
) -> Result<()> {
    let (truth, valid) = truth_and_valid(sample);
    let mut values: Vec<f64> = truth
        .iter()
        .zip(&valid)
        .filter(|(_, &ok)| ok)
        .map(|(&t, _)| t)
        .collect();
    values.sort_by(f64::total_cmp);
    let (lo, hi) = match values.len() {
        0 => (0.0, 1.0),
        n => (values[n * 2 / 100], values[(n - 1) * 98 / 100]),
    };
    let span = (hi - lo).max(1e-12);
    let learned = &renderings[0].1;
    let error: Vec<f64> = learned
        .iter()
        .zip(&truth)
        .map(|(x, t)| (x - t).abs() + lo)
        .collect();
    let mut tiles: Vec<&[f64]> = vec![&truth];
    tiles.extend(renderings.iter().map(|(_, r)| r.as_slice()));
    tiles.push(&error);
    let (edge, gap) = (CROP_PX as u32, 4u32);
    let width = tiles.len() as u32 * (edge + gap) - gap;
    let mut img = image::RgbImage::from_pixel(width, edge, image::Rgb([255, 255, 255]));
    for (t, tile) in tiles.iter().enumerate() {
        for k in 0..CROP_PX * CROP_PX {
            let (x, y) = (
                t as u32 * (edge + gap) + (k % CROP_PX) as u32,
                (k / CROP_PX) as u32,
            );
            let px = if !valid[k] || !tile[k].is_finite() {
                image::Rgb([120, 0, 0])
            } else {
                let v = (((tile[k] - lo) / span).clamp(0.0, 1.0) * 255.0).round() as u8;
                image::Rgb([v, v, v])
            };
            img.put_pixel(x, y, px);
        }
    }
    img.save_with_format(path, image::ImageFormat::Png)
        .with_context(|| format!("writing {}", path.display()))
}

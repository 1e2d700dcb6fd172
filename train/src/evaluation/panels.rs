//! PNG panels: ground truth | each method | |learned − ground truth|, each column labelled, the grey scale stated.

use std::path::Path;

use anyhow::{Context, Result};
use dataset::contract::schema::{Sample, CROP_PX};
use image::{Rgb, RgbImage};

use crate::baseline::truth_and_valid;

/// Height of the strip of column names above the tiles.
pub const PANEL_HEADER_PX: u32 = 18;
/// Height of the strip below the tiles that states the grey scale.
pub const PANEL_FOOTER_PX: u32 = 18;
/// Gap between tiles.
pub const PANEL_GAP_PX: u32 = 4;

const INVALID: Rgb<u8> = Rgb([120, 0, 0]);

/// A PNG panel: GT | each method | |learned − GT|, every tile stretched with the GT's 2–98 % range (the error tile
/// from 0 over the same span, so its grey reads in the images' units), invalid pixels dark red. Column names above,
/// the grey scale below; without a system font ([`dataset::plot::system_font`]) the strips stay blank.
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
    let (learned_name, learned) = (renderings[0].0, &renderings[0].1);
    let error: Vec<f64> = learned
        .iter()
        .zip(&truth)
        .map(|(x, t)| (x - t).abs() + lo)
        .collect();
    let error_name = format!("|{learned_name} - GT|");
    let mut tiles: Vec<(&str, &[f64])> = vec![("GT", &truth)];
    tiles.extend(renderings.iter().map(|(name, r)| (*name, r.as_slice())));
    tiles.push((&error_name, &error));
    let edge = CROP_PX as u32;
    let width = tiles.len() as u32 * (edge + PANEL_GAP_PX) - PANEL_GAP_PX;
    let height = PANEL_HEADER_PX + edge + PANEL_FOOTER_PX;
    let mut img = RgbImage::from_pixel(width, height, Rgb([255, 255, 255]));
    for (t, (_, tile)) in tiles.iter().enumerate() {
        for k in 0..CROP_PX * CROP_PX {
            let (x, y) = (
                t as u32 * (edge + PANEL_GAP_PX) + (k % CROP_PX) as u32,
                PANEL_HEADER_PX + (k / CROP_PX) as u32,
            );
            let px = if !valid[k] || !tile[k].is_finite() {
                INVALID
            } else {
                let v = (((tile[k] - lo) / span).clamp(0.0, 1.0) * 255.0).round() as u8;
                Rgb([v, v, v])
            };
            img.put_pixel(x, y, px);
        }
    }
    if let Some(font) = dataset::plot::system_font() {
        for (t, (name, _)) in tiles.iter().enumerate() {
            let x = t as u32 * (edge + PANEL_GAP_PX);
            dataset::plot::draw_text_fitted(&mut img, &font, name, x as i32, 2, edge);
        }
        let scale = format!(
            "grey: I/F {lo:.4} (black) to {hi:.4} (white), 2-98 % of GT; error column: 0 to {span:.4}; dark red: invalid"
        );
        dataset::plot::draw_text_fitted(
            &mut img,
            &font,
            &scale,
            0,
            (PANEL_HEADER_PX + edge + 2) as i32,
            width,
        );
    }
    dataset::files::write_atomic(path, |tmp| {
        img.save_with_format(tmp, image::ImageFormat::Png)
            .with_context(|| format!("writing {}", path.display()))
    })
}

//! Scatter plots of time against error, log x and log or linear y, for `report` and `results-page` (PNG, drawn
//! with imageproc).
//!
//! Labels need a TrueType font. None ships with the project (licences, size), so the first of a few common system
//! fonts is used (`.ci/setup` installs DejaVu). Without one, the plot is still drawn — points, axes, decade grid —
//! and the caller is told, so a missing font costs the labels, never the figure.

use std::path::Path;

use ab_glyph::{FontVec, PxScale};
use anyhow::{Context, Result};
use image::{Rgb, RgbImage};
use imageproc::drawing::{
    draw_filled_circle_mut, draw_hollow_rect_mut, draw_line_segment_mut, draw_text_mut, text_size,
};
use imageproc::rect::Rect;

/// One labelled point; both coordinates must be > 0 (log axes).
#[derive(Debug, Clone)]
pub struct Point {
    pub label: String,
    pub x: f64,
    pub y: f64,
}

pub struct Scatter<'a> {
    pub title: &'a str,
    pub x_label: &'a str,
    pub y_label: &'a str,
    pub points: &'a [Point],
    /// How the y axis maps values: log decades for quantities spanning orders of magnitude (times, MSEs), linear
    /// for ratios that stay within one (an error against a baseline's).
    pub y_axis: Axis,
}

/// A plot axis' scale.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Axis {
    Log,
    Linear,
}

/// Fonts tried in order (Debian/Ubuntu paths).
const FONT_PATHS: [&str; 3] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
    "/usr/share/fonts/truetype/noto/NotoSans-Regular.ttf",
];

pub fn system_font() -> Option<FontVec> {
    FONT_PATHS
        .iter()
        .find_map(|p| std::fs::read(p).ok())
        .and_then(|bytes| FontVec::try_from_vec(bytes).ok())
}

const WIDTH: u32 = 900;
const HEIGHT: u32 = 600;
/// Plot area inside the margins (left, top, right, bottom).
const AREA: (f32, f32, f32, f32) = (90.0, 50.0, 870.0, 530.0);
const INK: Rgb<u8> = Rgb([30, 30, 30]);
const GRID: Rgb<u8> = Rgb([225, 225, 225]);
const POINT: Rgb<u8> = Rgb([31, 119, 180]);

/// Decade range [10^lo, 10^hi] covering the values with a little room.
fn decades(values: impl Iterator<Item = f64>) -> (i32, i32) {
    let (min, max) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
        (a.min(v), b.max(v))
    });
    let lo = min.log10().floor() as i32;
    let hi = (max.log10().ceil() as i32).max(lo + 1);
    (lo, hi)
}

/// Pixel position of a value on a log axis spanning `[lo, hi]` decades over pixels `[p0, p1]`.
fn to_px(v: f64, (lo, hi): (i32, i32), p0: f32, p1: f32) -> f32 {
    let t = (v.log10() - lo as f64) / (hi - lo) as f64;
    p0 + (p1 - p0) * t as f32
}

/// Ticks of a linear axis covering the values: a 1, 2 or 5 × 10^k step giving about five intervals, the range
/// widened to whole steps (and by one step where a value would sit on the frame). Returns (ticks, decimals).
fn linear_ticks(values: impl Iterator<Item = f64>) -> (Vec<f64>, usize) {
    let (min, max) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
        (a.min(v), b.max(v))
    });
    let span = if max > min {
        max - min
    } else {
        min.abs().max(1.0)
    };
    let raw = span / 5.0;
    let magnitude = 10f64.powf(raw.log10().floor());
    let step = [1.0, 2.0, 5.0, 10.0]
        .into_iter()
        .map(|m| m * magnitude)
        .find(|s| *s >= raw)
        .unwrap_or(10.0 * magnitude);
    // A value within rounding of a tick counts as on it (0.1 × 11 is not 1.1 in binary).
    let on_tick = |q: f64| (q - q.round()).abs() < 1e-9;
    let (q_lo, q_hi) = (min / step, max / step);
    let lo = if on_tick(q_lo) {
        q_lo.round() - 1.0
    } else {
        q_lo.floor()
    };
    let hi = if on_tick(q_hi) {
        q_hi.round() + 1.0
    } else {
        q_hi.ceil()
    };
    let ticks = (lo as i64..=hi as i64).map(|k| k as f64 * step).collect();
    let decimals = (-step.log10().floor()).max(0.0) as usize;
    (ticks, decimals)
}

/// Pixel position of a value on a linear axis from `lo` to `hi` over pixels `[p0, p1]`.
fn to_px_linear(v: f64, (lo, hi): (f64, f64), p0: f32, p1: f32) -> f32 {
    p0 + (p1 - p0) * ((v - lo) / (hi - lo)) as f32
}

/// Draw the scatter; returns the image and whether labels were drawn (a font was found).
pub fn draw_scatter(plot: &Scatter, font: Option<&FontVec>) -> (RgbImage, bool) {
    let mut img = RgbImage::from_pixel(WIDTH, HEIGHT, Rgb([255, 255, 255]));
    let (left, top, right, bottom) = AREA;
    let points: Vec<&Point> = plot
        .points
        .iter()
        .filter(|p| p.x > 0.0 && p.y > 0.0 && p.x.is_finite() && p.y.is_finite())
        .collect();
    if points.is_empty() {
        return (img, font.is_some());
    }
    let xd = decades(points.iter().map(|p| p.x));
    let yd = decades(points.iter().map(|p| p.y));
    let small = PxScale::from(15.0);
    // A decade tick label: `place` turns the text's size into its top-left corner.
    let tick_label = |img: &mut RgbImage, d: i32, place: &dyn Fn(u32, u32) -> (i32, i32)| {
        if let Some(f) = font {
            let text = format!("1e{d}");
            let (w, h) = text_size(small, f, &text);
            let (x, y) = place(w, h);
            draw_text_mut(img, INK, x, y, small, f, &text);
        }
    };
    for d in xd.0..=xd.1 {
        let x = to_px(10f64.powi(d), xd, left, right);
        draw_line_segment_mut(&mut img, (x, top), (x, bottom), GRID);
        tick_label(&mut img, d, &|w, _| {
            (x as i32 - w as i32 / 2, bottom as i32 + 6)
        });
    }
    // y grows upward: the top of the area is the axis' highest value.
    let y_ticks: Vec<(f64, String)> = match plot.y_axis {
        Axis::Log => (yd.0..=yd.1)
            .map(|d| (10f64.powi(d), format!("1e{d}")))
            .collect(),
        Axis::Linear => {
            let (ticks, decimals) = linear_ticks(points.iter().map(|p| p.y));
            ticks
                .into_iter()
                .map(|v| (v, format!("{v:.decimals$}")))
                .collect()
        }
    };
    let y_range = (y_ticks[0].0, y_ticks[y_ticks.len() - 1].0);
    let y_px = |v: f64| match plot.y_axis {
        Axis::Log => to_px(v, yd, bottom, top),
        Axis::Linear => to_px_linear(v, y_range, bottom, top),
    };
    for (value, text) in &y_ticks {
        let y = y_px(*value);
        draw_line_segment_mut(&mut img, (left, y), (right, y), GRID);
        if let Some(f) = font {
            let (w, h) = text_size(small, f, text);
            let (x, y) = (left as i32 - w as i32 - 6, y as i32 - h as i32 / 2);
            draw_text_mut(&mut img, INK, x, y, small, f, text);
        }
    }
    draw_hollow_rect_mut(
        &mut img,
        Rect::at(left as i32, top as i32).of_size((right - left) as u32, (bottom - top) as u32),
        INK,
    );
    for p in &points {
        let (x, y) = (to_px(p.x, xd, left, right), y_px(p.y));
        draw_filled_circle_mut(&mut img, (x.round() as i32, y.round() as i32), 5, POINT);
        if let Some(f) = font {
            draw_text_mut(
                &mut img,
                INK,
                x as i32 + 8,
                y as i32 - 18,
                small,
                f,
                &p.label,
            );
        }
    }
    if let Some(f) = font {
        let big = PxScale::from(20.0);
        draw_text_mut(&mut img, INK, left as i32, 4, big, f, plot.title);
        let (w, _) = text_size(small, f, plot.x_label);
        let x_mid = ((left + right) / 2.0) as i32 - w as i32 / 2;
        draw_text_mut(
            &mut img,
            INK,
            x_mid,
            bottom as i32 + 32,
            small,
            f,
            plot.x_label,
        );
        // No rotated text in imageproc: the y label goes above the axis.
        draw_text_mut(&mut img, INK, 8, top as i32 - 22, small, f, plot.y_label);
    }
    (img, font.is_some())
}

/// Render and write a scatter PNG atomically (temp name, then rename). Returns whether labels were drawn.
pub fn write_scatter(plot: &Scatter, font: Option<&FontVec>, path: &Path) -> Result<bool> {
    let (img, labelled) = draw_scatter(plot, font);
    crate::files::write_atomic(path, |tmp| {
        img.save_with_format(tmp, image::ImageFormat::Png)
            .with_context(|| format!("writing {}", path.display()))
    })?;
    Ok(labelled)
}

/// `text` in black at (x, y), in the largest of a few sizes that fits `width` pixels (the smallest when none does):
/// the column names and scale lines of image panels.
pub fn draw_text_fitted(
    img: &mut RgbImage,
    font: &FontVec,
    text: &str,
    x: i32,
    y: i32,
    width: u32,
) {
    let sizes = [14.0, 12.0, 10.0, 9.0];
    let scale = sizes
        .iter()
        .map(|&s| PxScale::from(s))
        .find(|&scale| text_size(scale, font, text).0 <= width)
        .unwrap_or(PxScale::from(sizes[sizes.len() - 1]));
    draw_text_mut(img, Rgb([0, 0, 0]), x, y, scale, font, text);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn is_blue(p: &Rgb<u8>) -> bool {
        *p == POINT
    }

    #[test]
    fn points_land_where_the_log_axes_put_them() {
        let points = vec![
            Point {
                label: "a".into(),
                x: 20.0,
                y: 2e-4,
            },
            Point {
                label: "b".into(),
                x: 300.0,
                y: 5e-3,
            },
            Point {
                label: "skipped: not positive".into(),
                x: 0.0,
                y: 1.0,
            },
        ];
        let plot = Scatter {
            title: "t",
            x_label: "x",
            y_label: "y",
            points: &points,
            y_axis: Axis::Log,
        };
        let (img, _) = draw_scatter(&plot, None);
        // Axes span x 1e1..1e3 and y 1e-4..1e-2 over the area 90..870 × 530..50 (y up).
        let at = |x: f64, y: f64| {
            let px = 90.0 + 780.0 * (x.log10() - 1.0) / 2.0;
            let py = 530.0 - 480.0 * (y.log10() + 4.0) / 2.0;
            (px.round() as u32, py.round() as u32)
        };
        for (x, y) in [(20.0, 2e-4), (300.0, 5e-3)] {
            let (px, py) = at(x, y);
            assert!(
                is_blue(img.get_pixel(px, py)),
                "no point at ({px}, {py}) for ({x}, {y})"
            );
        }
        // Exactly two discs: the point at x = 0 drew nothing.
        let blue = |img: &RgbImage| img.pixels().filter(|p| is_blue(p)).count();
        let one = Scatter {
            points: &points[..1],
            ..plot
        };
        let (single, _) = draw_scatter(&one, None);
        assert!(blue(&single) > 50);
        assert_eq!(blue(&img), 2 * blue(&single));
        let (px, py) = at(60.0, 1e-3);
        assert!(!is_blue(img.get_pixel(px, py)));
    }

    #[test]
    fn a_linear_y_axis_puts_points_at_their_value_between_whole_ticks() {
        let points = vec![
            Point {
                label: "a".into(),
                x: 10.0,
                y: 0.62,
            },
            Point {
                label: "b".into(),
                x: 100.0,
                y: 1.1,
            },
        ];
        let plot = Scatter {
            title: "t",
            x_label: "x",
            y_label: "y",
            points: &points,
            y_axis: Axis::Linear,
        };
        let (img, _) = draw_scatter(&plot, None);
        // Span 0.48 → raw step 0.096 → step 0.1; 0.62 lies above the tick 0.6, and 1.1 on a tick, which gets one
        // more step of room: the axis runs 0.6..1.2.
        let (ticks, decimals) = linear_ticks([0.62, 1.1].into_iter());
        assert_eq!(decimals, 1);
        assert!((ticks[0] - 0.6).abs() < 1e-12 && (ticks[ticks.len() - 1] - 1.2).abs() < 1e-12);
        for (x, y) in [(10.0_f64, 0.62_f64), (100.0, 1.1)] {
            let px = 90.0 + 780.0 * (f64::log10(x) - 1.0);
            let py = 530.0 - 480.0 * (y - 0.6) / 0.6;
            let (px, py) = (px.round() as u32, py.round() as u32);
            assert!(
                is_blue(img.get_pixel(px, py)),
                "no point at ({px}, {py}) for y {y}"
            );
        }
    }

    #[test]
    fn linear_ticks_take_a_one_two_five_step_and_cover_the_values() {
        let (ticks, decimals) = linear_ticks([3.0, 47.0].into_iter());
        assert_eq!(decimals, 0);
        assert_eq!(ticks, vec![0.0, 10.0, 20.0, 30.0, 40.0, 50.0]);
        // A value exactly on a step gets one more step of room, so no point sits on the frame.
        let (ticks, _) = linear_ticks([0.5, 1.0].into_iter());
        assert!(
            ticks[0] < 0.5 - 1e-9 && ticks[ticks.len() - 1] > 1.0 + 1e-9,
            "{ticks:?}"
        );
    }

    #[test]
    fn decades_cover_the_values() {
        assert_eq!(decades([3e-4, 2e-3].into_iter()), (-4, -2));
        assert_eq!(decades([5.0, 5.0].into_iter()), (0, 1));
    }
}

//! PNG previews of one sample for the viewer: a hillshaded DEM, a percentile-stretched image, the lit fraction,
//! and the context window with the crop's footprint marked.
//! Previews are for eyes only; the tensors themselves are served unaltered by `/v1/rows` and the shards.

use image::{ImageEncoder, Rgb, RgbImage};

use dataset::contract::schema::{ContextWindow, Sample, CONTEXT_PX, CROP_PX, DEM_PX};

/// Which preview.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Preview {
    Dem,
    Image,
    Lit,
    Context,
}

impl Preview {
    pub fn from_file_name(name: &str) -> Option<Self> {
        match name {
            "dem.png" => Some(Self::Dem),
            "image.png" => Some(Self::Image),
            "lit.png" => Some(Self::Lit),
            "context.png" => Some(Self::Context),
            _ => None,
        }
    }
}

/// Shaded relief of the crop interior: Lambertian shading under a light from the north-west at 45° elevation
/// (the cartographic convention), slopes by central differences over the 1-px apron at the crop's GSD.
fn hillshade(sample: &Sample) -> RgbImage {
    let h = |r: usize, c: usize| sample.dem_m[r * DEM_PX + c] as f64;
    let gsd = sample.gsd_m.max(f64::MIN_POSITIVE);
    let light = {
        let (az, el) = (315f64.to_radians(), 45f64.to_radians());
        // east, north, up
        [az.sin() * el.cos(), az.cos() * el.cos(), el.sin()]
    };
    RgbImage::from_fn(CROP_PX as u32, CROP_PX as u32, |x, y| {
        let (r, c) = (y as usize + 1, x as usize + 1);
        let dzdx = (h(r, c + 1) - h(r, c - 1)) / (2.0 * gsd);
        let dzdy = (h(r - 1, c) - h(r + 1, c)) / (2.0 * gsd); // rows run north to south
        let norm = (dzdx * dzdx + dzdy * dzdy + 1.0).sqrt();
        let shade = (-dzdx * light[0] - dzdy * light[1] + light[2]) / norm;
        let v = (shade.clamp(0.0, 1.0) * 255.0).round() as u8;
        Rgb([v, v, v])
    })
}

/// Every preview is this many pixels square: the crop's previews pixel for pixel, the context window's cells
/// magnified `PREVIEW_PX / CONTEXT_PX` times (nearest neighbour, so cells stay visible as cells).
const PREVIEW_PX: usize = CROP_PX;

/// Value at quantile `q` of `values` (sorted copy; NaN-free input).
fn quantile(values: &[f32], q: f64) -> f32 {
    let mut sorted = values.to_vec();
    sorted.sort_by(f32::total_cmp);
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

/// The grey level of a value under a linear stretch from the 2nd to the 98th percentile of `values` (NaN-free;
/// 0 to 1 when empty), clipped at both ends.
fn stretch_2_98(values: &[f32]) -> impl Fn(f32) -> u8 {
    let (lo, hi) = if values.is_empty() {
        (0.0, 1.0)
    } else {
        (quantile(values, 0.02), quantile(values, 0.98))
    };
    let span = (hi - lo).max(f32::EPSILON);
    move |v| (((v - lo) / span).clamp(0.0, 1.0) * 255.0).round() as u8
}

/// Image stretched from its 2nd to 98th percentile over valid pixels; invalid pixels in dark red.
fn stretched_image(sample: &Sample) -> RgbImage {
    let valid: Vec<f32> = sample
        .image
        .iter()
        .zip(&sample.valid)
        .filter(|(_, &v)| v != 0)
        .map(|(&i, _)| i)
        .collect();
    let grey = stretch_2_98(&valid);
    RgbImage::from_fn(CROP_PX as u32, CROP_PX as u32, |x, y| {
        let k = y as usize * CROP_PX + x as usize;
        if sample.valid[k] == 0 {
            return Rgb([90, 0, 0]);
        }
        let v = grey(sample.image[k]);
        Rgb([v, v, v])
    })
}

fn lit_fraction(sample: &Sample) -> RgbImage {
    RgbImage::from_fn(CROP_PX as u32, CROP_PX as u32, |x, y| {
        let v = sample.sun_lit[y as usize * CROP_PX + x as usize];
        let v = (v.clamp(0.0, 1.0) * 255.0).round() as u8;
        Rgb([v, v, (v as u16 * 3 / 4) as u8])
    })
}

/// The context window's heights stretched from their 2nd to 98th percentile (cells without DEM in dark red), with
/// the crop's footprint outlined in yellow at the centre, so the viewer shows where the crop sits in its terrain.
fn context_image(context: &ContextWindow, crop_gsd_m: f64) -> RgbImage {
    let scale = PREVIEW_PX / CONTEXT_PX;
    let finite: Vec<f32> = context
        .heights_m
        .iter()
        .copied()
        .filter(|h| h.is_finite())
        .collect();
    let grey = stretch_2_98(&finite);
    // The window is centred on the crop centre, which is the corner shared by the four middle cells.
    let centre = PREVIEW_PX as f64 / 2.0;
    let half_side = (CROP_PX as f64 * crop_gsd_m / context.gsd_m * scale as f64 / 2.0).max(1.0);
    let (near, far) = (
        (centre - half_side).round() as i64,
        (centre + half_side).round() as i64 - 1,
    );
    RgbImage::from_fn(PREVIEW_PX as u32, PREVIEW_PX as u32, |x, y| {
        let (x, y) = (x as i64, y as i64);
        let inside = |v: i64| (near..=far).contains(&v);
        if (inside(x) && (y == near || y == far)) || (inside(y) && (x == near || x == far)) {
            return Rgb([255, 220, 0]);
        }
        let h = context.heights_m[y as usize / scale * CONTEXT_PX + x as usize / scale];
        if !h.is_finite() {
            return Rgb([90, 0, 0]);
        }
        let v = grey(h);
        Rgb([v, v, v])
    })
}

/// Encode the preview as PNG bytes; `None` when the sample lacks what the preview shows (a schema 1.1 sample has no
/// context window).
pub fn preview_png(sample: &Sample, preview: Preview) -> Option<Vec<u8>> {
    let img = match preview {
        Preview::Dem => hillshade(sample),
        Preview::Image => stretched_image(sample),
        Preview::Lit => lit_fraction(sample),
        Preview::Context => context_image(sample.context.as_ref()?, sample.gsd_m),
    };
    let mut bytes = Vec::new();
    image::codecs::png::PngEncoder::new(&mut bytes)
        .write_image(
            img.as_raw(),
            img.width(),
            img.height(),
            image::ExtendedColorType::Rgb8,
        )
        .expect("encoding an in-memory RGB image cannot fail");
    Some(bytes)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample_with_dem(f: impl Fn(f64, f64) -> f64) -> Sample {
        let n = CROP_PX * CROP_PX;
        Sample {
            dem_m: (0..DEM_PX * DEM_PX)
                .map(|k| f((k % DEM_PX) as f64 * 5.0, -((k / DEM_PX) as f64) * 5.0) as f32)
                .collect(),
            image: (0..n).map(|k| k as f32 / n as f32).collect(),
            valid: (0..n).map(|k| u8::from(k >= CROP_PX)).collect(),
            sun_lit: vec![0.5; n],
            gsd_m: 5.0,
            ..dataset::testing::synthetic_sample(0)
        }
    }

    #[test]
    fn hillshade_of_a_plane_matches_lambert_with_the_north_west_light() {
        // Flat: cos(45°) everywhere. A slope facing the light (rising to the south-east) is brighter than flat.
        let flat = hillshade(&sample_with_dem(|_, _| 100.0));
        let expected = (45f64.to_radians().sin() * 255.0).round() as u8;
        assert!(flat.pixels().all(|p| p.0[0] == expected));
        let facing = hillshade(&sample_with_dem(|x, y| 0.5 * x - 0.5 * y));
        let away = hillshade(&sample_with_dem(|x, y| -0.5 * x + 0.5 * y));
        assert!(facing.get_pixel(64, 64).0[0] > expected && away.get_pixel(64, 64).0[0] < expected);
        // Exact value for slope 0.5 east-up, 0.5 north-down: n = (-0.5, 0.5, 1)/|.|; light (-0.5, 0.5, 0.707).
        let n = [-0.5, 0.5, 1.0];
        let norm = (0.25f64 + 0.25 + 1.0).sqrt();
        let l = [
            -(0.5f64.sqrt()) * 0.5f64.sqrt(),
            0.5f64.sqrt() * 0.5f64.sqrt(),
            0.5f64.sqrt(),
        ];
        let shade = (n[0] * l[0] + n[1] * l[1] + n[2] * l[2]) / norm;
        assert_eq!(facing.get_pixel(64, 64).0[0], (shade * 255.0).round() as u8);
    }

    #[test]
    fn stretch_marks_invalid_pixels_and_spans_the_valid_range() {
        let img = stretched_image(&sample_with_dem(|_, _| 0.0));
        assert_eq!(img.get_pixel(5, 0).0, [90, 0, 0]); // first row invalid
        assert_eq!(img.get_pixel(0, 2).0[0], 0); // below the 2nd percentile
        assert_eq!(img.get_pixel(127, 127).0[0], 255);
        let png = preview_png(&sample_with_dem(|_, _| 0.0), Preview::Lit).unwrap();
        assert_eq!(&png[1..4], b"PNG");
    }

    #[test]
    fn context_preview_magnifies_cells_marks_holes_and_outlines_the_crop() {
        // Heights rise west to east by column; the last row has no DEM.
        let heights_m = (0..CONTEXT_PX * CONTEXT_PX)
            .map(|k| {
                if k / CONTEXT_PX == CONTEXT_PX - 1 {
                    f32::NAN
                } else {
                    (k % CONTEXT_PX) as f32 * 10.0
                }
            })
            .collect();
        // 128 px × 5 m = 640 m crop in 160 m cells: 4 cells = 16 preview pixels, centred.
        let context = ContextWindow {
            gsd_m: 160.0,
            heights_m,
            highland: None,
        };
        let img = context_image(&context, 5.0);
        assert_eq!((img.width(), img.height()), (128, 128));
        let yellow = [255, 220, 0];
        for k in 56..=71 {
            for (x, y) in [(k, 56), (k, 71), (56, k), (71, k)] {
                assert_eq!(img.get_pixel(x, y).0, yellow, "outline at ({x}, {y})");
            }
        }
        assert_ne!(img.get_pixel(55, 60).0, yellow);
        assert_ne!(img.get_pixel(60, 60).0, yellow);
        assert_ne!(img.get_pixel(72, 60).0, yellow);
        // Cells are 4 × 4 blocks of one grey; grey rises eastwards; 2-98 % stretch clips the ends.
        assert_eq!(img.get_pixel(8, 3).0, img.get_pixel(11, 0).0);
        assert!(img.get_pixel(40, 10).0[0] > img.get_pixel(36, 10).0[0]);
        assert_eq!(img.get_pixel(0, 0).0, [0, 0, 0]);
        assert_eq!(img.get_pixel(127, 0).0, [255, 255, 255]);
        assert_eq!(img.get_pixel(30, 125).0, [90, 0, 0]);
        // A sample without a window has no context preview; with one, a PNG.
        let mut sample = sample_with_dem(|_, _| 0.0);
        sample.context = None;
        assert_eq!(preview_png(&sample, Preview::Context), None);
        sample.context = Some(context);
        assert_eq!(
            &preview_png(&sample, Preview::Context).unwrap()[1..4],
            b"PNG"
        );
    }
}

//! The novel-view renderer: [`raycast`] (ray marching over the DEM with cast shadows) and [`trajectory`] (camera
//! poses). This module is `g2r-train render`: read the DEM, the optional parameter maps and the trajectory; render
//! every view; write 16-bit PNGs on one I/F scale shared by all views and methods, plus `views.json`.

pub mod raycast;
pub mod trajectory;

use std::path::Path;
use std::time::Instant;

use crate::science::brdf::BrdfModel;
use crate::science::hapke::HapkeParams;
use anyhow::{bail, Context, Result};
use glam::DVec3;

use crate::views::raycast::{render_view, RayCaster, Reflectance, ViewOptions, ViewStats};
use crate::views::trajectory::read_trajectory;

pub struct RenderJob<'a> {
    pub dem: &'a Path,
    pub params: Option<&'a Path>,
    pub trajectory: &'a Path,
    pub sun_body: DVec3,
    pub out: &'a Path,
    pub options: ViewOptions,
}

#[derive(Debug, serde::Serialize)]
struct ViewRecord {
    view: usize,
    method: String,
    file: String,
    seconds: f64,
    stats: ViewStats,
}

/// Render every view of the job (see the module docs).
pub fn run(job: &RenderJob) -> Result<()> {
    if job.sun_body.length() == 0.0 || !job.sun_body.is_finite() {
        bail!("--sun X,Y,Z must be a finite non-zero body-fixed position (e.g. 1.4e11,-5.2e10,-1.2e10)");
    }
    if job.options.width == 0
        || job.options.height == 0
        || !(0.1..179.0).contains(&job.options.fov_deg)
    {
        bail!("--width/--height must be positive and --fov within (0.1, 179) degrees");
    }
    let poses = read_trajectory(job.trajectory)?;
    let mut dem = crate::science::raster::read_raster(job.dem)?;
    let filled = crate::views::raycast::fill_holes(&mut dem);
    if filled > 0 {
        tracing::warn!(
            filled,
            "{}: filled nodata pixels from their neighbours for rendering",
            job.dem.display()
        );
    }
    let field = RayCaster::new(&dem).with_context(|| format!("{}", job.dem.display()))?;
    let mut methods = vec![("hapke", Reflectance::Hapke(HapkeParams::lunar_typical()))];
    if let Some(path) = job.params {
        let mut bands = crate::science::raster::read_bands(path)?;
        if bands[0].width != dem.width
            || bands[0].height != dem.height
            || bands[0].transform != dem.transform
        {
            bail!(
                "{}: not on the DEM's grid; run `g2r-train infer --dem {}` to make parameter maps for this DEM",
                path.display(),
                job.dem.display()
            );
        }
        // The maps are NaN where the DEM had holes; the DEM was filled above, so fill the maps the same way.
        for band in &mut bands {
            crate::views::raycast::fill_holes(band);
        }
        let model =
            crate::science::raster::read_metadata_item(path, crate::science::brdf::BRDF_MODEL_KEY)?
                .with_context(|| {
                    format!(
                        "{}: no {} metadata item: pass a GeoTIFF written by `g2r-train infer`",
                        path.display(),
                        crate::science::brdf::BRDF_MODEL_KEY
                    )
                })?
                .parse::<BrdfModel>()
                .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
        let learned = Reflectance::from_param_bands(model, bands)
            .with_context(|| format!("{}", path.display()))?;
        methods.push(("learned", learned));
    }
    std::fs::create_dir_all(job.out)?;
    let progress =
        crate::progress::Progress::start("render", "views", (poses.len() * methods.len()) as u64);
    let mut images = Vec::new();
    let mut records = Vec::new();
    for (view, pose) in poses.iter().enumerate() {
        for (name, reflectance) in &methods {
            let t0 = Instant::now();
            let (image, stats) = render_view(
                &field,
                reflectance,
                pose,
                job.sun_body,
                &job.options,
                view as u64,
            );
            records.push(ViewRecord {
                view,
                method: name.to_string(),
                file: format!("view_{view:04}_{name}.png"),
                seconds: t0.elapsed().as_secs_f64(),
                stats,
            });
            images.push(image);
            progress.inc(1);
        }
    }
    progress.finish();
    // One display scale for every image: the 99.5th percentile of all lit pixels, so views compare directly.
    let mut lit: Vec<f64> = images
        .iter()
        .flatten()
        .copied()
        .filter(|v| *v > 0.0)
        .collect();
    lit.sort_by(f64::total_cmp);
    let scale = lit
        .get((lit.len().saturating_sub(1)) * 995 / 1000)
        .copied()
        .unwrap_or(1.0)
        .max(1e-12);
    for (image, record) in images.iter().zip(&records) {
        let png = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(
            job.options.width as u32,
            job.options.height as u32,
            |x, y| {
                let v = image[y as usize * job.options.width + x as usize] / scale;
                image::Luma([(v.clamp(0.0, 1.0) * 65535.0).round() as u16])
            },
        );
        let path = job.out.join(&record.file);
        crate::files::write_atomic(&path, |tmp| {
            png.save_with_format(tmp, image::ImageFormat::Png)
                .with_context(|| format!("writing {}", path.display()))
        })?;
    }
    let sheet = contact_sheet(&images, &records, methods.len(), &job.options, scale);
    let path = job.out.join(CONTACT_SHEET);
    crate::files::write_atomic(&path, |tmp| {
        sheet
            .save_with_format(tmp, image::ImageFormat::Png)
            .with_context(|| format!("writing {}", path.display()))
    })?;
    crate::files::write_json_atomic(
        &job.out.join("views.json"),
        &serde_json::json!({
            "i_over_f_scale": scale,
            "encoding": "I/F = png_value / 65535 * i_over_f_scale",
            "width": job.options.width, "height": job.options.height, "fov_deg": job.options.fov_deg,
            "rays_per_pixel": job.options.rays_per_pixel, "shadows": job.options.shadows,
            "psf_sigma_px": job.options.psf_sigma_px, "seed": job.options.seed,
            "views": records,
        }),
    )?;
    crate::outln!(
        "{}: {} views × {} methods, I/F scale {scale:.4} (views.json; {CONTACT_SHEET} to look at)",
        job.out.display(),
        poses.len(),
        methods.len()
    );
    Ok(())
}

/// The views at a glance: one row per view, one column per method, each labelled, 8-bit on the views' shared
/// scale (the 16-bit PNGs beside it are the data; this picture is for eyes).
pub const CONTACT_SHEET: &str = "views.png";

fn contact_sheet(
    images: &[Vec<f64>],
    records: &[ViewRecord],
    methods: usize,
    options: &raycast::ViewOptions,
    scale: f64,
) -> image::RgbImage {
    const LABEL_PX: u32 = 18;
    const GAP_PX: u32 = 4;
    let (w, h) = (options.width as u32, options.height as u32);
    let rows = images.len().div_ceil(methods.max(1)) as u32;
    let (cell_w, cell_h) = (w + GAP_PX, LABEL_PX + h + GAP_PX);
    let width = methods as u32 * cell_w - GAP_PX;
    let height = rows * cell_h + LABEL_PX;
    let mut sheet = image::RgbImage::from_pixel(width, height, image::Rgb([255, 255, 255]));
    for (k, image) in images.iter().enumerate() {
        let (x0, y0) = ((k % methods) as u32 * cell_w, (k / methods) as u32 * cell_h);
        for (i, v) in image.iter().enumerate() {
            let g = ((v / scale).clamp(0.0, 1.0) * 255.0).round() as u8;
            let (x, y) = (i as u32 % w, i as u32 / w);
            sheet.put_pixel(x0 + x, y0 + LABEL_PX + y, image::Rgb([g, g, g]));
        }
    }
    if let Some(font) = crate::plot::system_font() {
        for (k, record) in records.iter().enumerate() {
            let (x0, y0) = ((k % methods) as u32 * cell_w, (k / methods) as u32 * cell_h);
            let label = format!("view {} · {}", record.view, record.method);
            crate::plot::draw_text_fitted(&mut sheet, &font, &label, x0 as i32, y0 as i32 + 2, w);
        }
        let caption = format!("grey: I/F 0 (black) to {scale:.4} (white), every view on one scale");
        crate::plot::draw_text_fitted(
            &mut sheet,
            &font,
            &caption,
            0,
            (rows * cell_h) as i32 + 2,
            width,
        );
    }
    sheet
}

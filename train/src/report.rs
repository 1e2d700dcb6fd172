//! `g2r-train report`: time against error, all measured in one run on this machine ("model only what a scene
//! needs": what each shortcut saves and what it costs).
//!
//! Each measured section is also drawn as a log–log PNG (see [`dataset::plot`]).
//!
//! - **BRDF model**: each of M1–M6, L2–L4, H1 and H3 with one least-squares coefficient set, uniform Hapke × one scale and
//!   Lunar-Lambert with one albedo, all fitted on train crops, rendered on the evaluation crops: pixel MSE against
//!   the per-pixel evaluation time of the reflectance model (geometry is shared and timed once).
//! - **Inference overlap** (with `--run` and `--dem`): wall time and seam score of `infer` at several overlaps.
//! - **Renderer** (with `--dem`): rays per pixel and shadows on/off against a 16-ray reference view.
//! - **Projection resampling kernel** (with `--ortho` and `--dem`): area average (the pipeline's) against bilinear
//!   and nearest point sampling of the cell centre, on crops cut from a real ortho: time per crop against the
//!   RMS difference from the exact area average. The kernels live in `dataset::science::resample`, shared with the stage.

use std::path::Path;
use std::time::Instant;

use anyhow::Result;
use dataset::contract::schema::{Sample, Split};
use dataset::science::brdf::BrdfModel;
use dataset::science::geometry::PixelGeometry;
use dataset::science::hapke::HapkeParams;
use dataset::science::raster::Raster;

use crate::baseline::hapke_from_geometry;
use crate::data::{for_each_sample_group, SampleSource};
use crate::inference::{infer_params, render_maps, seam_score, InferOptions};
use crate::kernels::TrainOps;
use crate::model::UNet;
use crate::run_dir::{load_trained, Checkpoint};
use crate::uniform_fit::{calibrate, lunar_lambert_from_geometry, model_uniform_from_geometry};
use dataset::plot::{write_scatter, Axis, Point, Scatter};

#[derive(Debug, Clone, serde::Serialize)]
pub struct ModelRow {
    pub name: String,
    pub parameters_per_pixel: usize,
    pub pixel_mse: f64,
    /// Reflectance evaluation only, nanoseconds per pixel (geometry excluded: shared by all rows).
    pub ns_per_pixel: f64,
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct OverlapRow {
    pub overlap_px: usize,
    pub crops: usize,
    pub seconds: f64,
    pub seam_score: f64,
    /// Crops whose level the run's crater level set (as `infer` sets them); `None` when it was not applied.
    pub crater_level_crops: Option<usize>,
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct RenderRow {
    pub rays_per_pixel: usize,
    pub shadows: bool,
    pub seconds: f64,
    /// RMS difference from the reference (16 rays/pixel, shadows on), I/F.
    pub rms_vs_reference: f64,
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct ResampleRow {
    pub kernel: String,
    pub crops: usize,
    pub ms_per_crop: f64,
    /// RMS difference from the exact area average over pixels valid for both, reflectance units.
    pub rms_vs_area: f64,
    pub max_abs_vs_area: f64,
    /// Pixels this kernel calls valid, over pixels the area average calls valid.
    pub valid_ratio: f64,
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct Report {
    pub split: Split,
    pub images: usize,
    pub pixels: usize,
    pub calibration_samples: usize,
    /// Shared per-pixel geometry (normals, cosines, half/difference angles), nanoseconds per pixel.
    pub geometry_ns_per_pixel: f64,
    pub brdf_models: Vec<ModelRow>,
    pub inference_overlap: Vec<OverlapRow>,
    /// The overlap run keeps a crater level that was left out (no `--crater-catalogue`, or none of its craters on
    /// the DEM): its rows time the network's maps alone, not what `infer` gives with the catalogue.
    pub inference_crater_level_left_out: bool,
    pub renderer: Vec<RenderRow>,
    pub resampling: Vec<ResampleRow>,
}

/// Crop + its precomputed geometry → I/F per pixel.
type RenderFn = Box<dyn Fn(&Sample, &[PixelGeometry]) -> Vec<f64>>;

/// A reflectance model as the report times it: one f64 per pixel from geometry and lit fraction.
struct Candidate {
    name: String,
    parameters: usize,
    render: RenderFn,
}

fn candidates(source: &dyn SampleSource, calibration_samples: usize) -> Result<Vec<Candidate>> {
    let (mut out, mut scales) = (Vec::new(), (0.0, 0.0));
    for model in BrdfModel::ALL {
        let fit = calibrate(source, calibration_samples, model)?;
        scales = (fit.hapke_scale, fit.lunar_lambert_albedo);
        let coefficients = fit.model_uniform.clone();
        out.push(Candidate {
            name: format!("{} uniform", model.name()),
            parameters: model.param_count(),
            render: Box::new(move |s, geometry| {
                model_uniform_from_geometry(geometry, &s.sun_lit, model, &coefficients)
            }),
        });
    }
    let params = HapkeParams::lunar_typical();
    let (scale, albedo) = scales;
    out.push(Candidate {
        name: "Hapke (uniform, scaled)".into(),
        parameters: 6,
        render: Box::new(move |s, geometry| {
            let unscaled = hapke_from_geometry(geometry, &s.sun_lit, &params);
            unscaled.iter().map(|v| v * scale).collect()
        }),
    });
    out.push(Candidate {
        name: "Lunar-Lambert".into(),
        parameters: 1,
        render: Box::new(move |s, geometry| {
            lunar_lambert_from_geometry(geometry, &s.sun_lit, albedo)
        }),
    });
    Ok(out)
}

/// BRDF-model rows over (up to `max_samples`) crops of `split`.
pub fn brdf_model_rows(
    source: &dyn SampleSource,
    split: Split,
    max_samples: Option<usize>,
    calibration_samples: usize,
) -> Result<(Vec<ModelRow>, usize, usize, f64)> {
    let candidates = candidates(source, calibration_samples)?;
    let (mut sse, mut seconds) = (vec![0.0; candidates.len()], vec![0.0; candidates.len()]);
    let (mut pixels, mut valid_pixels, mut images, mut geometry_s) = (0usize, 0usize, 0usize, 0.0);
    for_each_sample_group(source, split, max_samples, "report", |samples| {
        for s in samples {
            let t0 = Instant::now();
            let geometry = s.pixel_geometry();
            geometry_s += t0.elapsed().as_secs_f64();
            images += 1;
            pixels += geometry.len();
            for (k, candidate) in candidates.iter().enumerate() {
                let t0 = Instant::now();
                let rendered = (candidate.render)(s, &geometry);
                seconds[k] += t0.elapsed().as_secs_f64();
                for ((r, &t), &v) in rendered.iter().zip(&s.image).zip(&s.valid) {
                    if v != 0 {
                        sse[k] += (r - t as f64).powi(2);
                    }
                }
            }
            valid_pixels += s.valid.iter().filter(|&&v| v != 0).count();
        }
    })?;
    let rows = candidates
        .iter()
        .enumerate()
        .map(|(k, c)| ModelRow {
            name: c.name.clone(),
            parameters_per_pixel: c.parameters,
            pixel_mse: sse[k] / valid_pixels.max(1) as f64,
            ns_per_pixel: seconds[k] * 1e9 / pixels.max(1) as f64,
        })
        .collect();
    Ok((
        rows,
        images,
        pixels,
        geometry_s * 1e9 / pixels.max(1) as f64,
    ))
}

/// Inference-overlap rows: the same network over the same DEM with the same `options` (input, crater frames and
/// level), at each overlap.
pub fn overlap_rows<B: TrainOps>(
    net: &UNet<B>,
    model: BrdfModel,
    dem: &Raster,
    options: &InferOptions,
    overlaps: &[usize],
    device: &B::Device,
) -> Result<Vec<OverlapRow>> {
    overlaps
        .iter()
        .map(|&overlap| {
            let options = InferOptions {
                overlap,
                ..options.clone()
            };
            let t0 = Instant::now();
            let maps = infer_params(net, model, dem, &options, device, |_, _| {})?;
            let seconds = t0.elapsed().as_secs_f64();
            // A sun 50° from zenith in the south-east: every crop has lit slopes of both orientations.
            let sun = [0.55, -0.45, 0.70];
            let image = render_maps(&maps, dem, sun);
            Ok(OverlapRow {
                overlap_px: overlap,
                crops: maps.crops,
                seconds,
                seam_score: seam_score(&image, maps.width, maps.height, overlap),
                crater_level_crops: maps.crater_level_crops,
            })
        })
        .collect()
}

/// Renderer rows: a nadir 128 × 128 view of the DEM centre (45° FOV covering half the DEM's width) under a sun
/// 50° from zenith in the east, at several rays/pixel with and without shadows, against a 16-ray reference.
pub fn renderer_rows(dem: &Raster) -> Result<Vec<RenderRow>> {
    use dataset::views::raycast::{render_view, RayCaster, Reflectance, ViewOptions};
    let mut dem = dem.clone();
    dataset::views::raycast::fill_holes(&mut dem);
    let field = RayCaster::new(&dem)?;
    let f = &field.frame;
    let half_width_m = dem.width as f64 * dem.transform.gsd_m() / 4.0;
    let altitude = f.origin_height_m + half_width_m / 22.5f64.to_radians().tan();
    let pose = dataset::views::trajectory::pose_from_lonlat(
        f.origin_lon_deg,
        f.origin_lat_deg,
        altitude,
        0.0,
        0.0,
        0.0,
    );
    let sun_enu = glam::DVec3::new(50f64.to_radians().sin(), 0.0, 50f64.to_radians().cos());
    let sun_body = f.enu_to_body_point(sun_enu * 1.5e11);
    let reflectance = Reflectance::Hapke(HapkeParams::lunar_typical());
    let view = |rays: usize, shadows: bool| {
        let options = ViewOptions {
            width: 128,
            height: 128,
            fov_deg: 45.0,
            rays_per_pixel: rays,
            shadows,
            psf_sigma_px: 0.0,
            seed: 7,
        };
        let t0 = Instant::now();
        let (image, _) = render_view(&field, &reflectance, &pose, sun_body, &options, rays as u64);
        (image, t0.elapsed().as_secs_f64())
    };
    let (reference, _) = view(16, true);
    Ok([(1, true), (2, true), (4, true), (8, true), (4, false)]
        .into_iter()
        .map(|(rays, shadows)| {
            let (image, seconds) = view(rays, shadows);
            let sq: f64 = image
                .iter()
                .zip(&reference)
                .map(|(a, b)| (a - b).powi(2))
                .sum();
            RenderRow {
                rays_per_pixel: rays,
                shadows,
                seconds,
                rms_vs_reference: (sq / image.len() as f64).sqrt(),
            }
        })
        .collect())
}

/// Resampling-kernel rows: up to `max_crops` 128 × 128 crops on a regular grid of DEM cells inside `ortho`
/// (only crops the area average finds fully valid), each kernel timed over all of them.
pub fn resampling_rows(
    ortho: &Raster,
    dem: &dataset::science::raster::GeoTransform,
    max_crops: usize,
) -> Vec<ResampleRow> {
    use dataset::contract::schema::CROP_PX;
    use dataset::science::resample::{resample_cells, ResampleKernel};
    let ot = &ortho.transform;
    // The ortho's extent in DEM cell coordinates (corner convention).
    let (a, b) = (
        ot.edge_in(dem, 0.0, 0.0),
        ot.edge_in(dem, ortho.width as f64, ortho.height as f64),
    );
    let (c_lo, c_hi) = (
        a.0.min(b.0).ceil().max(0.0) as usize,
        a.0.max(b.0).floor() as usize,
    );
    let (r_lo, r_hi) = (
        a.1.min(b.1).ceil().max(0.0) as usize,
        a.1.max(b.1).floor() as usize,
    );
    let mut corners = Vec::new();
    let mut r = r_lo;
    while r + CROP_PX <= r_hi && corners.len() < max_crops {
        let mut c = c_lo;
        while c + CROP_PX <= c_hi && corners.len() < max_crops {
            let (_, valid) = resample_cells(ortho, dem, (c, r), CROP_PX, ResampleKernel::Area);
            if valid.iter().all(|&v| v == 1) {
                corners.push((c, r));
            }
            c += CROP_PX;
        }
        r += CROP_PX;
    }
    // Each kernel timed over all crops; the area kernel's own timed output is the reference.
    let timed: Vec<_> = ResampleKernel::ALL
        .into_iter()
        .map(|kernel| {
            let t0 = Instant::now();
            let crops: Vec<_> = corners
                .iter()
                .map(|&corner| resample_cells(ortho, dem, corner, CROP_PX, kernel))
                .collect();
            (kernel, crops, t0.elapsed().as_secs_f64())
        })
        .collect();
    let exact = &timed
        .iter()
        .find(|(kernel, _, _)| *kernel == ResampleKernel::Area)
        .expect("ALL holds the area kernel")
        .1;
    timed
        .iter()
        .map(|(kernel, crops, seconds)| {
            let (mut sq, mut max_abs, mut valid) = (0f64, 0f64, 0usize);
            for ((image, mask), (reference, _)) in crops.iter().zip(exact) {
                for k in 0..image.len() {
                    if mask[k] == 1 {
                        valid += 1;
                        let d = (image[k] - reference[k]) as f64;
                        sq += d * d;
                        max_abs = max_abs.max(d.abs());
                    }
                }
            }
            let total = corners.len() * CROP_PX * CROP_PX;
            ResampleRow {
                kernel: kernel.name().into(),
                crops: corners.len(),
                ms_per_crop: 1e3 * *seconds / corners.len().max(1) as f64,
                rms_vs_area: if valid > 0 {
                    (sq / valid as f64).sqrt()
                } else {
                    0.0
                },
                max_abs_vs_area: max_abs,
                valid_ratio: valid as f64 / total.max(1) as f64,
            }
        })
        .collect()
}

pub fn markdown(report: &Report) -> String {
    let mut text = format!(
        "# Speed against error (measured in one run)\n\n## BRDF model\n\n{} {} crops ({} pixels); models fitted on {} \
         train crops. Shared geometry: {:.0} ns/pixel.\n\n| model | parameters | pixel MSE | ns/pixel (BRDF only) |\n|---|---|---|---|\n",
        report.images, report.split, report.pixels, report.calibration_samples, report.geometry_ns_per_pixel
    );
    for r in &report.brdf_models {
        text.push_str(&format!(
            "| {} | {} | {:.4e} | {:.1} |\n",
            r.name, r.parameters_per_pixel, r.pixel_mse, r.ns_per_pixel
        ));
    }
    text.push_str("\n## Inference overlap\n\n");
    if report.inference_overlap.is_empty() {
        text.push_str("Not measured: pass --run RUN_DIR and --dem DEM.tif.\n");
    } else {
        text.push_str("| overlap px | crops | seconds | seam score (≤ 1.05 = invisible) | crops the crater level set |\n|---|---|---|---|---|\n");
        for r in &report.inference_overlap {
            let level = r.crater_level_crops.map_or("—".into(), |n| n.to_string());
            text.push_str(&format!(
                "| {} | {} | {:.2} | {:.3} | {level} |\n",
                r.overlap_px, r.crops, r.seconds, r.seam_score
            ));
        }
        if report.inference_crater_level_left_out {
            text.push_str("\nThe run's crater level was left out (no --crater-catalogue, or none of its craters on this DEM): these are its network's maps alone.\n");
        }
    }
    text.push_str("\n## Renderer: rays per pixel and shadows\n\n");
    if report.renderer.is_empty() {
        text.push_str("Not measured: pass --dem DEM.tif.\n");
    } else {
        text.push_str(
            "Nadir 128 × 128 view, 45° FOV, uniform Hapke, sun 50° from zenith; error = RMS I/F difference from a \
             16-ray render with shadows.\n\n| rays/pixel | shadows | seconds | RMS vs reference |\n|---|---|---|---|\n",
        );
        for r in &report.renderer {
            text.push_str(&format!(
                "| {} | {} | {:.2} | {:.3e} |\n",
                r.rays_per_pixel,
                if r.shadows { "on" } else { "off" },
                r.seconds,
                r.rms_vs_reference
            ));
        }
    }
    text.push_str("\n## Projection resampling kernel\n\n");
    if report.resampling.is_empty() {
        text.push_str("Not measured: pass --ortho ORTHO.tif and --dem DEM.tif.\n");
    } else {
        text.push_str(&format!(
            "{} fully valid 128 × 128 crops of 5 m cells cut from the ortho; error = difference from the exact area \
             average (what a 5 m pixel records; the pipeline's kernel), so area's own row is 0 by definition.\n\n\
             | kernel | ms/crop | RMS vs area | max abs vs area | valid pixels |\n|---|---|---|---|---|\n",
            report.resampling[0].crops
        ));
        for r in &report.resampling {
            text.push_str(&format!(
                "| {} | {:.3} | {:.3e} | {:.3e} | {:.4} |\n",
                r.kernel, r.ms_per_crop, r.rms_vs_area, r.max_abs_vs_area, r.valid_ratio
            ));
        }
    }
    text
}

/// The time-against-error plots of a report: (file name, plot), only for the sections that were measured.
fn plots(report: &Report) -> Vec<(&'static str, &'static str, &'static str, Vec<Point>)> {
    let mut out = vec![(
        "brdf_models.png",
        "BRDF models: pixel MSE against evaluation time",
        "ns per pixel (BRDF only)",
        report
            .brdf_models
            .iter()
            .map(|r| Point {
                label: r.name.clone(),
                x: r.ns_per_pixel,
                y: r.pixel_mse,
            })
            .collect(),
    )];
    if !report.inference_overlap.is_empty() {
        out.push((
            "inference_overlap.png",
            "Inference overlap: seam score against wall time",
            "seconds",
            report
                .inference_overlap
                .iter()
                .map(|r| Point {
                    label: format!("overlap {} px", r.overlap_px),
                    x: r.seconds,
                    y: r.seam_score,
                })
                .collect(),
        ));
    }
    if !report.renderer.is_empty() {
        out.push((
            "renderer.png",
            "Renderer: RMS I/F vs a 16-ray reference against wall time",
            "seconds",
            report
                .renderer
                .iter()
                .map(|r| Point {
                    label: format!(
                        "{} ray{}, shadows {}",
                        r.rays_per_pixel,
                        if r.rays_per_pixel == 1 { "" } else { "s" },
                        if r.shadows { "on" } else { "off" }
                    ),
                    x: r.seconds,
                    y: r.rms_vs_reference,
                })
                .collect(),
        ));
    }
    if !report.resampling.is_empty() {
        out.push((
            "resampling.png",
            "Resampling kernel: RMS vs exact area average (area = 0, not drawn)",
            "ms per crop",
            report
                .resampling
                .iter()
                .map(|r| Point {
                    label: r.kernel.clone(),
                    x: r.ms_per_crop,
                    y: r.rms_vs_area,
                })
                .collect(),
        ));
    }
    out
}

/// `g2r-train report` as data: which sections to measure, on what.
pub struct ReportJob<'a> {
    pub source: &'a dyn SampleSource,
    pub split: Split,
    pub max_samples: Option<usize>,
    pub calibration_samples: usize,
    /// With `dem`: the run whose inference overlap is timed against its seam score.
    pub run: Option<(&'a Path, Checkpoint)>,
    /// Enables the renderer section, and with `run` or `ortho` theirs.
    pub dem: Option<&'a Path>,
    pub overlaps: &'a [usize],
    /// With `run`: the crater catalogue (and the least diameter that frames a crop, by default the run's) `infer`
    /// would be given, so a run with a crater input or a crater level is timed as `infer` runs it.
    pub crater_catalogue: Option<(&'a Path, Option<f64>)>,
    /// With `dem`: an ortho on the DEM's grid whose resampling kernels are compared.
    pub ortho: Option<&'a Path>,
    pub resampling_crops: usize,
}

/// Measure every section the job enables (see [`ReportJob`]).
pub fn run_job<B: TrainOps>(job: &ReportJob, device: &B::Device) -> Result<Report> {
    let (brdf_models, images, pixels, geometry_ns_per_pixel) = brdf_model_rows(
        job.source,
        job.split,
        job.max_samples,
        job.calibration_samples,
    )?;
    let raster = job
        .dem
        .map(dataset::science::raster::read_raster)
        .transpose()?;
    let renderer = raster
        .as_ref()
        .map(renderer_rows)
        .transpose()?
        .unwrap_or_default();
    let (inference_overlap, inference_crater_level_left_out) = match (job.run, raster.as_ref()) {
        (Some((run, checkpoint)), Some(raster)) => {
            let trained = load_trained::<B>(run, checkpoint, device)?;
            let crater_frames = job
                .crater_catalogue
                .map(|(catalogue, min_diameter_m)| {
                    crate::inference::crater_frames_for_runs(
                        &[run],
                        raster,
                        catalogue,
                        min_diameter_m,
                    )
                    .map(std::sync::Arc::new)
                })
                .transpose()?;
            let options = InferOptions {
                overlap: 0,
                batch_size: 8,
                input: trained.input,
                crater_frames,
                unit_map: None,
                crater_level: trained.crater_level.clone(),
                input_range: trained.input_range.clone(),
                clamp_crater_relief: false,
            };
            let rows = overlap_rows::<B>(
                &trained.net,
                trained.config.model,
                raster,
                &options,
                job.overlaps,
                device,
            )?;
            // `infer_params` says whether it applied the level (`None`: no frames with a crater on this DEM).
            let left_out = trained.crater_level.is_some()
                && rows.first().is_some_and(|r| r.crater_level_crops.is_none());
            if left_out {
                tracing::warn!("the run keeps a crater level, left out of the overlap rows (no --crater-catalogue, or none of its craters on this DEM): they time the network alone");
            }
            (rows, left_out)
        }
        _ => (Vec::new(), false),
    };
    let resampling = match (job.ortho, raster.as_ref()) {
        (Some(ortho), Some(raster)) => {
            let image = dataset::science::raster::read_raster(ortho)?;
            let corners = image.transform.corners(image.width, image.height);
            anyhow::ensure!(
                raster.crs.same_map(&image.crs, &corners)?,
                "{}: its CRS differs from the DEM's; pass an ortho on the DEM's map grid (as the pipeline requires)",
                ortho.display()
            );
            resampling_rows(&image, &raster.transform, job.resampling_crops)
        }
        _ => Vec::new(),
    };
    Ok(Report {
        split: job.split,
        images,
        pixels,
        calibration_samples: job.calibration_samples,
        geometry_ns_per_pixel,
        brdf_models,
        inference_overlap,
        inference_crater_level_left_out,
        renderer,
        resampling,
    })
}

/// Write `report.json`, `report.md`, one PNG per measured section and the run's `provenance.json` into `out`.
pub fn write(report: &Report, out: &Path) -> Result<()> {
    std::fs::create_dir_all(out)?;
    dataset::provenance::Provenance::capture().write(&out.join("provenance.json"))?;
    dataset::files::write_json_atomic(&out.join("report.json"), report)?;
    let mut text = markdown(report);
    let font = dataset::plot::system_font();
    for (file, title, x_label, points) in plots(report) {
        let y_label = if file == "inference_overlap.png" {
            "seam score (log)"
        } else {
            "error (log)"
        };
        let plot = Scatter {
            title,
            x_label,
            y_label,
            points: &points,
            y_axis: Axis::Log,
        };
        write_scatter(&plot, font.as_ref(), &out.join(file))?;
        text.push_str(&format!("\n![{title}]({file})\n"));
    }
    if font.is_none() {
        tracing::warn!(
            "no TrueType font found (install fonts-dejavu-core): plots are drawn without labels"
        );
        text.push_str("\n(Plots drawn without labels: no system font was found.)\n");
    }
    dataset::files::write_text_atomic(&out.join("report.md"), &text)?;
    Ok(())
}

//! `g2r-train render`.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;

/// Novel views by ray marching the DEM (max-mipmap, cast shadows, N rays/pixel, optional Gaussian PSF) along
/// a trajectory; with --params renders the learned BRDF and uniform Hapke side by side on one scale.
/// Writes view_NNNN_{hapke,learned}.png (16-bit, I/F = value / 65535 x scale) and views.json.
#[derive(Args, Debug)]
pub struct RenderArgs {
    /// DEM GeoTIFF (lunar CRS, no nodata holes).
    #[arg(long)]
    pub dem: PathBuf,
    /// Parameter GeoTIFF from `infer` on the same DEM grid (omit for uniform Hapke only).
    #[arg(long)]
    pub params: Option<PathBuf>,
    /// CSV with header `x,y,z,q0,qx,qy,qz` (body-fixed m, camera->body quaternion) or
    /// `lon,lat,alt,yaw,pitch,roll` (deg, m above the sphere, deg; all angles 0 = nadir, north up).
    #[arg(long)]
    pub trajectory: PathBuf,
    /// Sun position in body-fixed metres, X,Y,Z (only its direction matters).
    #[arg(long, allow_hyphen_values = true, value_parser = parse_body_vector)]
    pub sun: glam::DVec3,
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, default_value_t = 256)]
    pub width: usize,
    #[arg(long, default_value_t = 256)]
    pub height: usize,
    /// Horizontal field of view, degrees.
    #[arg(long, default_value_t = 45.0)]
    pub fov: f64,
    /// Jittered rays per pixel (1 = through pixel centres).
    #[arg(long, default_value_t = 4)]
    pub rays: usize,
    #[arg(long)]
    pub no_shadows: bool,
    /// Gaussian PSF sigma, pixels (0 = none).
    #[arg(long, default_value_t = 0.0)]
    pub psf_sigma: f64,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

/// `X,Y,Z` (body-fixed metres) as a vector.
fn parse_body_vector(text: &str) -> Result<glam::DVec3, String> {
    let parts: Vec<f64> = text
        .split(',')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("'{text}': {e}; expected X,Y,Z in body-fixed metres"))?;
    match parts[..] {
        [x, y, z] => Ok(glam::DVec3::new(x, y, z)),
        _ => Err(format!(
            "'{text}' has {} numbers; expected three, X,Y,Z in body-fixed metres",
            parts.len()
        )),
    }
}

pub fn run(args: RenderArgs) -> Result<()> {
    let RenderArgs {
        dem,
        params,
        trajectory,
        sun,
        out,
        width,
        height,
        fov,
        rays,
        no_shadows,
        psf_sigma,
        seed,
    } = args;
    dataset::views::run(&dataset::views::RenderJob {
        dem: &dem,
        params: params.as_deref(),
        trajectory: &trajectory,
        sun_body: sun,
        out: &out,
        options: dataset::views::raycast::ViewOptions {
            width,
            height,
            fov_deg: fov,
            rays_per_pixel: rays,
            shadows: !no_shadows,
            psf_sigma_px: psf_sigma,
            seed,
        },
    })
}

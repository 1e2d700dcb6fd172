//! `dataset`: the data contract shared by the pipeline and the trainer.
//!
//! Read in data-flow order: [`crs`] (lunar CRS, local ENU frames) → [`raster`] (GeoTIFF IO, pixel-centre
//! convention) → [`geometry`] (normals, cosines, half/difference angles) → [`horizon`] (cast shadows, visibility)
//! → [`brdf`] and [`hapke`] (photometry reference in f64) → [`schema`] → [`shard`] → [`manifest`].

pub mod acquisition;
pub mod brdf;
pub mod crs;
pub mod geometry;
pub mod hapke;
pub mod horizon;
pub mod manifest;
pub mod raster;
pub mod schema;
pub mod shard;

/// Initialise structured logging for the binaries (`RUST_LOG` overrides the default `info`).
pub fn init_logging() {
    let filter =
        tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into());
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_target(false)
        .with_writer(std::io::stderr)
        .try_init();
}

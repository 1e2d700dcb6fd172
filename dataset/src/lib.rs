//! `dataset`: the data contract shared by the pipeline and the trainer.
//!
//! Read in data-flow order: [`crs`] (lunar CRS, local ENU frames) → [`raster`] (GeoTIFF IO, pixel-centre
//! convention) → [`geometry`] (normals, cosines, half/difference angles) → [`horizon`] (cast shadows, visibility)
//! → [`brdf`] and [`hapke`] (photometry reference in f64) → [`schema`] → [`shard`] → [`manifest`].

pub mod acquisition;
pub mod brdf;
#[cfg(feature = "client")]
pub mod client;
pub mod context;
pub mod crs;
pub mod geometry;
pub mod hapke;
pub mod horizon;
#[cfg(feature = "client")]
pub mod loadtest;
pub mod malloc;
pub mod manifest;
pub mod planner;
pub mod publication;
pub mod raster;
pub mod resample;
pub mod rng;
pub mod schema;
#[cfg(feature = "server")]
pub mod server;
pub mod shard;
pub mod testing;
pub mod world;

/// Initialise structured logging for the binaries (`RUST_LOG` overrides the default `info`), and route GDAL's own
/// messages into it: by default GDAL prints `ERROR 4: …` lines to stderr next to our one-line errors, which
/// already carry the file and the fix.
pub fn init_logging() {
    // burn-collective logs every peer's registration and its whole config at info: kept for RUST_LOG=debug.
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| "info,burn_collective=warn".into());
    // Colour only on a terminal: escape codes in redirected logs make them unreadable and ungreppable.
    let ansi = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_target(false)
        .with_ansi(ansi)
        .with_writer(std::io::stderr)
        .try_init();
    gdal::config::set_error_handler(|class, number, message| {
        tracing::debug!(gdal_class = ?class, gdal_error = number, "GDAL: {message}");
    });
}

//! `dataset`: what the pipeline and the trainer share, in two layers, the second built on the first.
//!
//! - [`science`], the lunar science core: CRS and local frames → rasters → surface geometry → shadows →
//!   reflectance (BRDF models, Hapke) in f64. It knows nothing of datasets.
//! - [`contract`], the data contract on that core: acquisition metadata and the synthetic world's layout → seeded
//!   draw streams → terrain context → the sample schema → Parquet shards → manifests → publication → the epoch
//!   planner that reads them back.
//!
//! Beside them: the HTTP [`client`] of a served dataset (the server itself is the `g2r-dataset-server` crate),
//! published datasets in object [`storage`] (S3 and the like),
//! the binaries' allocator settings and logging, the provenance written next to measurements, and test fixtures.

pub mod science;

pub mod contract;

pub mod client;
pub mod malloc;
pub mod provenance;
pub mod storage;
pub mod testing;

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

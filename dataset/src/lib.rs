//! `dataset`: what the pipeline and the trainer share, in two layers, the second built on the first.
//!
//! - [`science`], the lunar science core: CRS and local frames → rasters → surface geometry → shadows →
//!   reflectance (BRDF models, Hapke) in f64. It knows nothing of datasets.
//! - [`contract`], the data contract on that core: acquisition metadata and the synthetic world's layout → seeded
//!   draw streams → terrain context → the sample schema → Parquet shards → manifests → publication → the epoch
//!   planner that reads them back.
//!
//! Beside them: the HTTP [`client`] of a served dataset (the server itself is the `g2r-dataset-server` crate),
//! published datasets in object [`storage`] (S3 and the like), atomic writes and hashes of [`files`], novel
//! [`views`] of a DEM by ray casting (`g2r-train render`) and the PNG [`plot`]s and labels the commands draw, the
//! binaries' allocator settings, logging and [`progress`], the provenance written next to measurements, and test
//! fixtures.

pub mod science;

pub mod contract;

pub mod client;
pub mod files;
pub mod malloc;
pub mod plot;
pub mod progress;
pub mod provenance;
pub mod storage;
#[cfg(any(test, feature = "testing"))]
pub mod testing;
pub mod views;

/// How every binary reports a failure: `error: ` and the whole cause chain on one line (a cause may carry line
/// breaks of its own, e.g. an object store's XML error body), so a log reader or a test sees one error line.
pub fn error_line(error: &anyhow::Error) -> String {
    format!("error: {error:#}")
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .collect::<Vec<_>>()
        .join(" ")
}

/// `print!` for the binaries' reports on stdout. Rust ignores SIGPIPE, so `print!` into a reader that stopped
/// reading (`g2r-train compare-evals … | head`) panics; [`write_stdout`] ends the process quietly with success
/// instead, as a Unix tool does. A command writes its files before it prints, so nothing it writes is cut short.
#[macro_export]
macro_rules! out {
    ($($arg:tt)*) => { $crate::write_stdout(format_args!($($arg)*)) };
}

/// [`out!`] with a line break, as `println!`.
#[macro_export]
macro_rules! outln {
    () => { $crate::write_stdout(format_args!("\n")) };
    ($($arg:tt)*) => { $crate::write_stdout(format_args!("{}\n", format_args!($($arg)*))) };
}

/// Write to stdout and flush; a closed stdout (the reader is gone) exits 0, any other failure exits 1 with one
/// error line. The SIGPIPE default is not restored instead: the trainer's replicas and the server talk over sockets,
/// where a gone peer must be an error to report, not a signal that kills the process.
pub fn write_stdout(args: std::fmt::Arguments) {
    use std::io::Write;
    let mut stdout = std::io::stdout().lock();
    match stdout.write_fmt(args).and_then(|()| stdout.flush()) {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => std::process::exit(0),
        Err(e) => {
            eprintln!("error: cannot write to stdout: {e}");
            std::process::exit(1);
        }
    }
}

/// Initialise structured logging for the binaries (`RUST_LOG` overrides the default `info`), and route GDAL's own
/// messages into it: by default GDAL prints `ERROR 4: …` lines to stderr next to our one-line errors, which
/// already carry the file and the fix.
pub fn init_logging() {
    let filter =
        tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into());
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

#[cfg(test)]
mod tests {
    /// A cause chain whose inner message spans lines (an S3 XML body) comes out as one line, every part kept.
    #[test]
    fn an_error_chain_with_line_breaks_is_one_line() {
        let inner = anyhow::anyhow!("<Error>\n  <Code>NoSuchBucket</Code>\n</Error>\n");
        let e = inner.context("s3://b/dataset/manifest.json: cannot read it");
        let line = super::error_line(&e);
        assert_eq!(
            line,
            "error: s3://b/dataset/manifest.json: cannot read it: <Error> <Code>NoSuchBucket</Code> </Error>"
        );
    }
}

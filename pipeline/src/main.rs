//! `g2r-pipeline`: build datasets of lunar DEM–image pairs; generate the synthetic lunar world.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::Context;
use clap::{Parser, Subcommand};
use pipeline::synth::{config, WorldConfig};

#[derive(Parser)]
#[command(
    name = "g2r-pipeline",
    version,
    about = "Turn a lunar DEM + orthoimages into DEM-image pair shards; generate a synthetic lunar world",
    long_about = "Turn a lunar DEM + orthoimages + acquisition metadata into Parquet shards of DEM-image pairs \
(erode -> sample -> project -> split -> publish), and generate a seeded synthetic lunar world with a hidden \
ground truth to run it on.\n\nLogs go to stderr (RUST_LOG=debug for more); progress bars show on a terminal."
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Generate a synthetic lunar world: GeoTIFF DEM (5 m, stereo-like), GeoTIFF ortho strips with nodata borders,
    /// one acquisition-metadata JSON per ortho, and truth/ (true fine DEM, true Hapke parameter maps, crater list).
    ///
    /// Output layout: OUT/dem/dem.tif, OUT/ortho/{ID}.tif + {ID}.json, OUT/truth/*, OUT/world.json (file list
    /// with blake3). Built under OUT.partial and renamed when complete. Same preset/config + seed => same bytes.
    Synth {
        /// Built-in world: `demo` (12 x 12 km, about a minute) or `tycho-full` (40 x 40 km, for the 83,614-pair
        /// publication). These are manifests/world-demo.toml and manifests/world-tycho-full.toml.
        #[arg(long, default_value = "demo", conflicts_with = "config")]
        preset: String,
        /// A world TOML file instead of a preset (see manifests/world-demo.toml for every field).
        #[arg(long)]
        config: Option<PathBuf>,
        /// Seed of every random draw (terrain, craters, albedo, acquisitions, noise).
        #[arg(long, default_value_t = 42)]
        seed: u64,
        /// Output directory (must not exist unless --force).
        #[arg(long)]
        out: PathBuf,
        /// Replace OUT if it exists.
        #[arg(long)]
        force: bool,
    },
}

fn main() -> ExitCode {
    dataset::init_logging();
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Synth {
            preset,
            config: config_path,
            seed,
            out,
            force,
        } => {
            let (text, source) = match &config_path {
                Some(p) => (std::fs::read_to_string(p).with_context(|| format!("reading world config {}", p.display()))?, p.display().to_string()),
                None => (
                    config::preset(&preset).ok_or_else(|| anyhow::anyhow!("unknown preset '{preset}': use demo or tycho-full, or --config FILE"))?.to_string(),
                    format!("preset {preset}"),
                ),
            };
            let world = WorldConfig::from_toml(&text)
                .with_context(|| format!("{source}: invalid world config"))?;
            let started = Instant::now();
            let dir = pipeline::synth::generate(&world, seed, &out, force)?;
            let bytes: u64 = walk_bytes(&dir);
            tracing::info!(out = %dir.display(), seconds = format!("{:.1}", started.elapsed().as_secs_f64()), mib = bytes / (1 << 20), "world written");
        }
    }
    Ok(())
}

fn walk_bytes(dir: &std::path::Path) -> u64 {
    std::fs::read_dir(dir)
        .map(|entries| {
            entries
                .flatten()
                .map(|e| {
                    if e.path().is_dir() {
                        walk_bytes(&e.path())
                    } else {
                        e.metadata().map(|m| m.len()).unwrap_or(0)
                    }
                })
                .sum()
        })
        .unwrap_or(0)
}

//! `g2r-dataset`: inspect and verify the data contract (schemas, shards, manifests).

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "g2r-dataset",
    version,
    about = "Inspect and verify lunar DEM–image pair datasets (Parquet shards + manifest.json)"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Print the sample schema (one Parquet row = one DEM–image pair) as a Markdown table.
    Schema,
    /// Summarise one shard: rows, row groups, and the first sample's metadata.
    Inspect {
        /// Path to a `{split}-{i:05}-of-{n:05}.parquet` shard.
        shard: PathBuf,
    },
    /// Check every shard listed in DIR/manifest.json against its size and blake3; exit 1 on any mismatch.
    Verify {
        /// Published dataset directory (holds manifest.json and the shards).
        dir: PathBuf,
    },
}

fn main() -> ExitCode {
    dataset::init_logging();
    match run(Cli::parse()) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<ExitCode> {
    match cli.command {
        Command::Schema => print!("{}", dataset::schema::schema_markdown()),
        Command::Inspect { shard } => {
            let sizes = dataset::shard::row_group_sizes(&shard)?;
            println!(
                "{}: {} rows in {} row groups {:?}",
                shard.display(),
                sizes.iter().sum::<usize>(),
                sizes.len(),
                sizes
            );
            if let Some(first) = dataset::shard::read_row_group(&shard, 0)?.first() {
                println!(
                    "first sample {} (split {}, tile {}, ortho {}) at lon {:.5} lat {:.5}, i={:.1} e={:.1} g={:.1}",
                    first.sample_id, first.split, first.tile_id, first.ortho_id, first.center_lon_deg,
                    first.center_lat_deg, first.incidence_deg, first.emission_deg, first.phase_deg
                );
            }
        }
        Command::Verify { dir } => {
            let manifest = dataset::manifest::DatasetManifest::load(&dir.join("manifest.json"))?;
            let problems = manifest.verify(&dir);
            for p in &problems {
                eprintln!("{p}");
            }
            if !problems.is_empty() {
                eprintln!(
                    "{} of {} shards failed verification",
                    problems.len(),
                    manifest.shards.len()
                );
                return Ok(ExitCode::FAILURE);
            }
            println!("all {} shards match manifest.json", manifest.shards.len());
        }
    }
    Ok(ExitCode::SUCCESS)
}

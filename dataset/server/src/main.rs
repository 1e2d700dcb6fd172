//! `g2r-dataset`: inspect and verify the data contract (schemas, shards, manifests).

use std::io::Write;
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
        /// Published dataset directory (holds manifest.json and the shards), or its object-storage URL
        /// (`s3://bucket/prefix`; S3 settings from AWS_* variables, e.g. AWS_ENDPOINT_URL, AWS_ALLOW_HTTP=true).
        dir: String,
    },
    /// Copy a published dataset to object storage (`s3://bucket/prefix` or `file://`): verified
    /// first, every shard and document uploaded, then manifest.json last with a conditional put, so a reader
    /// never sees a half-published dataset and a published one is never overwritten. `g2r-train fit --data URL`
    /// then trains from it with ranged reads.
    Upload {
        /// Published dataset directory.
        dir: PathBuf,
        /// Destination prefix; must not hold a manifest.json yet.
        url: String,
    },
    /// Verify every shard against manifest.json, then (re)write the dataset card (README.md) and croissant.json.
    /// Refuses (exit 1, nothing written) when any shard does not match.
    Publish {
        /// Published dataset directory (holds manifest.json, the shards and summary.json).
        dir: PathBuf,
    },
    /// Serve a published dataset read-only over HTTP: JSON API under /v1, a browser viewer at /, shard bytes with
    /// Range support, and Arrow IPC streams for training (`g2r-train fit --data http://ADDR`). The dataset may sit
    /// in a directory or in object storage: from a bucket, start-up reads the manifest, each shard's footer and
    /// the small metadata columns; tensors are fetched per request.
    Serve {
        /// Published dataset directory, or its object-storage URL (`s3://bucket/prefix`; S3 settings from AWS_*
        /// variables, e.g. AWS_ENDPOINT_URL, AWS_ALLOW_HTTP=true).
        dir: String,
        /// Address to listen on; port 0 picks a free port. Keep it on loopback unless a proxy fronts it.
        #[arg(long, default_value = "127.0.0.1:8080")]
        addr: std::net::SocketAddr,
        /// Hash every shard against manifest.json before serving (sizes are always checked).
        #[arg(long)]
        verify: bool,
        /// Memory for decoded rows and PNG previews kept between requests, MiB (0 keeps none). A request whose row
        /// is not kept decodes it from its shard, as without a cache.
        #[arg(long, default_value_t = dataset_server::cache::DEFAULT_CACHE_MIB,
              value_parser = clap::value_parser!(u64).range(0..=1 << 24))]
        cache_mib: u64,
    },
    /// Hammer a running server with concurrent clients (metadata pages, tensor rows, previews, shard range reads)
    /// and print requests/s, rows/s, MB/s and latency percentiles as JSON; exit 1 if any request failed.
    LoadTest {
        /// Server base URL, e.g. http://127.0.0.1:8080.
        url: String,
        #[arg(long, default_value_t = 32)]
        clients: usize,
        /// Total requests over all clients.
        #[arg(long, default_value_t = 3200)]
        requests: usize,
        /// Seed of the request mix (same seed, same requests).
        #[arg(long, default_value_t = 0)]
        seed: u64,
    },
}

fn main() -> ExitCode {
    dataset::init_logging();
    match run(Cli::parse()) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("{}", dataset::error_line(&e));
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<ExitCode> {
    match cli.command {
        Command::Schema => dataset::out!("{}", dataset::contract::schema::schema_markdown()),
        Command::Inspect { shard } => {
            let sizes = dataset::contract::shard::row_group_sizes(&shard)?;
            dataset::outln!(
                "{}: {} rows in {} row groups {:?}",
                shard.display(),
                sizes.iter().sum::<usize>(),
                sizes.len(),
                sizes
            );
            if let Some(first) = dataset::contract::shard::read_row_group(&shard, 0)?.first() {
                dataset::outln!(
                    "first sample {} (split {}, tile {}, ortho {}) at lon {:.5} lat {:.5}, i={:.1} e={:.1} g={:.1}",
                    first.sample_id, first.split, first.tile_id, first.ortho_id, first.center_lon_deg,
                    first.center_lat_deg, first.incidence_deg, first.emission_deg, first.phase_deg
                );
            }
        }
        Command::Verify { dir } => {
            let (shards, problems) = if dataset::storage::is_url(&dir) {
                let remote = dataset::storage::RemoteDir::open(&dir)?;
                let shards = dataset::storage::remote_manifest(&remote)?.shards.len();
                (shards, dataset::storage::verify_remote(&remote)?)
            } else {
                let dir = PathBuf::from(&dir);
                let manifest = dataset::contract::manifest::DatasetManifest::load_dir(&dir)?;
                (manifest.shards.len(), manifest.verify(&dir))
            };
            for p in &problems {
                eprintln!("{p}");
            }
            if !problems.is_empty() {
                eprintln!("{} of {shards} shards failed verification", problems.len());
                return Ok(ExitCode::FAILURE);
            }
            dataset::outln!("all {shards} shards match manifest.json");
        }
        Command::Upload { dir, url } => {
            let remote = dataset::storage::RemoteDir::open(&url)?;
            let bytes = dataset::storage::upload_dataset(&dir, &remote)?;
            tracing::info!(
                url,
                mib = bytes >> 20,
                "dataset uploaded; manifest.json written last"
            );
        }
        Command::Publish { dir } => {
            let manifest = dataset::contract::manifest::DatasetManifest::load_dir(&dir)?;
            let problems = manifest.verify(&dir);
            if !problems.is_empty() {
                for p in &problems {
                    eprintln!("{p}");
                }
                anyhow::bail!(
                    "{}: {} of {} shards do not match manifest.json; nothing written (re-run the pipeline's publish stage)",
                    dir.display(),
                    problems.len(),
                    manifest.shards.len()
                );
            }
            dataset::contract::publication::write_descriptions(&dir, &manifest)?;
            dataset::outln!(
                "{}: {} shards verified; wrote README.md and croissant.json",
                dir.display(),
                manifest.shards.len()
            );
        }
        Command::Serve {
            dir,
            addr,
            verify,
            cache_mib,
        } => {
            let options = dataset_server::ServeOptions {
                verify_hashes: verify,
                cache_bytes: cache_mib << 20,
            };
            let runtime = tokio::runtime::Runtime::new()?;
            runtime.block_on(dataset_server::serve(&dir, addr, options, |bound| {
                // A banner nobody reads must not stop a server: a closed stdout is ignored here.
                let _ = writeln!(
                    std::io::stdout(),
                    "serving {dir} at http://{bound}/ (viewer) and http://{bound}/v1/info; Ctrl-C stops"
                );
            }))?;
        }
        Command::LoadTest {
            url,
            clients,
            requests,
            seed,
        } => {
            let report = dataset_server::loadtest::run(&url, clients, requests, seed)?;
            dataset::outln!("{}", serde_json::to_string_pretty(&report)?);
            if report.errors > 0 {
                return Ok(ExitCode::FAILURE);
            }
        }
    }
    Ok(ExitCode::SUCCESS)
}

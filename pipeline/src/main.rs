//! `g2r-pipeline`: build datasets of lunar DEM–image pairs; generate the synthetic lunar world.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use clap::{Parser, Subcommand};
use pipeline::jobs::RunScope;

/// Keep freed tensor-sized buffers (~17 MB per column per row group) in glibc's heap instead of a fresh mmap each
/// time: the page faults, zeroing and mmap-lock contention between threads dominated system time. Measured on
/// tycho-full with the equivalent MALLOC_* variables: project 141.6 s -> 121.4 s wall at the same peak RSS (1.9 GB)
/// with these values. A 1 GiB trim threshold was faster still but raised peak RSS to 2.6 GB, past the 2 GiB budget;
/// mimalloc was slower (publish 92 s against 72 s with glibc at a 1 GiB trim threshold).
fn tune_allocator() {
    dataset::malloc::tune(dataset::malloc::MallocSettings {
        mmap_threshold: 32 << 20,
        trim_threshold: 128 << 20,
        arena_max: Some(4),
    });
}

#[derive(Parser)]
#[command(
    name = "g2r-pipeline",
    version,
    about = "Turn a lunar DEM + orthoimages into DEM-image pair shards; generate a synthetic lunar world",
    long_about = "Turn a lunar DEM + orthoimages + acquisition metadata into Parquet shards of DEM-image pairs \
(ingest -> erode -> sample -> split -> project -> publish), and generate a seeded synthetic lunar world with a hidden \
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
        /// publication), or `many-craters` (tycho-full's size, with 3-4 complex craters of 8-14 km drawn per seed).
        /// These are manifests/world-demo.toml, world-tycho-full.toml and world-many-craters.toml.
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
    /// Run the stale stages of a pipeline manifest: ingest -> erode -> sample -> split -> project -> publish.
    ///
    /// A stage is stale when its code version, parameters or input files changed, or an output is missing or
    /// modified (see `status`). Outputs go to the manifest's output.dir: stages/ (intermediate Parquet tables),
    /// dataset/ (shards, manifest.json, README.md card, croissant.json, summary.json, map.png) and
    /// pipeline.lock.json. Outputs are written under temporary names and renamed when a stage succeeds. Inputs
    /// given as URLs (inputs.dem = "s3://…/dem.tif", inputs.ortho_dir = "s3://…/ortho/") are first copied to
    /// OUT/inputs/, only what changed since the last run (docs/scale-out.md).
    Run {
        /// Pipeline manifest (TOML), e.g. manifests/demo.toml.
        manifest: PathBuf,
        /// Stop after this stage (ingest, erode, sample, split, project, publish).
        #[arg(long, value_parser = clap::builder::PossibleValuesParser::new(pipeline::stages::STAGES))]
        until: Option<String>,
        /// Re-run this stage even if it is up to date (repeatable); later stages follow.
        #[arg(long, value_parser = clap::builder::PossibleValuesParser::new(pipeline::stages::STAGES))]
        force: Vec<String>,
        /// Run only partition I of N (0-based, e.g. `$SLURM_ARRAY_TASK_ID/4`): ingest through project over a run of
        /// consecutive orthos balanced by footprint area, in OUT/partitions/N/I/ with its own lock. Nothing is
        /// published until `--merge N` (docs/scale-out.md). With `output.exchange` in the manifest, a finished
        /// partition is also copied there, for a merge on a machine that shares no file system with this one.
        #[arg(long, value_name = "I/N", conflicts_with = "merge")]
        partition: Option<pipeline::partition::Partition>,
        /// Join the N finished partitions into OUT/stages/ and publish: the same bytes as one process builds. An
        /// unfinished partition is an error naming it, and nothing is published. With `output.exchange`, what the
        /// partitions copied there is fetched first.
        #[arg(long, value_name = "N", value_parser = parse_partition_count)]
        merge: Option<usize>,
    },
    /// Write an orthoimage's acquisition metadata JSON from an ALE ISD or an LROC cumulative-index row.
    ///
    /// The JSON (Moon body-fixed frame, metres; fields of dataset::contract::acquisition::AcquisitionMetadata) goes next to
    /// the image by default, where `run` looks for it. From an ISD (`isd_generate` of USGS ALE, with SPICE):
    /// positions and attitude are rotated from J2000 with the ISD's own lunar orientation, exact to interpolation.
    /// From CUMINDEX.TAB (+ CUMINDEX.LBL, found next to it) or a CSV of its columns: sun and spacecraft from the
    /// sub-points, distance and altitude, the spacecraft carried along the track to the first and last lines via
    /// the corner coordinates, the boresight toward the image centre (docs/bring-your-own-data.md gives the
    /// errors this implies). Any missing or inconsistent key is an error naming the file and the key.
    ImportMetadata {
        /// ALE image support data (JSON) of the image.
        #[arg(long, required_unless_present = "index", conflicts_with = "index")]
        isd: Option<PathBuf>,
        /// Cumulative index table (CUMINDEX.TAB, or a CSV with a header row) holding the image's row.
        #[arg(long)]
        index: Option<PathBuf>,
        /// PDS3 label of the index table (default: the table's name with .LBL, when present).
        #[arg(long, requires = "index")]
        label: Option<PathBuf>,
        /// The orthoimage (any GDAL-readable raster in a lunar projected CRS); its pixel size is the ortho's GSD.
        #[arg(long)]
        image: PathBuf,
        /// PRODUCT_ID of the image (default: the image's file stem, e.g. M1234567890LE).
        #[arg(long)]
        product_id: Option<String>,
        /// Output JSON (default: the image path with .json).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Replace an existing output.
        #[arg(long)]
        force: bool,
    },
    /// Say for each stage whether it is up to date, and if not, why (params, inputs, code version, outputs); list
    /// stray files under stages/ that no stage of this version writes (an older layout's outputs).
    Status {
        /// Pipeline manifest (TOML).
        manifest: PathBuf,
        /// The status of partition I of N instead (see `run --partition`).
        #[arg(long, value_name = "I/N")]
        partition: Option<pipeline::partition::Partition>,
    },
    /// Remove every stage output, stray files under stages/, the published dataset, the partitions' outputs and the
    /// lock of a manifest.
    Clean {
        /// Pipeline manifest (TOML).
        manifest: PathBuf,
    },
}

fn main() -> ExitCode {
    tune_allocator();
    dataset::init_logging();
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("{}", dataset::error_line(&e));
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Synth {
            preset,
            config,
            seed,
            out,
            force,
        } => {
            let world = pipeline::jobs::world_config(&preset, config.as_deref())?;
            let started = Instant::now();
            let dir = pipeline::synth::generate(&world, seed, &out, force)?;
            let mib = pipeline::jobs::tree_bytes(&dir) / (1 << 20);
            tracing::info!(out = %dir.display(), seconds = format!("{:.1}", started.elapsed().as_secs_f64()), mib, "world written");
        }
        Command::Run {
            manifest,
            until,
            force,
            partition,
            merge,
        } => {
            let manifest = pipeline::manifest::PipelineManifest::load(&manifest)?;
            let scope = match (partition, merge) {
                (Some(part), _) => RunScope::Partition(part),
                (None, Some(count)) => RunScope::Merge(count),
                (None, None) => RunScope::Whole,
            };
            // The projection's crops (the long stage); each stage's start and end are logged besides.
            let progress = dataset::progress::Progress::start("pipeline", "crops", 0);
            let force: Vec<&str> = force.iter().map(String::as_str).collect();
            let outcome = pipeline::jobs::run(
                &manifest,
                scope,
                until.as_deref(),
                &force,
                progress.bar().clone(),
            )?;
            progress.finish();
            if outcome.stages.is_empty() {
                tracing::info!("everything up to date");
            } else {
                let names: Vec<&str> = outcome.stages.iter().map(|stage| stage.name).collect();
                tracing::info!(stages = names.join(","), seconds = format!("{:.1}", outcome.seconds), out = %manifest.out_dir().display(), "pipeline run");
            }
        }
        Command::ImportMetadata {
            isd,
            index,
            label,
            image,
            product_id,
            out,
            force,
        } => {
            let source = match (&isd, &index) {
                (Some(isd), _) => pipeline::import::Source::Isd(isd),
                (None, Some(table)) => pipeline::import::Source::Index {
                    table,
                    label: label.as_deref(),
                },
                (None, None) => unreachable!("clap requires --isd or --index"),
            };
            let product_id = product_id.unwrap_or_else(|| {
                image
                    .file_stem()
                    .map(|s| s.to_string_lossy().into_owned())
                    .unwrap_or_default()
            });
            let out = out.unwrap_or_else(|| image.with_extension("json"));
            let meta = pipeline::import::import(source, &image, &product_id, &out, force)?;
            tracing::info!(out = %out.display(), product_id, start = meta.start_time_utc, roll_deg = format!("{:.3}", meta.roll_deg), "acquisition metadata written");
        }
        Command::Status {
            manifest,
            partition,
        } => {
            let manifest = pipeline::manifest::PipelineManifest::load(&manifest)?;
            for line in pipeline::jobs::status_lines(&manifest, partition)? {
                dataset::outln!("{line}");
            }
        }
        Command::Clean { manifest } => {
            let manifest = pipeline::manifest::PipelineManifest::load(&manifest)?;
            let removed = pipeline::jobs::clean(&manifest)?;
            tracing::info!(files = removed, "cleaned");
        }
    }
    Ok(())
}

/// `--merge N`: the number of partitions the map tasks ran, at least one.
fn parse_partition_count(text: &str) -> Result<usize, String> {
    match text.trim().parse::<usize>() {
        Ok(n) if n >= 1 => Ok(n),
        _ => Err(format!(
            "'{text}' is not a partition count: --merge N takes the N of the map tasks' --partition I/N (N ≥ 1)"
        )),
    }
}

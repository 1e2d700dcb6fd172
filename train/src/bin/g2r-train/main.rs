//! `g2r-train`: learn a spatially varying lunar BRDF from DEM geometry (Burn). Dispatch only: each subcommand's
//! flags and call live in [`commands`], the work in the library.

mod commands;

use anyhow::Result;
use clap::{Parser, Subcommand};

use commands::*;

#[derive(Parser)]
#[command(
    name = "g2r-train",
    version,
    about = "Train a U-Net that maps 128x128 DEM crops to per-pixel BRDF parameters (M1-M6, L2-L4, H1, H3) through a differentiable renderer",
    long_about = "Train a U-Net that maps 128x128 DEM crops (5 m/px) to per-pixel parameters of a small \
cosine-polynomial BRDF, supervised by rendering through a differentiable renderer layer and comparing with the \
orthoimage (MSE over valid pixels).\n\nData: a dataset directory published by `g2r-pipeline run` (manifest.json + \
shards). CPU training is slow (the paper-size U-Net costs ~6 GFLOP per sample): use --width 4 or 8 and \
--max-train-samples for CPU budgets, the cuda backend on a GPU machine for full runs."
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand)]
pub enum Command {
    /// List the BRDF models (M1-M6, L2-L4, H1, H3) with their parameter order (the band order of parameter GeoTIFFs).
    Models,
    Fit(fit::FitArgs),
    CompareModels(compare_models::CompareModelsArgs),
    Eval(eval::EvalArgs),
    CompareEvals(compare_evals::CompareEvalsArgs),
    ModelChoice(model_choice::ModelChoiceArgs),
    CraterLevel(crater_level::CraterLevelArgs),
    InputRange(input_range::InputRangeArgs),
    Infer(infer::InferArgs),
    Report(report::ReportArgs),
    Render(render::RenderArgs),
    Bench(bench::BenchArgs),
}

/// Keep freed activation-sized buffers (up to 17 MB at width 16, batch 8) in glibc's heap: with the defaults, which
/// buffers came back as fresh mappings (page faults, zeroing, TLB shootdowns) shifted with unrelated changes to
/// the step and moved it by 10 % (`docs/performance.md`). With these values the width-16 bench step was 455–467 ms
/// against 516–525 ms with the defaults, in one sitting.
fn tune_allocator() {
    dataset::malloc::tune(dataset::malloc::MallocSettings {
        mmap_threshold: 32 << 20,
        trim_threshold: 256 << 20,
        arena_max: None,
    });
}

fn main() {
    tune_allocator();
    dataset::init_logging();
    if let Err(e) = run(Cli::parse()) {
        eprintln!("{}", dataset::error_line(&e));
        std::process::exit(1);
    }
}

fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Models => models::run(),
        Command::Fit(args) => fit::run(args),
        Command::CompareModels(args) => compare_models::run(args),
        Command::Eval(args) => eval::run(args),
        Command::CompareEvals(args) => compare_evals::run(args),
        Command::ModelChoice(args) => model_choice::run(args),
        Command::CraterLevel(args) => crater_level::run(args),
        Command::InputRange(args) => input_range::run(args),
        Command::Infer(args) => infer::run(args),
        Command::Report(args) => report::run(args),
        Command::Render(args) => render::run(args),
        Command::Bench(args) => bench::run(args),
    }
}

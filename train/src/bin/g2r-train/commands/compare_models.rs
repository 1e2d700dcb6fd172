//! `g2r-train compare-models`.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use train::with_backend;

use super::training_args::{training_source, TrainArgs};

/// Train every BRDF model (M1-M6, L2-L4, H1, H3) under the same budget and write a comparison table (val MSE, parameters, step time).
#[derive(Args, Debug)]
pub struct CompareModelsArgs {
    /// Dataset directory or server URL, as for `fit`.
    #[arg(long)]
    pub data: String,
    #[arg(long)]
    pub out: PathBuf,
    #[command(flatten)]
    pub training: TrainArgs,
}

pub fn run(args: CompareModelsArgs) -> Result<()> {
    let CompareModelsArgs {
        data,
        out,
        training,
    } = args;
    train::data_parallel::refuse_launcher_world(
        &|name| std::env::var(name).ok(),
        "compare-models",
    )?;
    let (source, config) = training_source(&data, &training)?;
    let backend = training.backend.name();
    let markdown = with_backend!(training.backend, B => {
        train::model_comparison::compare_models::<B>(source, &config, backend, &out)
    })?;
    dataset::out!("{markdown}");
    Ok(())
}

//! `g2r-train input-range`.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use train::data::{open_source, PooledSource, SampleSource};

/// Measure the range a run's per-crop inputs spanned over its train crops (crop height std, context off the DEM,
/// crater-relative height, crater relief over diameter) and keep it in the run as input_range.json, against which
/// `eval` and `infer` count the crops outside it. `fit` keeps one from the start; this measures it for a run
/// trained before. Give the publications the run trained on, in the order `fit` was given them.
#[derive(Args, Debug)]
pub struct InputRangeArgs {
    /// Run directory written by `fit`.
    #[arg(long)]
    pub run: PathBuf,
    /// The run's --data: a dataset directory, server URL or object-storage prefix.
    #[arg(long)]
    pub data: String,
    /// The run's further training publications (its --also-train-on, in order).
    #[arg(long, value_name = "DATA")]
    pub also_train_on: Vec<String>,
}

pub fn run(args: InputRangeArgs) -> Result<()> {
    let InputRangeArgs {
        run,
        data,
        also_train_on,
    } = args;
    let first = open_source(&data)?;
    let mut datasets = vec![first.manifest().name.clone()];
    let source: std::sync::Arc<dyn SampleSource> = if also_train_on.is_empty() {
        first
    } else {
        let more = also_train_on
            .iter()
            .map(|d| open_source(d))
            .collect::<Result<Vec<_>>>()?;
        let pool = PooledSource::new(first, more)?;
        datasets.extend(pool.further_names());
        std::sync::Arc::new(pool)
    };
    let range = train::run_dir::record_input_range(&run, source.as_ref(), datasets)?;
    for (name, interval) in &range.inputs {
        dataset::outln!("{name}: {:.6} to {:.6}", interval.min, interval.max);
    }
    dataset::outln!(
        "wrote {}: the range of {} train crops of {}",
        run.join(train::data::INPUT_RANGE_FILE).display(),
        range.crops,
        range.datasets.join(", ")
    );
    Ok(())
}

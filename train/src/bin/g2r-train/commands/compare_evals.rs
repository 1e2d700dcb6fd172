//! `g2r-train compare-evals`.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;

/// Can two evaluations of the same crops be told apart? Pairs them crop by crop and bootstraps the candidate's
/// learned SSE over the base's by whole orthos (the crops of one ortho share sun, view and ground, so the ortho
/// is what varies between held-out tiles): prints the ratio, its 95 % interval and whether it holds 1; with
/// --out, writes comparison.json, comparison.md and provenance.json.
#[derive(Args, Debug)]
pub struct CompareEvalsArgs {
    /// The base: an `eval --out` directory (or its metrics.json).
    pub base: PathBuf,
    /// The candidate, evaluated on the same split with the same --max-samples.
    pub candidate: PathBuf,
    /// Ortho resamples.
    #[arg(long, default_value_t = 4000)]
    pub resamples: usize,
    /// Seed of the resampling stream.
    #[arg(long, default_value_t = 42)]
    pub seed: u64,
    #[arg(long)]
    pub out: Option<PathBuf>,
}

pub fn run(args: CompareEvalsArgs) -> Result<()> {
    let CompareEvalsArgs {
        base,
        candidate,
        resamples,
        seed,
        out,
    } = args;
    let names = (base.display().to_string(), candidate.display().to_string());
    let names = (names.0.as_str(), names.1.as_str());
    let comparison = train::evaluation::compare_evals(
        &train::evaluation::read_eval_record(&base)?,
        &train::evaluation::read_eval_record(&candidate)?,
        names,
        resamples,
        seed,
    )?;
    let markdown = train::evaluation::comparison_markdown(&comparison, names);
    // The files first: a reader that stops early (`| head`) must not cut them.
    if let Some(out) = &out {
        train::evaluation::write_comparison(&comparison, &markdown, out)?;
    }
    dataset::out!("{markdown}");
    if let Some(out) = out {
        dataset::outln!(
            "\nwrote {}/comparison.json and comparison.md",
            out.display()
        );
    }
    Ok(())
}

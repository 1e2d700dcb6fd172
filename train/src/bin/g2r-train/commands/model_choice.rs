//! `g2r-train model-choice`.

use std::path::PathBuf;

use anyhow::Result;
use clap::Args;
use dataset::science::brdf::BrdfModel;
use train::data::open_source;

/// Which BRDF model each kind of ground needs, with no network in the way: per crop, each candidate's
/// model-form oracle (the best geometry-blind coefficients for the true material at every pixel: what its form
/// attains) and its uniform fit, grouped by terrain class and unit; per ground, the cheapest candidate whose
/// form error is within --tolerance of the best. Needs a synthetic world (--world). Writes model-choice.json
/// and model-choice.md.
#[derive(Args, Debug)]
pub struct ModelChoiceArgs {
    /// Dataset directory or server URL.
    #[arg(long)]
    pub data: String,
    /// Choose on validation; score test once, after.
    #[arg(long, default_value = "val")]
    pub split: dataset::contract::schema::Split,
    /// Synthetic world directory (its truth/ maps).
    #[arg(long)]
    pub world: PathBuf,
    /// Candidate models, comma-separated (default: two cosine polynomials, the Lommel-Seeliger family's best
    /// and the one-scale Hapke the trainer ships). Cost: parameter maps, then whether it evaluates Hapke.
    #[arg(long, value_delimiter = ',', default_value = "m1,m2,l3,h1")]
    pub models: Vec<BrdfModel>,
    /// How far above the best form error a cheaper model may be and still be chosen (0.05 = 5 %).
    #[arg(long, default_value_t = 0.05)]
    pub tolerance: f64,
    /// Images, spread evenly over the split (default: all).
    #[arg(long)]
    pub max_samples: Option<usize>,
    /// Train crops (spread evenly) for each candidate's uniform fit.
    #[arg(long, default_value_t = 256)]
    pub calibration_samples: usize,
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(args: ModelChoiceArgs) -> Result<()> {
    let ModelChoiceArgs {
        data,
        split,
        world,
        models,
        tolerance,
        max_samples,
        calibration_samples,
        out,
    } = args;
    let source = open_source(&data)?;
    let truth = train::evaluation::TruthMaps::open(&world)?;
    let options = train::evaluation::ModelChoiceOptions {
        split,
        max_samples,
        calibration_samples,
        candidates: models,
        tolerance,
    };
    let report = train::evaluation::model_choice(source.as_ref(), &truth, &options)?;
    train::evaluation::write_model_choice(&report, &out)?;
    dataset::out!("{}", train::evaluation::model_choice_markdown(&report));
    dataset::outln!(
        "\nwrote {}/model-choice.json and model-choice.md",
        out.display()
    );
    Ok(())
}

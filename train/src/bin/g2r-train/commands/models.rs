//! `g2r-train models`.

use anyhow::Result;
use dataset::science::brdf::BrdfModel;

pub fn run() -> Result<()> {
    for model in BrdfModel::ALL {
        dataset::outln!(
            "{}: {} params: {}",
            model.name(),
            model.param_count(),
            model.term_names().join(", ")
        );
    }
    Ok(())
}

//! Model comparison (`g2r-train compare-models`): every BRDF model trained under one budget by the same fit loop,
//! and the table of their last epochs.

use std::path::Path;
use std::sync::Arc;

use anyhow::{bail, Result};
use dataset::science::brdf::BrdfModel;

use crate::data::SampleSource;
use crate::fit_config::FitConfig;
use crate::kernels::TrainBackend;
use crate::training::fit;

/// `g2r-train compare-models`: one run per BRDF model (M1–M6, L2–L4, H1, H3) with `base`'s budget, into `out/{model}`;
/// the table of their last epochs is written as `out/compare.md` and `out/compare.json` and returned as Markdown.
/// Refuses before training anything if a model's directory already holds a run.
pub fn compare_models<B: TrainBackend>(
    source: Arc<dyn SampleSource>,
    base: &FitConfig,
    backend: &str,
    out: &Path,
) -> Result<String> {
    for model in BrdfModel::ALL {
        let run_dir = out.join(model.name());
        if run_dir.join("last").exists() {
            bail!(
                "{}: already holds a run: remove it or choose a new --out",
                run_dir.display()
            );
        }
    }
    let mut rows = Vec::new();
    let mut table = String::from("| model | params/pixel | trainable weights | val loss (pixel MSE) | val PSNR dB | val SSIM | s/step |\n|---|---|---|---|---|---|---|\n");
    for model in BrdfModel::ALL {
        let config = FitConfig {
            model,
            ..base.clone()
        };
        let outcome = fit::<B>(
            source.clone(),
            &config,
            &out.join(model.name()),
            false,
            None,
            &Default::default(),
            true,
        )?;
        let last = outcome.history.last().cloned();
        if let Some(m) = &last {
            table.push_str(&format!(
                "| {} | {} | {} | {:.4e} | {:.2} | {} | {:.3} |\n",
                model.name(),
                model.param_count(),
                outcome.trainable_params,
                m.val_loss,
                m.val_psnr_db,
                crate::metrics::ssim_text(m.val_ssim),
                outcome.seconds_per_step
            ));
        }
        rows.push(serde_json::json!({"model": model.name(), "trainable_params": outcome.trainable_params, "seconds_per_step": outcome.seconds_per_step, "last_epoch": last}));
    }
    let stream = &base.stream;
    let budget = format!(
        "Budget: {} epochs x {} train samples, batch {}, width {}, lr {}, seed {}, backend {backend}.\n\n",
        base.epochs,
        stream.max_samples.map_or("all".to_string(), |m| m.to_string()),
        stream.batch_size,
        base.base_width,
        base.learning_rate,
        stream.seed,
    );
    std::fs::create_dir_all(out)?;
    let markdown = format!("{budget}{table}");
    dataset::files::write_text_atomic(
        &out.join("compare.md"),
        &format!("# BRDF model comparison\n\n{markdown}"),
    )?;
    dataset::files::write_json_atomic(&out.join("compare.json"), &rows)?;
    Ok(markdown)
}

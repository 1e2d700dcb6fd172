//! `g2r-train crater-level`, and the crater level `fit --crater-level` fits when training ends.

use std::path::{Path, PathBuf};

use anyhow::Result;
use clap::Args;
use train::backend::{BackendKind, Inner};
use train::crater_level_fit::CraterLevelOptions;
use train::data::{open_source, SampleSource};
use train::run_dir::Checkpoint;
use train::with_backend;

use super::RunsArgs;

/// Fit a crater level beside an H1 run and keep it in the run directory (crater_level.json), where `eval` and
/// `infer` apply it: each crop near a large catalogued crater gets the brightness level a small regression
/// gives it from its height against the crater's median profile, its slope and its radius, while the network's
/// pattern inside the crop stays. Zones of crater radii are grown on train crops, one regression each (no
/// network); how many zones to keep and how far each moves the network's level are chosen on the validation
/// split, by the run's summed squared error. With --world, no kind of ground (the world's terrain classes) may
/// end with a larger validation error than the network's alone. Needs a dataset published with
/// inputs.crater_catalogue (schema 1.3).
#[derive(Args, Debug)]
pub struct CraterLevelArgs {
    #[command(flatten)]
    pub runs: RunsArgs,
    /// Dataset directory or server URL.
    #[arg(long)]
    pub data: String,
    /// Train crops read, spread evenly over the split (those within 3 radii of a crater are fitted on).
    #[arg(long)]
    pub max_train_samples: Option<usize>,
    /// Validation crops the choice is scored on, spread evenly (default: all).
    #[arg(long)]
    pub max_val_samples: Option<usize>,
    #[arg(long, default_value_t = 8)]
    pub batch: usize,
    /// The synthetic world the dataset was published from: its truth/terrain_class.tif names each validation
    /// crop's ground (class and unit), and the weights are held so that none ends worse than the network.
    #[arg(long)]
    pub world: Option<PathBuf>,
    /// Where to write it (default RUN/crater_level.json, which eval and infer load with the run).
    #[arg(long)]
    pub out: Option<PathBuf>,
}

pub fn run(args: CraterLevelArgs) -> Result<()> {
    let CraterLevelArgs {
        runs,
        data,
        max_train_samples,
        max_val_samples,
        batch,
        world,
        out,
    } = args;
    if !runs.ensemble.is_empty() {
        anyhow::bail!("a crater level is fitted beside one run: drop --ensemble");
    }
    let source = open_source(&data)?;
    let options = CraterLevelOptions {
        train_samples: max_train_samples,
        val_samples: max_val_samples,
        batch_size: batch,
    };
    let choice = fit_and_write(
        (&runs.run, runs.checkpoint, runs.backend),
        source.as_ref(),
        &options,
        world.as_deref(),
        out,
    )?;
    dataset::out!("{choice}");
    Ok(())
}

/// Fit the crater level of `run` (its checkpoint, on its backend) on its network alone, guarded by `world`'s
/// terrain classes when given, write it (default RUN/crater_level.json) and return the choice as text, which the
/// caller prints once every file is written.
pub fn fit_and_write(
    (run, checkpoint, backend): (&Path, Checkpoint, BackendKind),
    source: &dyn SampleSource,
    options: &CraterLevelOptions,
    world: Option<&Path>,
    out: Option<PathBuf>,
) -> Result<String> {
    let out = out.unwrap_or_else(|| run.join(train::crater_level::CRATER_LEVEL_FILE));
    let terrain = match world {
        Some(world) => Some(train::evaluation::TerrainMap::open(world)?.ok_or_else(|| {
            anyhow::anyhow!(
                "{}: missing: --world must be a synthetic world of v3 or later (g2r-pipeline synth --out), whose truth/ names each crop's ground",
                world.join(dataset::contract::world::TRUE_TERRAIN_CLASS).display()
            )
        })?),
        None => None,
    };
    let fit = with_backend!(backend, B => {
        let device = Default::default();
        // The network alone: a level already kept beside it must not score the candidates.
        let mut trained = train::run_dir::load_trained::<Inner<B>>(run, checkpoint, &device)?;
        trained.crater_level = None;
        train::crater_level_fit::fit_crater_level(&trained, source, options, terrain.as_ref(), &device)
    })?;
    dataset::files::write_json_atomic(&out, &fit.level)?;
    Ok(format!(
        "{}\nwrote {}\n",
        train::crater_level_fit::markdown(&fit),
        out.display()
    ))
}

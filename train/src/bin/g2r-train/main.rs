//! `g2r-train`: learn a spatially varying lunar BRDF from DEM geometry (Burn). Parsing ([`args`]) and wiring
//! only; the work lives in the library.

mod args;

use std::sync::Arc;

use anyhow::Result;
use clap::Parser;
use dataset::science::brdf::BrdfModel;
use train::backend::Inner;
use train::backend::RankDevice;
use train::data::{open_source, PooledSource, SampleSource};
use train::fit_config::FitConfig;
use train::with_backend;

use args::{Cli, Command, TrainArgs};

/// `--data`, pooled with `--also-train-on`'s publications when there are any, and the run's config, which names
/// them.
fn training_source(data: &str, args: &TrainArgs) -> Result<(Arc<dyn SampleSource>, FitConfig)> {
    let (first, mut config) = (open_source(data)?, args.fit_config());
    if args.also_train_on.is_empty() {
        return Ok((first, config));
    }
    let more = args
        .also_train_on
        .iter()
        .map(|data| open_source(data))
        .collect::<Result<Vec<_>>>()?;
    let pool = PooledSource::new(first, more)?;
    config.also_train_on = pool.further_names();
    Ok((Arc::new(pool), config))
}

/// Train as this process's rank ([`train::data_parallel::launch`]): the outcome, on the lead rank only.
fn run_fit(
    source: Arc<dyn SampleSource>,
    config: &FitConfig,
    args: &TrainArgs,
    out: &std::path::Path,
    resume: bool,
    stop: Option<u64>,
) -> Result<Option<train::training::FitOutcome>> {
    let env = |name: &str| std::env::var(name).ok();
    let timeout = std::time::Duration::from_secs(args.collective_timeout);
    let ranks = train::data_parallel::launch(&env, timeout)?;
    let outcome = with_backend!(args.backend, B => {
        let device = <B as RankDevice>::rank_device(ranks.local_rank());
        train::training::fit_ranks::<B>(source, config, out, resume, stop, &device, &ranks, true)
    })
    .map_err(|e| ranks.end_on_error(e))?;
    Ok(ranks.leads().then_some(outcome))
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

/// `crater-level` (and `fit --crater-level`): fit the run's crater level on its network alone, write it (default
/// RUN/crater_level.json) and return the choice as text, which the caller prints once every file is written.
fn fit_and_write_crater_level(
    runs: &args::RunsArgs,
    source: &dyn SampleSource,
    train_samples: Option<usize>,
    val_samples: Option<usize>,
    batch: usize,
    out: Option<std::path::PathBuf>,
) -> Result<String> {
    let options = train::crater_level::CraterLevelOptions {
        train_samples,
        val_samples,
        batch_size: batch,
    };
    let out = out.unwrap_or_else(|| runs.run.join(train::crater_level::CRATER_LEVEL_FILE));
    let fit = with_backend!(runs.backend, B => {
        let device = Default::default();
        // The network alone: a level already kept beside it must not score the candidates.
        let mut run = train::run_dir::load_trained::<Inner<B>>(&runs.run, runs.checkpoint, &device)?;
        run.crater_level = None;
        train::crater_level::fit_crater_level(&run, source, &options, &device)
    })?;
    dataset::contract::manifest::write_json_atomic(&out, &fit.level)?;
    Ok(format!(
        "{}\nwrote {}\n",
        train::crater_level::markdown(&fit),
        out.display()
    ))
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
        Command::Eval {
            runs,
            data,
            split,
            world,
            out,
            max_samples,
            batch,
            calibration_samples,
            panels,
            symmetry_mean,
        } => {
            let source = open_source(&data)?;
            let out = out.unwrap_or_else(|| runs.run.join(format!("eval-{split}")));
            let paths = runs.paths();
            let job = train::evaluation::EvalJob {
                runs: &paths,
                checkpoint: runs.checkpoint,
                source: source.as_ref(),
                world: world.as_deref(),
                out: &out,
                options: train::evaluation::EvalOptions {
                    split,
                    max_samples,
                    batch_size: batch.max(1),
                    calibration_samples,
                    panels,
                    symmetry_mean,
                },
            };
            let report = with_backend!(runs.backend, B => {
                train::evaluation::run_job::<Inner<B>>(&job, &Default::default())
            })?;
            dataset::out!("{}", train::evaluation::markdown(&report));
            dataset::outln!(
                "\nwrote {}/metrics.json, metrics.md and panels/",
                out.display()
            );
        }
        Command::CompareEvals {
            base,
            candidate,
            resamples,
            seed,
            out,
        } => {
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
        }
        Command::ModelChoice {
            data,
            split,
            world,
            models,
            tolerance,
            max_samples,
            calibration_samples,
            out,
        } => {
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
        }
        Command::CraterLevel {
            runs,
            data,
            max_train_samples,
            max_val_samples,
            batch,
            out,
        } => {
            if !runs.ensemble.is_empty() {
                anyhow::bail!("a crater level is fitted beside one run: drop --ensemble");
            }
            let source = open_source(&data)?;
            let choice = fit_and_write_crater_level(
                &runs,
                source.as_ref(),
                max_train_samples,
                max_val_samples,
                batch,
                out,
            )?;
            dataset::out!("{choice}");
        }
        Command::Infer {
            runs,
            dem,
            out,
            overlap,
            batch,
            dem_std_m,
            craters,
        } => {
            let progress = dataset::progress::Progress::start("infer", "batches", 0);
            let raster = dataset::science::raster::read_raster(&dem)?;
            let crater_frames = craters
                .catalogue
                .map(|path| {
                    train::inference::crater_frames_from_catalogue(
                        &raster,
                        &path,
                        craters.min_diameter_m,
                    )
                })
                .transpose()?;
            let paths = runs.paths();
            let job = train::inference::InferJob {
                runs: &paths,
                checkpoint: runs.checkpoint,
                dem: &raster,
                dem_path: &dem,
                overlap,
                batch_size: batch,
                dem_std_m,
                crater_frames,
            };
            let maps = with_backend!(runs.backend, B => {
                train::inference::run_job::<Inner<B>>(&job, &Default::default(), |member, done, total| {
                    progress.set_message(member.display().to_string());
                    progress.set_length(total as u64);
                    progress.set_position(done as u64);
                })
            })?;
            progress.finish();
            match maps.crater_level_crops {
                Some(crops) => tracing::info!(crops, "crater level applied"),
                None if std::fs::exists(runs.run.join(train::crater_level::CRATER_LEVEL_FILE))? => {
                    tracing::warn!(
                        "the run keeps a crater level, left out: give --crater-catalogue to set the level of the crops around its large craters"
                    )
                }
                None => {}
            }
            train::inference::write_params_geotiff(&maps, &raster, overlap, &out)?;
            dataset::outln!(
                "{}: {} x {} px, {} bands ({}), {} crops at overlap {overlap}",
                out.display(),
                maps.width,
                maps.height,
                maps.bands.len(),
                maps.model.name(),
                maps.crops
            );
        }
        Command::Report {
            data,
            out,
            split,
            max_samples,
            calibration_samples,
            run,
            checkpoint,
            dem,
            overlaps,
            craters,
            ortho,
            resampling_crops,
            backend,
        } => {
            if craters.catalogue.is_some() && run.is_none() {
                anyhow::bail!("--crater-catalogue frames the crops of --run's overlap rows: give --run RUN_DIR (and --dem), or drop --crater-catalogue");
            }
            let source = open_source(&data)?;
            let job = train::report::ReportJob {
                source: source.as_ref(),
                split,
                max_samples,
                calibration_samples,
                run: run.as_deref().map(|run| (run, checkpoint)),
                dem: dem.as_deref(),
                overlaps: &overlaps,
                crater_catalogue: craters
                    .catalogue
                    .as_deref()
                    .map(|path| (path, craters.min_diameter_m)),
                ortho: ortho.as_deref(),
                resampling_crops,
            };
            let report = with_backend!(backend, B => {
                train::report::run_job::<Inner<B>>(&job, &Default::default())
            })?;
            train::report::write(&report, &out)?;
            dataset::out!("{}", train::report::markdown(&report));
        }
        Command::Render {
            dem,
            params,
            trajectory,
            sun,
            out,
            width,
            height,
            fov,
            rays,
            no_shadows,
            psf_sigma,
            seed,
        } => {
            train::views::run(&train::views::RenderJob {
                dem: &dem,
                params: params.as_deref(),
                trajectory: &trajectory,
                sun_body: sun,
                out: &out,
                options: train::views::raycast::ViewOptions {
                    width,
                    height,
                    fov_deg: fov,
                    rays_per_pixel: rays,
                    shadows: !no_shadows,
                    psf_sigma_px: psf_sigma,
                    seed,
                },
            })?;
        }
        Command::Models => {
            for model in BrdfModel::ALL {
                dataset::outln!(
                    "{}: {} params: {}",
                    model.name(),
                    model.param_count(),
                    model.term_names().join(", ")
                );
            }
        }
        Command::Fit {
            data,
            out,
            resume,
            stop_after_steps,
            crater_level,
            train,
        } => {
            if crater_level && train.model != BrdfModel::H1 {
                anyhow::bail!(
                    "--crater-level scales H1's one scale, but --model is {}: train with --model h1, or drop --crater-level",
                    train.model.name()
                );
            }
            let (source, config) = training_source(&data, &train)?;
            let Some(outcome) = run_fit(
                source.clone(),
                &config,
                &train,
                &out,
                resume,
                stop_after_steps,
            )?
            else {
                // Another rank of a data-parallel fit: the lead reports and fits the crater level.
                return Ok(());
            };
            // The crater level is fitted and written before anything is printed: a reader that stops early
            // (`| head`) ends the process at its first print, and must not cut the fit short.
            let crater_level_text = if !crater_level {
                String::new()
            } else if outcome.cursor.epoch < config.epochs {
                "training stopped before its last epoch: the crater level is fitted when it finishes (--resume --crater-level)\n".to_string()
            } else {
                let runs = args::RunsArgs {
                    run: out.clone(),
                    ensemble: Vec::new(),
                    checkpoint: train::run_dir::Checkpoint::Auto,
                    backend: train.backend,
                };
                fit_and_write_crater_level(&runs, source.as_ref(), None, None, 8, None)?
            };
            dataset::outln!(
                "{}: {} steps, {} trainable parameters, {:.3} s/step; metrics in {}",
                out.display(),
                outcome.cursor.step,
                outcome.trainable_params,
                outcome.seconds_per_step,
                out.join("metrics.jsonl").display()
            );
            if let Some(last) = outcome.history.last() {
                dataset::outln!(
                    "last epoch: val per-pixel MSE {:.4e}, PSNR {:.2} dB, SSIM {}",
                    last.val_pixel_mse,
                    last.val_psnr_db,
                    train::metrics::ssim_text(last.val_ssim)
                );
            }
            dataset::out!("{crater_level_text}");
        }
        Command::CompareModels { data, out, train } => {
            train::data_parallel::refuse_launcher_world(
                &|name| std::env::var(name).ok(),
                "compare-models",
            )?;
            let (source, config) = training_source(&data, &train)?;
            let backend = train.backend.name();
            let markdown = with_backend!(train.backend, B => {
                train::training::compare_models::<B>(source, &config, backend, &out)
            })?;
            dataset::out!("{markdown}");
        }
        Command::Bench {
            batch,
            width,
            model,
            iters,
            backend,
            torch,
            conv_backward,
            compare_conv_backward,
            rounds,
        } => {
            let (name, torch_device) = (backend.name(), backend.torch_device());
            train::kernels::cubecl::set_conv_backward(conv_backward);
            let measured = match torch {
                None if compare_conv_backward => {
                    let comparison = with_backend!(backend, B => Ok::<_, anyhow::Error>(
                        train::bench::compare_conv_backward::<B>(
                            name, model, batch, width, iters, rounds, &Default::default()
                        )
                    ))?;
                    serde_json::to_value(&comparison)?
                }
                Some(python) => {
                    anyhow::ensure!(
                        model == BrdfModel::M2,
                        "--torch compares the M2 step only: drop --model or use --model m2"
                    );
                    let comparison = with_backend!(backend, B => train::bench::compare_with_torch::<B>(
                        &python, name, torch_device, batch, width, iters, rounds, &Default::default()
                    ))?;
                    serde_json::to_value(&comparison)?
                }
                None => {
                    let report: train::bench::BenchReport = with_backend!(backend, B => Ok::<_, anyhow::Error>(
                        train::bench::bench::<B>(name, model, batch, width, iters, &Default::default())
                    ))?;
                    serde_json::to_value(&report)?
                }
            };
            let provenance = dataset::provenance::Provenance::capture();
            let record = serde_json::json!({ "bench": measured, "provenance": provenance });
            dataset::outln!("{}", serde_json::to_string_pretty(&record)?);
        }
        Command::ResultsPage {
            records,
            out,
            embed_in,
            check,
        } => dataset::outln!(
            "{}",
            train::results_page::run_job(&records, &out, &embed_in, check)?
        ),
    }
    Ok(())
}

//! A replica's epochs: steps (gradients averaged over the ranks), validation and checkpoints by the lead.

use std::sync::Arc;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use burn::module::AutodiffModule;
use burn::optim::{GradientsParams, Optimizer};
use burn::prelude::*;
use burn::record::Recorder;
use dataset::contract::rng::keyed_u64;
use dataset::contract::schema::Split;

use crate::data::{EpochStream, InputNormalisation, SampleSource, StreamConfig};
use crate::data_parallel::Ranks;
use crate::fit_config::FitConfig;
use crate::kernels::TrainBackend;
use crate::model::UNet;
use crate::renderer_layer::HostTerms;
use crate::run_dir::{
    append_jsonl, save_last, save_model, Checkpoint, Cursor, EpochMetrics, Rec, ValMetrics,
};

use super::loss::{train_loss_with_terms, validate};
use super::FitOutcome;

/// Give the rank its optimiser (its saved state when resuming) and train.
pub(super) fn launch<B: TrainBackend, O: FitOptimizer<B>>(
    run: RunContext,
    state: ReplicaState<B, ()>,
    optim: O,
    resume: bool,
    device: &B::Device,
    ranks: &Ranks,
) -> Result<FitOutcome> {
    let optim = if resume {
        let last = run.out.join("last");
        optim.load_record(
            Rec::new()
                .load(last.join("optim"), device)
                .with_context(|| format!("{}: cannot load the optimizer state", last.display()))?,
        )
    } else {
        optim
    };
    let state = ReplicaState {
        net: state.net,
        optim,
        cursor: state.cursor,
        history: state.history,
        average: state.average,
    };
    train_rank::<B, O>(&run, state, ranks, device)
}

/// What a fit steps with: Adam, or AdamW for a run with weight decay.
pub(super) trait FitOptimizer<B: TrainBackend>:
    Optimizer<UNet<B>, B> + Clone + Send + 'static
{
}
impl<B: TrainBackend, O: Optimizer<UNet<B>, B> + Clone + Send + 'static> FitOptimizer<B> for O {}

/// What every replica of a fit shares.
pub(super) struct RunContext {
    pub(super) source: Arc<dyn SampleSource>,
    pub(super) config: FitConfig,
    pub(super) out: std::path::PathBuf,
    pub(super) input: InputNormalisation,
    pub(super) row_weights: Option<Arc<[f64]>>,
    pub(super) stop_after_steps: Option<u64>,
    pub(super) show_progress: bool,
    pub(super) trainable: usize,
}

/// What each replica starts from: the same network, optimiser state and cursor on every one.
#[derive(Clone)]
pub(super) struct ReplicaState<B: TrainBackend, O> {
    pub(super) net: UNet<B>,
    pub(super) optim: O,
    pub(super) cursor: Cursor,
    pub(super) history: Vec<EpochMetrics>,
    pub(super) average: Option<UNet<B::InnerBackend>>,
}

/// One rank's epochs (the whole fit when it is the only one).
fn train_rank<B: TrainBackend, O: FitOptimizer<B>>(
    run: &RunContext,
    state: ReplicaState<B, O>,
    ranks: &Ranks,
    device: &B::Device,
) -> Result<FitOutcome> {
    let replica = ranks.replica();
    let RunContext {
        source,
        config,
        out,
        input,
        row_weights,
        stop_after_steps,
        show_progress,
        trainable,
    } = run;
    let (out, input, stop_after_steps, trainable) =
        (out.as_path(), *input, *stop_after_steps, *trainable);
    let show_progress = *show_progress && replica.leads();
    let ReplicaState {
        mut net,
        mut optim,
        mut cursor,
        mut history,
        mut average,
    } = state;
    let recorder = Rec::new();
    let seed = config.stream.seed;
    let last = out.join("last");
    // Time in optimiser steps only (not data waits, validation or checkpoints), for s/step figures.
    let mut step_time = StepTime::default();
    // The run's steps: a bar on a terminal, structured lines naming the rank in a scheduler's log file.
    let progress = if show_progress {
        let context = format!("rank={} world={}", replica.rank, replica.world);
        dataset::progress::Progress::start_in("fit", "steps", 0, &context)
    } else {
        dataset::progress::Progress::hidden()
    };
    progress.resume_at(cursor.step);
    while cursor.epoch < config.epochs {
        let epoch = cursor.epoch;
        let model = config.model;
        let stream = EpochStream::start(
            source.clone(),
            Split::Train,
            // Each replica takes its share of every step's crops.
            StreamConfig {
                batch_size: config.stream.batch_size / replica.world,
                ..config.stream
            },
            input,
            row_weights.clone(),
            epoch as u64,
            cursor.next_batch,
            replica,
            move |batch| {
                let terms = HostTerms::evaluate_serial(&batch, model);
                (batch, terms)
            },
        )?;
        let stream_batches = stream.batches;
        // Every epoch has the same batch count, so the run's length is known from the first stream.
        let total_steps = (config.epochs * stream_batches) as u64;
        progress.set_length(total_steps);
        for prepared in stream {
            let (batch, terms) = prepared?;
            // Dropout masks from (seed, step, rank): a resumed run draws exactly what an uninterrupted one would,
            // and each rank its own masks (rank 0 the masks of a one-rank run).
            B::seed(
                device,
                keyed_u64(seed, "dropout", cursor.step) ^ replica.rank as u64,
            );
            let step_started = Instant::now();
            let loss = train_loss_with_terms(&net, &batch, &terms, device);
            let loss_value: f64 = loss
                .clone()
                .into_data()
                .convert::<f64>()
                .to_vec::<f64>()
                .expect("f64")[0];
            // Every replica checks (and the lead logs) the mean over the replicas, so all stop together.
            let loss_value = ranks.mean_scalar(loss_value, "loss", cursor.step);
            if !loss_value.is_finite() {
                bail!(
                    "non-finite training loss at step {} (epoch {epoch}); lower --lr",
                    cursor.step
                );
            }
            let grads = ranks.mean_gradients(
                &net,
                GradientsParams::from_grads(loss.backward(), &net),
                cursor.step,
            )?;
            let rate = config
                .lr_schedule
                .rate(config.learning_rate, cursor.step, total_steps);
            net = optim.step(rate, net, grads);
            if let (Some(decay), Some(avg)) = (config.ema_decay, average.take()) {
                average = Some(crate::weight_average::ema_update(
                    avg,
                    &net.valid(),
                    crate::weight_average::ema_decay_at(decay, cursor.step),
                ));
            }
            step_time.add(step_started);
            cursor.step += 1;
            cursor.next_batch += 1;
            cursor.epoch_loss_sum += loss_value;
            cursor.epoch_batches += 1;
            progress.inc(1);
            let epoch_loss = cursor.epoch_loss_sum / cursor.epoch_batches as f64;
            progress.set_message(format!(
                "epoch {}/{} loss {epoch_loss:.3e}",
                epoch + 1,
                config.epochs
            ));
            if stop_after_steps.is_some_and(|s| cursor.step >= s) {
                let (net, average) = mean_running_stats(ranks, net, average, cursor.step);
                if replica.leads() {
                    save_last(&net, &optim, average.as_ref(), &cursor, &last, &recorder)?;
                }
                progress.set_message(format!("stopped at step {} (resumable)", cursor.step));
                ranks.barrier(EPOCH_END, cursor.step);
                return Ok(outcome(cursor, history, trainable, step_time));
            }
        }
        // Every rank's BatchNorm statistics averaged before validation; the lead alone validates and writes,
        // while the others wait for it.
        (net, average) = mean_running_stats(ranks, net, average, cursor.step);
        if !replica.leads() {
            cursor.next_epoch();
            ranks.barrier(EPOCH_END, cursor.step);
            continue;
        }
        let validate_net = |network: &UNet<B::InnerBackend>| {
            validate(
                network,
                config.model,
                &input,
                source.as_ref(),
                config.max_val_samples,
                config.stream.batch_size,
                device,
            )
        };
        let val = validate_net(&net.valid())?;
        let ema_val = average.as_ref().map(validate_net).transpose()?;
        let metrics = EpochMetrics {
            epoch,
            steps: cursor.step,
            train_loss: cursor.epoch_loss_sum / cursor.epoch_batches.max(1) as f64,
            val_loss: val.pixel_mse_pooled,
            val_pixel_mse: val.pixel_mse,
            val_psnr_db: val.psnr_db,
            val_ssim: val.ssim,
            val_images: val.images,
            ema_val: ema_val.as_ref().map(ValMetrics::from),
        };
        tracing::info!(?metrics, "epoch done");
        append_jsonl(&out.join("metrics.jsonl"), &metrics)?;
        history.push(metrics.clone());
        if cursor
            .best_val_loss
            .is_none_or(|b| val.pixel_mse_pooled < b)
        {
            cursor.best_val_loss = Some(val.pixel_mse_pooled);
            save_model(&net, &Checkpoint::Best.path(out), &recorder)?;
        }
        if let (Some(avg), Some(val)) = (&average, &ema_val) {
            if cursor
                .best_ema_val_loss
                .is_none_or(|b| val.pixel_mse_pooled < b)
            {
                cursor.best_ema_val_loss = Some(val.pixel_mse_pooled);
                save_model(avg, &Checkpoint::EmaBest.path(out), &recorder)?;
            }
        }
        cursor.next_epoch();
        save_last(&net, &optim, average.as_ref(), &cursor, &last, &recorder)?;
        ranks.barrier(EPOCH_END, cursor.step);
    }
    progress.finish();
    Ok(outcome(cursor, history, trainable, step_time))
}

/// The collective at which the other ranks wait for the lead's validation and checkpoint.
const EPOCH_END: &str = "epoch end (the lead validates and writes)";

/// The network's and the weight average's BatchNorm statistics averaged over the ranks (unchanged alone).
fn mean_running_stats<B: TrainBackend>(
    ranks: &Ranks,
    net: UNet<B>,
    average: Option<UNet<B::InnerBackend>>,
    step: u64,
) -> (UNet<B>, Option<UNet<B::InnerBackend>>) {
    if ranks.world() == 1 {
        return (net, average);
    }
    // Taking a record folds the last update into the statistics (Burn holds it apart until then).
    let _ = net.clone().into_record();
    let _ = average.clone().map(Module::into_record);
    let net = ranks.mean_running_stats(net, step);
    let average = average.map(|a| ranks.mean_running_stats(a, step));
    (net, average)
}

#[derive(Default)]
struct StepTime {
    seconds: f64,
    steps: u64,
}

impl StepTime {
    fn add(&mut self, started: Instant) {
        self.seconds += started.elapsed().as_secs_f64();
        self.steps += 1;
    }
}

fn outcome(
    cursor: Cursor,
    history: Vec<EpochMetrics>,
    trainable: usize,
    time: StepTime,
) -> FitOutcome {
    FitOutcome {
        cursor,
        history,
        trainable_params: trainable,
        seconds_per_step: time.seconds / time.steps.max(1) as f64,
    }
}

//! The fit loop on a tiny published dataset of synthetic samples (written with the real shard writer and
//! manifest): overfitting a handful of samples takes the loss ≥ 10× below the uniform fit it starts at, a run
//! stopped mid-epoch and resumed ends with the same network as an uninterrupted one, and a checkpoint for another
//! BRDF model is refused.

use std::path::Path;
use std::sync::Arc;

use burn::backend::{Autodiff, Flex};
use burn::module::Module;
use burn::record::{FullPrecisionSettings, NamedMpkFileRecorder};
use dataset::contract::schema::CROP_PX;
use dataset::science::brdf::{inverse_leaky_relu, BrdfModel};
use train::data::{HostBatch, InputNormalisation, LocalSource, SampleSource, StreamConfig};
use train::data_parallel::Replica;
use train::fit_config::FitConfig;
use train::model::UNetConfig;
use train::prediction::predict_images;
use train::renderer_layer::reference_render;
use train::testing::synthetic_samples;
use train::training::fit;

type Ad = Autodiff<Flex>;

/// Flex's RNG (weight init, dropout) is process-global: tests that train must not interleave.
static SERIAL: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn config(
    model: BrdfModel,
    epochs: usize,
    lr: f64,
    max_samples: usize,
    dropout: bool,
) -> FitConfig {
    FitConfig {
        version: train::fit_config::FIT_CONFIG_VERSION,
        model,
        epochs,
        learning_rate: lr,
        base_width: 4,
        dropout,
        stream: StreamConfig {
            seed: 3,
            batch_size: 4,
            window_groups: 2,
            augment: true,
            max_samples: Some(max_samples),
        },
        max_val_samples: Some(4),
        lr_schedule: train::fit_config::LrSchedule::Constant,
        elevation_input: false,
        context_input: false,
        ema_decay: None,
        steep_weight: 1.0,
        head_hidden: 0,
        crop_level: false,
        film: false,
        nonnegative_start: false,
        log_coefficients: false,
        weight_decay: None,
        also_train_on: Vec::new(),
        also_validate_on: Vec::new(),
        context_absolute: false,
        crater_input: false,
        crater_frame_input: false,
        crater_relief_input: false,
        unit_input: false,
    }
}

/// A uniform head (zero weights, the fit as bias) makes every pixel's raw parameters that bias, so step 0 renders
/// exactly the uniform model (checked against the scalar reference, negative coefficients included).
#[test]
fn a_head_bias_renders_the_uniform_model_before_any_step() {
    let device = Default::default();
    let relief =
        HostBatch::from_samples(&synthetic_samples(2, 11), &InputNormalisation::relief(20.0));
    let with_elevation = HostBatch::from_samples(
        &synthetic_samples(2, 11),
        &InputNormalisation {
            elevation: Some(train::data::ElevationNormalisation {
                mean_m: 10.0,
                std_m: 30.0,
            }),
            ..InputNormalisation::relief(20.0)
        },
    );
    let npx = CROP_PX * CROP_PX;
    // H1 also with a hidden layer before the head and with the crop-level branch: a zero head ignores the one,
    // a zeroed branch adds nothing, whatever they compute.
    for (model, head_hidden, crop_level) in [
        (BrdfModel::M2, 0, false),
        (BrdfModel::L3, 0, false),
        (BrdfModel::H1, 0, false),
        (BrdfModel::H1, 6, false),
        (BrdfModel::H1, 6, true),
    ] {
        let batch = if crop_level { &with_elevation } else { &relief };
        let coefficients: Vec<f64> = (0..model.param_count())
            .map(|k| 0.9 - 0.45 * k as f64)
            .collect();
        let raw: Vec<f64> = coefficients
            .iter()
            .map(|&c| inverse_leaky_relu(c))
            .collect();
        let net = UNetConfig::new(model.param_count())
            .with_base_width(4)
            .with_head_hidden(head_hidden)
            .with_crop_level(crop_level)
            .with_in_channels(batch.input_channels)
            .init::<Flex>(&device)
            .with_uniform_head(&raw, &device);
        let got = predict_images(&net, model, batch, &device);
        let planar: Vec<f64> = (0..batch.len())
            .flat_map(|_| raw.iter().flat_map(|&r| std::iter::repeat_n(r, npx)))
            .collect();
        let want = reference_render(model, batch, &planar);
        let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(scale > 0.0);
        let worst = got
            .iter()
            .zip(&want)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(worst <= 1e-5 * scale, "{model:?}: {worst:e} of {scale:e}");
    }
}

/// Every run starts at the model's uniform least-squares fit, which on these four samples (the calibration's
/// crops too) is the best any spatially constant parameter set can do: the first step's loss is that floor. The
/// truth varies in space, so a network that learns must go far below it: a tenth within 120 steps (measured
/// 1.56e-4 → 7.8e-6, 20×; 11× at step 100).
#[test]
fn overfitting_a_handful_of_samples_drops_the_loss_tenfold_below_the_uniform_fit() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    train::testing::write_synthetic_dataset(
        tmp.path(),
        synthetic_samples(4, 1),
        synthetic_samples(4, 2),
    );
    let source: Arc<dyn SampleSource> = Arc::new(LocalSource::open(tmp.path()).unwrap());
    let mut cfg = config(BrdfModel::M2, 120, 1e-2, 4, false);
    cfg.stream.augment = false;
    let out = fit::<Ad>(
        source,
        &cfg,
        &tmp.path().join("run"),
        false,
        None,
        &Default::default(),
        false,
    )
    .unwrap();
    let first = out.history.first().unwrap().train_loss;
    let best = out
        .history
        .iter()
        .map(|m| m.train_loss)
        .fold(f64::INFINITY, f64::min);
    assert!(
        best * 10.0 <= first,
        "train loss {first:e} -> best {best:e} in {} steps",
        out.cursor.step
    );
    eprintln!(
        "overfit: train loss {first:e} -> best {best:e} ({:.1}x) in {} steps",
        first / best,
        out.cursor.step
    );
    assert_eq!(out.history.len(), 120);
    assert!(
        tmp.path().join("run/best/model.mpk").exists()
            && tmp.path().join("run/metrics.jsonl").exists()
    );
}

/// `nonnegative_start` starts the head at the non-negative least-squares fit, not the unconstrained one: a run
/// stopped after one step at a vanishing rate still renders the non-negative coefficients everywhere (the first
/// model, of H3, L3 and M2, whose unconstrained fit on these crops has a negative coefficient, so the two starts
/// differ).
#[test]
fn a_nonnegative_start_renders_the_nonnegative_uniform_fit() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    train::testing::write_synthetic_dataset(
        tmp.path(),
        synthetic_samples(8, 1),
        synthetic_samples(4, 2),
    );
    let source: Arc<dyn SampleSource> = Arc::new(LocalSource::open(tmp.path()).unwrap());
    let (model, uniform) = negative_start_model(&*source);
    assert!(uniform.model_uniform_nonnegative.iter().all(|&c| c >= 0.0));

    let mut cfg = config(model, 1, 1e-12, 8, false);
    cfg.nonnegative_start = true;
    cfg.stream.augment = false;
    let run = tmp.path().join("run");
    fit::<Ad>(
        source,
        &cfg,
        &run,
        false,
        Some(1),
        &Default::default(),
        false,
    )
    .unwrap();
    let got = fingerprint(&run, &cfg);

    let input = train::run_dir::run_input(&run, &cfg).unwrap();
    let batch = HostBatch::from_samples(&synthetic_samples(2, 77), &input);
    let npx = CROP_PX * CROP_PX;
    let render = |coefficients: &[f64]| {
        let planar: Vec<f64> = (0..batch.len())
            .flat_map(|_| {
                coefficients
                    .iter()
                    .flat_map(|&c| std::iter::repeat_n(inverse_leaky_relu(c), npx))
            })
            .collect();
        reference_render(model, &batch, &planar)
    };
    let worst = |want: &[f64]| worst_relative(&got, want);
    let nonnegative = worst(&render(&uniform.model_uniform_nonnegative));
    let unconstrained = worst(&render(&uniform.model_uniform));
    eprintln!(
        "{model:?} start {:?} (unconstrained {:?}): {nonnegative:e} from the non-negative render, \
         {unconstrained:e} from the unconstrained one",
        uniform.model_uniform_nonnegative, uniform.model_uniform
    );
    assert!(
        nonnegative <= 1e-5,
        "{model:?}: {nonnegative:e} from the non-negative fit"
    );
    assert!(
        unconstrained > 1e-3,
        "{model:?}: the two starts render alike ({unconstrained:e})"
    );
}

/// `log_coefficients` starts the head at the logarithm of the uniform fit: an H1 run stopped after one step at a
/// vanishing rate still renders H1's uniform coefficient everywhere. A model whose unconstrained fit has a
/// coefficient below 0 is refused with the flag named, before anything is written.
#[test]
fn log_coefficients_start_at_the_uniform_fit_and_refuse_a_negative_one() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    train::testing::write_synthetic_dataset(
        tmp.path(),
        synthetic_samples(8, 1),
        synthetic_samples(4, 2),
    );
    let source: Arc<dyn SampleSource> = Arc::new(LocalSource::open(tmp.path()).unwrap());
    let uniform = train::uniform_fit::calibrate(
        &*source,
        train::training::UNIFORM_INIT_SAMPLES,
        BrdfModel::H1,
    )
    .unwrap();
    assert!(uniform.model_uniform[0] > 0.0);

    let mut cfg = config(BrdfModel::H1, 1, 1e-12, 8, false);
    cfg.log_coefficients = true;
    cfg.stream.augment = false;
    let run = tmp.path().join("run");
    fit::<Ad>(
        source.clone(),
        &cfg,
        &run,
        false,
        Some(1),
        &Default::default(),
        false,
    )
    .unwrap();
    let got = fingerprint(&run, &cfg);
    let input = train::run_dir::run_input(&run, &cfg).unwrap();
    let batch = HostBatch::from_samples(&synthetic_samples(2, 77), &input);
    let planar: Vec<f64> = (0..batch.len() * CROP_PX * CROP_PX)
        .map(|_| inverse_leaky_relu(uniform.model_uniform[0]))
        .collect();
    let worst = worst_relative(&got, &reference_render(BrdfModel::H1, &batch, &planar));
    assert!(
        worst <= 1e-5,
        "{worst:e} from the uniform H1 render (tolerance 1e-5)"
    );

    let (model, _) = negative_start_model(&*source);
    let mut cfg = config(model, 1, 1e-12, 8, false);
    cfg.log_coefficients = true;
    let refused = tmp.path().join("refused");
    let err = fit::<Ad>(
        source,
        &cfg,
        &refused,
        false,
        Some(1),
        &Default::default(),
        false,
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("--log-coefficients"), "{err}");
    assert!(
        !refused.join("last").exists(),
        "a refused run wrote a checkpoint"
    );
}

/// The first of H3, L3 and M2 whose unconstrained uniform fit on `source` has a coefficient below 0, with its fit.
fn negative_start_model(source: &dyn SampleSource) -> (BrdfModel, train::uniform_fit::Calibration) {
    [BrdfModel::H3, BrdfModel::L3, BrdfModel::M2]
        .into_iter()
        .map(|m| {
            let fit =
                train::uniform_fit::calibrate(source, train::training::UNIFORM_INIT_SAMPLES, m)
                    .unwrap();
            (m, fit)
        })
        .find(|(_, fit)| fit.model_uniform.iter().any(|&c| c < 0.0))
        .expect("no candidate's unconstrained fit is negative on these crops")
}

/// The largest absolute difference between two renders, over the largest magnitude of `want`.
fn worst_relative(got: &[f64], want: &[f64]) -> f64 {
    let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    got.iter()
        .zip(want)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max)
        / scale
}

/// The network's inference output on fixed samples: weights and BatchNorm running stats in one vector.
fn fingerprint(run: &Path, cfg: &FitConfig) -> Vec<f64> {
    fingerprint_of(run, "last/model", cfg)
}

/// The network saved at `checkpoint` (relative to the run, without extension).
fn load_checkpoint(run: &Path, checkpoint: &str, cfg: &FitConfig) -> train::model::UNet<Flex> {
    let device = Default::default();
    cfg.net_config()
        .init::<Flex>(&device)
        .load_file(
            run.join(checkpoint),
            &NamedMpkFileRecorder::<FullPrecisionSettings>::new(),
            &device,
        )
        .unwrap()
}

/// [`fingerprint`] of the checkpoint at `checkpoint` (relative to the run, without extension).
fn fingerprint_of(run: &Path, checkpoint: &str, cfg: &FitConfig) -> Vec<f64> {
    let device = Default::default();
    let net = load_checkpoint(run, checkpoint, cfg);
    let input = train::run_dir::run_input(run, cfg).unwrap();
    predict_images(
        &net,
        cfg.model,
        &HostBatch::from_samples(&synthetic_samples(2, 77), &input),
        &device,
    )
}

#[test]
fn stopping_and_resuming_gives_the_same_network_as_an_uninterrupted_run() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    // 300 train rows = 2 row groups (256 + 44), so the window shuffle spans groups; 12 per epoch.
    train::testing::write_synthetic_dataset(
        tmp.path(),
        synthetic_samples(300, 5),
        synthetic_samples(4, 6),
    );
    let source: Arc<dyn SampleSource> = Arc::new(LocalSource::open(tmp.path()).unwrap());
    // Cosine schedule: the resumed half must continue the decay from the saved step, not restart it. With the
    // elevation plane and the context input (its crater planes as a frame: the synthetic samples lie 0.25 radii
    // apart, so some are framed and some past the reach, and their craters' relief; and the unit map's planes), the resumed half must feed the network what the first
    // half did; the hidden layer before the head must be checkpointed with the rest.
    let cfg = FitConfig {
        lr_schedule: train::fit_config::LrSchedule::Cosine,
        elevation_input: true,
        context_input: true,
        ema_decay: Some(0.9),
        steep_weight: 1.0,
        head_hidden: 6,
        crop_level: true,
        film: false,
        nonnegative_start: false,
        log_coefficients: false,
        context_absolute: false,
        crater_input: true,
        crater_frame_input: true,
        crater_relief_input: true,
        unit_input: true,
        ..config(BrdfModel::M2, 2, 1e-3, 12, true)
    };
    let device = Default::default();
    let straight = tmp.path().join("straight");
    let a = fit::<Ad>(source.clone(), &cfg, &straight, false, None, &device, false).unwrap();
    assert_eq!(a.cursor.step, 6);
    let input = train::run_dir::load_normalisation(&straight).unwrap().input;
    assert!(
        input.crater_frame_input()
            && input.crater_relief().is_some()
            && input.units()
            && input.context_channels() == train::data::CONTEXT_CHANNELS + 6
    );
    let split = tmp.path().join("split");
    // Stop mid-epoch (step 4 of 6 is batch 1 of epoch 1), then resume to the end.
    let b1 = fit::<Ad>(source.clone(), &cfg, &split, false, Some(4), &device, false).unwrap();
    assert_eq!((b1.cursor.epoch, b1.cursor.next_batch), (1, 1));
    let b2 = fit::<Ad>(source.clone(), &cfg, &split, true, None, &device, false).unwrap();
    assert_eq!(b2.cursor.step, 6);
    assert_eq!(
        a.history.last(),
        b2.history.last(),
        "same last-epoch metrics, computed live in both"
    );
    // Byte-equal metrics files: serde_json prints f64 exactly (shortest round trip), so this is bit equality.
    let metrics = |run: &Path| std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    assert_eq!(metrics(&straight), metrics(&split));
    assert_eq!(fingerprint(&straight, &cfg), fingerprint(&split, &cfg));
    // The weight average resumes too (its state is last/ema), and it is a network of its own: validated beside
    // the raw one every epoch, different from it, and what eval and infer load by default.
    let ema = |run: &Path| fingerprint_of(run, "last/ema", &cfg);
    assert_eq!(ema(&straight), ema(&split));
    assert_ne!(ema(&straight), fingerprint(&straight, &cfg));
    assert!(a.history.iter().all(|m| m.ema_val.is_some()));
    let auto =
        train::run_dir::load_trained::<Flex>(&straight, train::run_dir::Checkpoint::Auto, &device)
            .unwrap();
    assert_eq!(auto.checkpoint, "last/ema.mpk");

    // Resuming with another BRDF model is refused with the fix in the message.
    let other = FitConfig {
        model: BrdfModel::M3,
        ..cfg.clone()
    };
    let err = fit::<Ad>(source, &other, &split, true, None, &device, false)
        .unwrap_err()
        .to_string();
    assert!(err.contains("m2") && err.contains("--model"), "{err}");
}

/// Every float in a checkpoint, split into the trained weights and the BatchNorm running statistics (which the
/// forward pass updates and no optimiser touches), in visiting order.
fn weights_and_running_stats(run: &Path, cfg: &FitConfig) -> (Vec<f32>, Vec<f32>) {
    struct Collect {
        path: Vec<String>,
        weights: Vec<f32>,
        running: Vec<f32>,
    }
    impl burn::module::ModuleVisitor<Flex> for Collect {
        fn enter_module(&mut self, name: &str, _container: &str) {
            self.path.push(name.to_string());
        }
        fn exit_module(&mut self, _name: &str, _container: &str) {
            self.path.pop();
        }
        fn visit_float<const D: usize>(
            &mut self,
            param: &burn::module::Param<burn::tensor::Tensor<Flex, D>>,
        ) {
            let values = param.val().into_data().to_vec::<f32>().unwrap();
            if self.path.last().is_some_and(|n| n.starts_with("running_")) {
                self.running.extend(values);
            } else {
                self.weights.extend(values);
            }
        }
    }
    let net = load_checkpoint(run, "last/model", cfg);
    let mut collect = Collect {
        path: Vec::new(),
        weights: Vec::new(),
        running: Vec::new(),
    };
    net.visit(&mut collect);
    (collect.weights, collect.running)
}

/// `weight_decay` steps with AdamW: from the same start and batch, one step shrinks every weight by
/// (learning rate × decay) × its starting value more than Adam's step does, and leaves the running statistics
/// alone (Adam's update equals AdamW's without the decay, up to rounding: the same bias-corrected moments). With a
/// rate of 1e-6 the start differs from Adam's result by at most about 1e-6, so that result stands in for it.
/// A run with decay also resumes exactly: the AdamW state is checkpointed and loaded like Adam's.
#[test]
fn weight_decay_shrinks_each_weight_by_rate_times_decay_and_resumes_exactly() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    train::testing::write_synthetic_dataset(
        tmp.path(),
        synthetic_samples(40, 5),
        synthetic_samples(4, 6),
    );
    let source: Arc<dyn SampleSource> = Arc::new(LocalSource::open(tmp.path()).unwrap());
    let device = Default::default();
    let (rate, decay) = (1e-6, 1e5);
    let adam = config(BrdfModel::M2, 1, rate, 8, true);
    let adamw = FitConfig {
        weight_decay: Some(decay),
        ..adam.clone()
    };
    let one_step = |cfg: &FitConfig, name: &str| {
        let run = tmp.path().join(name);
        fit::<Ad>(source.clone(), cfg, &run, false, Some(1), &device, false).unwrap();
        weights_and_running_stats(&run, cfg)
    };
    let (plain, plain_running) = one_step(&adam, "adam");
    let (decayed, decayed_running) = one_step(&adamw, "adamw");
    assert!(!plain_running.is_empty() && plain_running == decayed_running);
    assert_eq!(plain.len(), decayed.len());
    let shrink = rate * decay; // 0.1 of each weight
    let mut worst = 0.0f64;
    for (&p, &d) in plain.iter().zip(&decayed) {
        let (p, d) = (f64::from(p), f64::from(d));
        let miss = ((p - d) - shrink * p).abs();
        assert!(
            miss <= 2e-6 + 1e-6 * p.abs(),
            "Adam {p} AdamW {d}: shrank by {} not {}",
            p - d,
            shrink * p
        );
        worst = worst.max(miss);
    }
    assert!(plain.iter().filter(|w| w.abs() > 1e-3).count() > plain.len() / 2);
    eprintln!(
        "weight decay: {} weights, worst miss {worst:e}",
        plain.len()
    );

    // Resumed mid-run, a run with decay ends where an uninterrupted one does.
    let cfg = FitConfig {
        epochs: 2,
        learning_rate: 1e-3,
        weight_decay: Some(0.5),
        ..adam
    };
    let straight = tmp.path().join("straight");
    fit::<Ad>(source.clone(), &cfg, &straight, false, None, &device, false).unwrap();
    let split = tmp.path().join("split");
    fit::<Ad>(source.clone(), &cfg, &split, false, Some(3), &device, false).unwrap();
    let resumed = fit::<Ad>(source.clone(), &cfg, &split, true, None, &device, false).unwrap();
    assert_eq!(resumed.cursor.step, 4);
    assert_eq!(
        weights_and_running_stats(&straight, &cfg),
        weights_and_running_stats(&split, &cfg)
    );
}

/// `--run` and `--ensemble` load together before any work: a missing member is named, and for parameter-map
/// averaging (`infer`) a member of another BRDF model is refused naming both runs, while rendering averages
/// (`eval`) accept the mix.
#[test]
fn an_ensemble_loads_every_member_first_and_map_averaging_refuses_mixed_models() {
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    train::testing::write_synthetic_dataset(
        tmp.path(),
        synthetic_samples(8, 21),
        synthetic_samples(4, 22),
    );
    let source: Arc<dyn SampleSource> = Arc::new(LocalSource::open(tmp.path()).unwrap());
    let device = Default::default();
    let m2 = tmp.path().join("run-m2");
    let l3 = tmp.path().join("run-l3");
    let m2_again = tmp.path().join("run-m2-again");
    for (model, out) in [
        (BrdfModel::M2, &m2),
        (BrdfModel::L3, &l3),
        (BrdfModel::M2, &m2_again),
    ] {
        fit::<Ad>(
            source.clone(),
            &config(model, 1, 1e-3, 4, false),
            out,
            false,
            Some(1),
            &device,
            false,
        )
        .unwrap();
    }
    let missing = tmp.path().join("no-such-run");
    let load = |runs: &[&Path], one_model| {
        train::run_dir::load_ensemble::<Flex>(
            runs,
            train::run_dir::Checkpoint::Auto,
            one_model,
            &Default::default(),
        )
    };

    let same = load(&[&m2, &m2_again], true).unwrap();
    assert_eq!(same.len(), 2);
    let mixed = load(&[&m2, &l3], false).unwrap();
    assert_eq!(
        (mixed[0].config.model, mixed[1].config.model),
        (BrdfModel::M2, BrdfModel::L3)
    );

    let err = format!(
        "{:#}",
        load(&[&m2, &l3], true).err().expect("mixed refused")
    );
    assert!(
        err.contains("run-l3")
            && err.contains("run-m2")
            && err.contains("l3")
            && err.contains("m2"),
        "{err}"
    );
    let err = format!(
        "{:#}",
        load(&[&m2, &missing], true).err().expect("missing refused")
    );
    assert!(
        err.contains("no-such-run") && err.contains("config.json"),
        "{err}"
    );
    // These runs stopped before any validation and kept no weight average: auto falls back to last/, and asking
    // for the average names the flag that makes one.
    assert_eq!(same[0].checkpoint, "last/model.mpk");
    let err = format!(
        "{:#}",
        train::run_dir::load_trained::<Flex>(&m2, train::run_dir::Checkpoint::EmaBest, &device)
            .err()
            .expect("no average kept")
    );
    assert!(err.contains("ema-best") && err.contains("--ema"), "{err}");
}

/// `--steep-weight`: every crop's weight comes from its delivered DEM's mean slope, and a capped epoch draws the
/// steep crops in proportion (a 30° plane among flat crops, weight 5: about 55 % of each epoch against the 25 % a
/// uniform draw gives), the same rows whenever the epoch is streamed again.
#[test]
fn steep_weighted_epochs_draw_steep_crops_in_proportion_to_their_weight() {
    use dataset::contract::schema::{Split, DEM_PX};
    use train::data::{steep_row_weights, EpochStream};
    let dir = tempfile::tempdir().unwrap();
    let mut train_samples = synthetic_samples(40, 11);
    let tan30 = 30f64.to_radians().tan();
    for (i, s) in train_samples.iter_mut().enumerate() {
        let gsd = s.gsd_m;
        s.dem_m = (0..DEM_PX * DEM_PX)
            .map(|k| {
                if i % 4 == 0 {
                    -1200.0 + ((k % DEM_PX) as f64 * gsd * tan30) as f32
                } else {
                    -1200.0
                }
            })
            .collect();
    }
    let steep_ids: Vec<String> = train_samples
        .iter()
        .step_by(4)
        .map(|s| s.sample_id.clone())
        .collect();
    train::testing::write_synthetic_dataset(dir.path(), train_samples, synthetic_samples(4, 12));
    let source: Arc<dyn SampleSource> = Arc::new(LocalSource::open(dir.path()).unwrap());
    let weights = steep_row_weights(&*source, Split::Train, 5.0).unwrap();
    assert_eq!(weights.len(), 40);
    // One row group, in file order: every fourth crop is the steep one.
    for (i, w) in weights.iter().enumerate() {
        assert_eq!(*w, if i % 4 == 0 { 5.0 } else { 1.0 }, "row {i}");
    }
    let weights: Arc<[f64]> = weights.into();
    let stream = StreamConfig {
        seed: 3,
        batch_size: 4,
        window_groups: 1,
        augment: false,
        max_samples: Some(10),
    };
    let input = InputNormalisation::relief(20.0);
    let ids_of = |epoch: u64| -> Vec<String> {
        EpochStream::start(
            source.clone(),
            Split::Train,
            stream,
            input,
            Some(weights.clone()),
            epoch,
            0,
            Replica::SOLE,
            std::convert::identity,
        )
        .unwrap()
        .flat_map(|b| b.unwrap().sample_ids)
        .collect()
    };
    let epochs = 40;
    let mut steep_drawn = 0;
    for epoch in 0..epochs {
        let ids = ids_of(epoch);
        assert_eq!(ids.len(), 10);
        let mut distinct = ids.clone();
        distinct.sort();
        distinct.dedup();
        assert_eq!(distinct.len(), 10, "without replacement");
        steep_drawn += ids.iter().filter(|id| steep_ids.contains(id)).count();
    }
    assert_eq!(ids_of(7), ids_of(7), "keyed by (seed, epoch)");
    // Successive sampling with weights 5 and 1 takes about 5.5 of the 10 steep crops per epoch (2.5 uniformly).
    let share = steep_drawn as f64 / (10 * epochs) as f64;
    assert!((0.45..0.65).contains(&share), "steep share {share}");
    // An uncapped epoch has nothing to weight.
    let uncapped = StreamConfig {
        max_samples: None,
        ..stream
    };
    let err = EpochStream::start(
        source,
        Split::Train,
        uncapped,
        input,
        Some(weights),
        0,
        0,
        Replica::SOLE,
        std::convert::identity,
    )
    .err()
    .expect("refused")
    .to_string();
    assert!(err.contains("--max-train-samples"), "{err}");
}

/// `fit --also-train-on`: a pool of two publications trains exactly as one publication holding both train
/// splits, shard after shard (the same row groups in the same order give the same epoch plan, batches and
/// steps), while its validation split is the first publication's alone. Its train rows read back as each member
/// holds them, and a dataset pooled twice is refused. A member pooled for validation only (`--also-validate-on`)
/// adds its validation split and nothing to train on.
#[test]
fn a_pool_of_publications_trains_as_one_holding_both_train_splits() {
    use dataset::contract::schema::{Sample, Split};
    use train::data::{for_each_sample_group, PooledSource};
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    let with_split = |mut samples: Vec<Sample>, split: Split| {
        samples.iter_mut().for_each(|s| s.split = split);
        samples
    };
    let (first_train, more_train) = (
        with_split(synthetic_samples(12, 5), Split::Train),
        with_split(synthetic_samples(10, 7), Split::Train),
    );
    let (first_val, more_val) = (
        with_split(synthetic_samples(4, 6), Split::Val),
        with_split(synthetic_samples(3, 8), Split::Val),
    );
    let publish = |name: &str, splits: &[(&str, Vec<Vec<Sample>>)]| {
        let dir = tmp.path().join(name);
        dataset::testing::write_dataset(&dir, name, splits, serde_json::Value::Null).unwrap();
        Arc::new(LocalSource::open(&dir).unwrap()) as Arc<dyn SampleSource>
    };
    let first = publish(
        "first",
        &[
            ("train", vec![first_train.clone()]),
            ("val", vec![first_val.clone()]),
        ],
    );
    let more = publish(
        "more",
        &[
            ("train", vec![more_train.clone()]),
            ("val", vec![more_val.clone()]),
        ],
    );
    let both = publish(
        "both",
        &[
            ("train", vec![first_train.clone(), more_train.clone()]),
            ("val", vec![first_val.clone()]),
        ],
    );
    let pool: Arc<dyn SampleSource> =
        Arc::new(PooledSource::new(first.clone(), vec![more.clone()]).unwrap());

    let rows = |source: &dyn SampleSource, split: Split| {
        let mut rows = Vec::new();
        for_each_sample_group(source, split, None, "rows", |group| {
            rows.extend(group.iter().map(|s| s.dem_m.clone()))
        })
        .unwrap();
        rows
    };
    let expected: Vec<_> = first_train
        .iter()
        .chain(&more_train)
        .map(|s| s.dem_m.clone())
        .collect();
    assert_eq!(rows(&*pool, Split::Train), expected);
    assert_eq!(
        rows(&*pool, Split::Val),
        first_val
            .iter()
            .map(|s| s.dem_m.clone())
            .collect::<Vec<_>>()
    );
    let sizes = |source: &dyn SampleSource| -> Vec<usize> {
        source
            .row_groups(Split::Train)
            .unwrap()
            .iter()
            .map(|g| g.rows)
            .collect()
    };
    assert_eq!(sizes(&*pool), sizes(&*both));

    // `--also-validate-on`: a member pooled for validation only adds its validation split, nothing to train.
    let validating = PooledSource::new(first.clone(), Vec::new())
        .unwrap()
        .also_validating_on(vec![more.clone()])
        .unwrap();
    let dems = |samples: &[Sample]| samples.iter().map(|s| s.dem_m.clone()).collect::<Vec<_>>();
    assert_eq!(rows(&validating, Split::Train), dems(&first_train));
    assert_eq!(
        rows(&validating, Split::Val),
        dems(&[first_val.clone(), more_val].concat())
    );
    assert_eq!(
        (validating.further_names(), validating.validation_names()),
        (Vec::<String>::new(), vec!["more".to_string()])
    );

    let err = PooledSource::new(first.clone(), vec![more.clone(), more.clone()])
        .err()
        .unwrap()
        .to_string();
    assert!(
        err.contains("\"more\"") && err.contains("--also-train-on"),
        "{err}"
    );
    assert!(PooledSource::new(first.clone(), vec![more.clone()])
        .unwrap()
        .also_validating_on(vec![more.clone()])
        .is_err());

    let device = Default::default();
    let cfg = config(BrdfModel::M2, 2, 1e-3, 16, false);
    let pooled_cfg = FitConfig {
        also_train_on: vec!["more".into()],
        ..cfg.clone()
    };
    let (on_pool, on_both) = (tmp.path().join("on-pool"), tmp.path().join("on-both"));
    fit::<Ad>(pool, &pooled_cfg, &on_pool, false, None, &device, false).unwrap();
    fit::<Ad>(both, &cfg, &on_both, false, None, &device, false).unwrap();
    assert_eq!(
        fingerprint(&on_pool, &pooled_cfg),
        fingerprint(&on_both, &cfg)
    );
    let saved: FitConfig =
        serde_json::from_str(&std::fs::read_to_string(on_pool.join("config.json")).unwrap())
            .unwrap();
    assert_eq!(saved.also_train_on, ["more"]);
}

/// A fit keeps the range its inputs spanned over the train crops (`input_range.json`); `eval` counts the crops
/// outside it, and with `clamp_crater_relief` feeds each crater's relief at the range's edge, exactly as a
/// dataset that carried the edge value.
#[test]
fn a_run_keeps_its_input_range_and_eval_counts_and_clamps_against_it() {
    use dataset::contract::schema::Split;
    use train::evaluation::{evaluate, EvalOptions};
    let _serial = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = tempfile::tempdir().unwrap();
    // synthetic_samples places sample i at ρ = 0.2 i with relief 0.04 + 0.01 i: framed (ρ < 3) for i < 15.
    let train_samples = synthetic_samples(40, 5);
    // Validation: the first four train crops (so every other input is within range), their reliefs replaced.
    let with_reliefs = |reliefs: [f64; 4]| -> Vec<_> {
        train_samples[..4]
            .iter()
            .zip(reliefs)
            .map(|(s, r)| {
                let mut s = s.clone();
                s.crater.as_mut().unwrap().relief_to_diameter = Some(r);
                s
            })
            .collect()
    };
    let data = tmp.path().join("data");
    train::testing::write_synthetic_dataset(
        &data,
        train_samples.clone(),
        with_reliefs([0.30, 0.01, 0.10, 0.12]),
    );
    let source: Arc<dyn SampleSource> = Arc::new(LocalSource::open(&data).unwrap());
    let cfg = FitConfig {
        context_input: true,
        crater_input: true,
        crater_frame_input: true,
        crater_relief_input: true,
        ..config(BrdfModel::M2, 1, 1e-3, 8, false)
    };
    let device = Default::default();
    let run = tmp.path().join("run");
    fit::<Ad>(source.clone(), &cfg, &run, false, None, &device, false).unwrap();
    let trained =
        train::run_dir::load_trained::<Flex>(&run, train::run_dir::Checkpoint::Auto, &device)
            .unwrap();
    let range = trained
        .input_range
        .clone()
        .expect("fit keeps input_range.json");
    assert_eq!(range.crops, 40);
    let relief = range.inputs["crater_relief_to_diameter"];
    assert_eq!((relief.min, relief.max), (0.04, 0.04 + 0.01 * 14.0));
    let off_dem = range.inputs["context_off_dem"];
    assert_eq!((off_dem.min, off_dem.max), (0.0, 0.0));

    let options = EvalOptions {
        split: Split::Val,
        max_samples: None,
        batch_size: 4,
        calibration_samples: 8,
        panels: 0,
        symmetry_mean: false,
        without_crater_frames: false,
        clamp_crater_relief: false,
    };
    let eval = |source: &dyn SampleSource, clamp: bool| {
        let calibration = train::uniform_fit::calibrate(source, 8, BrdfModel::M2).unwrap();
        let options = EvalOptions {
            clamp_crater_relief: clamp,
            ..options.clone()
        };
        evaluate(
            std::slice::from_ref(&trained),
            source,
            &options,
            calibration,
            None,
            &device,
            |_, _, _| Ok(()),
        )
        .unwrap()
    };
    let learned_sse = |report: &train::evaluation::EvalReport| {
        report
            .methods
            .iter()
            .find(|m| m.name == "learned")
            .unwrap()
            .aggregate
            .sse
    };
    let raw = eval(source.as_ref(), false);
    let counted = raw.inputs_outside_training_range.as_ref().unwrap();
    assert_eq!((counted.crops, counted.outside_any), (4, 2));
    let relief_count = counted.inputs["crater_relief_to_diameter"];
    assert_eq!((relief_count.below, relief_count.above), (1, 1));
    assert_eq!((relief_count.seen.min, relief_count.seen.max), (0.01, 0.30));
    let within: Vec<Option<bool>> = raw
        .per_image
        .iter()
        .map(|i| i.within_training_range)
        .collect();
    assert_eq!(within, [Some(false), Some(false), Some(true), Some(true)]);
    let by_range = raw
        .breakdowns
        .iter()
        .find(|b| b.by == "training_range")
        .unwrap();
    let groups: Vec<(&str, usize)> = by_range
        .groups
        .iter()
        .map(|g| (g.group.as_str(), g.images))
        .collect();
    assert_eq!(groups, [("inputs within", 2), ("an input outside", 2)]);
    // Clamped, the crops render exactly as crops that carried the range's edges.
    let clamped = eval(source.as_ref(), true);
    assert!(clamped.learned_crater_relief_clamped);
    let edges = tmp.path().join("edges");
    train::testing::write_synthetic_dataset(
        &edges,
        train_samples.clone(),
        with_reliefs([relief.max, relief.min, 0.10, 0.12]),
    );
    let at_edges = eval(&LocalSource::open(&edges).unwrap(), false);
    assert_eq!(learned_sse(&clamped), learned_sse(&at_edges));
    assert_ne!(learned_sse(&clamped), learned_sse(&raw));
    // The count is of the site's own inputs, clamped or not.
    assert_eq!(
        clamped.inputs_outside_training_range,
        raw.inputs_outside_training_range
    );

    // A range over other data is refused: it would count the wrong crops as outside.
    let other = tmp.path().join("other");
    train::testing::write_synthetic_dataset(
        &other,
        synthetic_samples(8, 9),
        synthetic_samples(2, 9),
    );
    let other_source = LocalSource::open(&other).unwrap();
    let name = other_source.manifest().name.clone();
    let err = train::run_dir::record_input_range(&run, &other_source, vec![name, "another".into()])
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("trained on") && err.contains("same publications"),
        "{err}"
    );
}

//! Data-parallel fits across MPI ranks ([`train::data_parallel`]), on a tiny published dataset. Needs the `mpi`
//! feature and Open MPI's `mpirun` (CI installs both); `mpirun` runs in a network namespace that has loopback
//! only, and its ranks talk through shared memory ([`support::mpi`]).
//!
//! The expectation is computed by hand, without MPI: each rank's crops (its stride of the one-rank batch), a loss
//! and gradients per rank on its own copy of the network, the gradients averaged, one Adam step applied to every
//! copy, and at the checkpoint the copies' BatchNorm running statistics averaged. A sum of two f32 values is the
//! same whichever order adds them, so the bound is f32 rounding through four steps (1e-6 of each tensor's scale;
//! measured: see the test's output).
//!
//! Against one rank taking the whole batch the steps differ by design: each rank normalises its BatchNorm layers
//! over its own crops (2 of them here, against 4), as PyTorch DDP does without `SyncBatchNorm`, and Adam's first
//! steps move every weight by about the learning rate whatever the gradient's size, so a small change in a
//! gradient near zero flips a whole step. The test prints how far the two trajectories part rather than bounding
//! it.
#![cfg(feature = "mpi")]

use burn::backend::Flex;
use burn::module::{AutodiffModule, Module, ModuleVisitor, Param, ParamId};
use burn::optim::{AdamConfig, GradientsParams, Optimizer};
use burn::prelude::*;
use burn::record::Recorder;
use dataset::contract::schema::Split;
use train::data::{EpochStream, HostBatch, StreamConfig};
use train::data_parallel::Replica;
use train::model::UNet;
use train::training::{fit, fit_ranks, input_normalisation, train_loss};

mod support;

use support::mpi::{mpirun, Job};
use support::{config, is_running_stat, load, tensors, worst_relative, Ad, Rec, STEPS};

/// The mean of two replicas' gradients, parameter by parameter.
struct MeanOf<'a> {
    grads: [&'a GradientsParams; 2],
    mean: GradientsParams,
}

impl ModuleVisitor<Ad> for MeanOf<'_> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<Ad, D>>) {
        let a = self.grads[0].get::<Flex, D>(param.id);
        let b = self.grads[1].get::<Flex, D>(param.id);
        match (a, b) {
            (Some(a), Some(b)) => self.mean.register::<Flex, D>(param.id, (a + b) / 2.0),
            (None, None) => {}
            _ => panic!("one replica has a gradient the other lacks"),
        }
    }
}

/// One rank of [`two_ranks_take_the_steps_of_their_averaged_gradients_and_repeat_bit_for_bit`]'s MPI runs: that
/// test starts this one under `mpirun -np 2`, naming the dataset and the run in the environment.
#[test]
#[ignore = "a rank of the MPI fit another test starts"]
fn rank_of_a_two_rank_fit() {
    let data = std::env::var("G2R_TEST_DATA").expect("started by the two-rank test");
    let run = std::env::var("G2R_TEST_RUN").expect("started by the two-rank test");
    let source: std::sync::Arc<dyn train::data::SampleSource> =
        std::sync::Arc::new(train::data::LocalSource::open(std::path::Path::new(&data)).unwrap());
    let env = |name: &str| std::env::var(name).ok();
    let ranks = train::data_parallel::launch(&env, std::time::Duration::from_secs(120)).unwrap();
    assert_eq!(
        ranks.world(),
        2,
        "mpirun -np 2 joined {} ranks",
        ranks.world()
    );
    let outcome = fit_ranks::<Ad>(
        source,
        &config(),
        std::path::Path::new(&run),
        true,
        Some(STEPS),
        &Default::default(),
        &ranks,
        false,
    )
    .unwrap();
    assert_eq!(outcome.cursor.step, STEPS);
}

#[test]
fn two_ranks_take_the_steps_of_their_averaged_gradients_and_repeat_bit_for_bit() {
    let tmp = tempfile::tempdir().unwrap();
    let source = train::testing::synthetic_source(tmp.path(), 300, 4);
    let cfg = config();
    let device = Default::default();
    // One rank takes the first step; its checkpoint is the common start (and a resume may change the rank count).
    let start = tmp.path().join("start");
    fit::<Ad>(source.clone(), &cfg, &start, false, Some(1), &device, false).unwrap();
    let mut replicated = Vec::new();
    for name in ["two-a", "two-b"] {
        let run = tmp.path().join(name);
        train::testing::copy_dir(&start, &run);
        let mut job = Job::start(
            mpirun(2)
                .arg(std::env::current_exe().unwrap())
                .args(["--ignored", "--exact", "rank_of_a_two_rank_fit"])
                .args(["--test-threads=1", "--nocapture"])
                .env("G2R_TEST_DATA", tmp.path())
                .env("G2R_TEST_RUN", &run),
        );
        let (status, log) = job.wait(std::time::Duration::from_secs(300));
        assert!(status.success(), "mpirun -np 2 failed ({status}):\n{log}");
        replicated.push(tensors(&load(&run, &cfg)));
    }
    // Process timing must not show: the second run's every tensor equals the first's, bit for bit.
    assert_eq!(
        replicated[0], replicated[1],
        "two-rank fits differ between runs"
    );

    // By hand: two copies of the start, each fed its stride of the one-replica batch.
    let recorder = Rec::new();
    let start_net = cfg
        .net_config()
        .init::<Ad>(&device)
        .load_file(start.join("last/model"), &recorder, &device)
        .unwrap();
    let copy = |net: &UNet<Ad>| {
        cfg.net_config()
            .init::<Ad>(&device)
            .load_record(net.clone().into_record())
    };
    let mut nets = [copy(&start_net), copy(&start_net)];
    let optim_record = || recorder.load(start.join("last/optim"), &device).unwrap();
    let mut optims = [
        AdamConfig::new()
            .with_epsilon(1e-8)
            .init::<Ad, UNet<Ad>>()
            .load_record(optim_record()),
        AdamConfig::new()
            .with_epsilon(1e-8)
            .init::<Ad, UNet<Ad>>()
            .load_record(optim_record()),
    ];
    let input = input_normalisation(source.as_ref(), &cfg).unwrap();
    let stream = |batch_size: usize, replica: Replica| -> Vec<HostBatch> {
        EpochStream::start(
            source.clone(),
            Split::Train,
            StreamConfig {
                batch_size,
                ..cfg.stream
            },
            input,
            None,
            0,
            1,
            replica,
            std::convert::identity,
        )
        .unwrap()
        .map(Result::unwrap)
        .collect()
    };
    let whole = stream(4, Replica::SOLE);
    let halves = [
        stream(2, Replica { rank: 0, world: 2 }),
        stream(2, Replica { rank: 1, world: 2 }),
    ];
    assert_eq!(whole.len(), STEPS as usize - 1);
    for (step, batch) in whole.iter().enumerate() {
        // Replica r takes crops r, r + 2 of the one-replica batch, turned as that batch turns them.
        for (rank, half) in halves.iter().enumerate() {
            let crop = batch.image.len() / 4;
            let picked = &half[step];
            assert_eq!(
                picked.sample_ids,
                vec![
                    batch.sample_ids[rank].clone(),
                    batch.sample_ids[rank + 2].clone()
                ]
            );
            assert_eq!(
                picked.image[..crop],
                batch.image[rank * crop..(rank + 1) * crop]
            );
        }
        let grads: Vec<GradientsParams> = (0..2)
            .map(|rank| {
                let loss = train_loss(&nets[rank], cfg.model, &halves[rank][step], &device);
                GradientsParams::from_grads(loss.backward(), &nets[rank])
            })
            .collect();
        for rank in 0..2 {
            let mut mean = MeanOf {
                grads: [&grads[0], &grads[1]],
                mean: GradientsParams::new(),
            };
            nets[rank].visit(&mut mean);
            let net = nets[rank].clone();
            nets[rank] = optims[rank].step(cfg.learning_rate, net, mean.mean);
        }
    }
    let by_hand: Vec<Vec<(String, ParamId, Vec<f64>)>> = nets
        .iter()
        .map(|n| {
            let _ = n.clone().into_record(); // fold the last BatchNorm update in
            tensors(&n.valid())
        })
        .collect();
    let got = &replicated[0];
    assert_eq!(got.len(), by_hand[0].len());
    let mut worst: f64 = 0.0;
    for (i, (path, id, values)) in got.iter().enumerate() {
        assert_eq!((path, id), (&by_hand[0][i].0, &by_hand[0][i].1));
        let want: Vec<f64> = if is_running_stat(path) {
            by_hand[0][i]
                .2
                .iter()
                .zip(&by_hand[1][i].2)
                .map(|(a, b)| (a + b) / 2.0)
                .collect()
        } else {
            // Both copies took the same steps.
            assert_eq!(by_hand[0][i].2, by_hand[1][i].2, "{path}");
            by_hand[0][i].2.clone()
        };
        let diff = worst_relative(&want, values);
        assert!(diff <= 1e-6, "{path}: {diff:e}");
        worst = worst.max(diff);
    }
    println!("two ranks against by hand, worst relative difference over every tensor: {worst:e}");

    // One rank with the whole batch, for the record: BatchNorm over 4 crops instead of 2 moves the steps.
    let one = tmp.path().join("one");
    train::testing::copy_dir(&start, &one);
    fit::<Ad>(
        source.clone(),
        &cfg,
        &one,
        true,
        Some(STEPS),
        &device,
        false,
    )
    .unwrap();
    let single = tensors(&load(&one, &cfg));
    let begin = tensors(&load(&start, &cfg));
    // How far the two trajectories part: the weights' change from the start, one replica against two.
    let (mut apart, mut moved) = (0.0f64, 0.0f64);
    for ((s, t), b) in single.iter().zip(got).zip(&begin) {
        if is_running_stat(&s.0) {
            continue;
        }
        for ((x, y), z) in s.2.iter().zip(&t.2).zip(&b.2) {
            apart += (x - y).powi(2);
            moved += (x - z).powi(2);
        }
    }
    assert!(moved > 0.0);
    println!(
        "one rank of batch 4 against two of 2: weight change differs by {:.3e} of its norm",
        (apart / moved).sqrt()
    );
}

/// Stands in for MPI in a refusal that comes before any collective.
struct NoPeers;

impl train::data_parallel::SumAllReduce for NoPeers {
    fn sum_f32(&self, _: &mut [f32]) {
        unreachable!("refused before any all-reduce")
    }
    fn sum_f64(&self, _: &mut [f64]) {
        unreachable!("refused before any all-reduce")
    }
    fn abort(&self, _: i32) -> ! {
        unreachable!("refused before any all-reduce")
    }
}

#[test]
fn a_batch_the_ranks_do_not_divide_is_refused_before_anything_is_written() {
    let tmp = tempfile::tempdir().unwrap();
    let source = train::testing::synthetic_source(tmp.path(), 20, 4);
    let three = train::data_parallel::Ranks::joined(
        Replica { rank: 0, world: 3 },
        0,
        Box::new(NoPeers),
        std::time::Duration::from_secs(60),
    );
    let run = tmp.path().join("run");
    let err = fit_ranks::<Ad>(
        source,
        &config(),
        &run,
        false,
        None,
        &Default::default(),
        &three,
        false,
    )
    .unwrap_err()
    .to_string();
    assert!(
        err.contains("--batch 4 does not split into 3 ranks"),
        "{err}"
    );
    assert!(!run.exists(), "a refused fit wrote {}", run.display());
}

//! The data-parallel fit under Slurm: `srun --mpi=pmix -n 2` on the one-node test cluster
//! ([`dataset::testing::slurm`]) trains the same steps as `mpirun -np 2` (whose steps `data_parallel.rs` checks
//! against steps computed by hand), bit for bit; every socket of the cluster, its job step and the ranks is on
//! loopback; two tasks without an MPI bootstrap (`srun --mpi=none`) are refused; and nothing of it is left running
//! afterwards. Needs the `mpi` feature, Open MPI and Slurm.
#![cfg(feature = "mpi")]

use std::path::Path;
use std::time::{Duration, Instant};

use dataset::testing::slurm::{marked_processes, processes_in_namespace, Cluster};

mod support;

use support::mpi::{mpirun, Job, LOOPBACK_ONLY};

/// Three epochs of four steps: the loopback check runs after the first checkpoint, while the ranks still train.
fn fit_args(data: &Path, run: &Path) -> Vec<String> {
    support::mpi::fit_args(data, run, 3, 120)
}
use support::{config, load, tensors};

#[test]
fn srun_with_pmix_trains_what_mpirun_trains_on_loopback_and_leaves_nothing_running() {
    let tmp = tempfile::tempdir().unwrap();
    let _ = train::testing::synthetic_source(tmp.path(), 40, 4);
    let bin = env!("CARGO_BIN_EXE_g2r-train");

    let by_mpirun = tmp.path().join("mpirun");
    let mut job = Job::start(mpirun(2).arg(bin).args(fit_args(tmp.path(), &by_mpirun)));
    let (status, log) = job.wait(Duration::from_secs(300));
    assert!(status.success(), "mpirun -np 2 failed ({status}):\n{log}");

    let cluster = Cluster::start(&tmp.path().join("slurm"));
    let by_srun = tmp.path().join("srun");
    let log = tmp.path().join("srun.log");
    let mut srun = cluster
        .client("srun")
        .args(["--mpi=pmix", "-n", "2", "-K1", "--cpus-per-task=1"])
        .arg(bin)
        .args(fit_args(tmp.path(), &by_srun))
        .envs(LOOPBACK_ONLY)
        .env("RAYON_NUM_THREADS", "1")
        .stdout(std::fs::File::create(&log).unwrap())
        .stderr(std::fs::File::create(tmp.path().join("srun.err")).unwrap())
        .spawn()
        .unwrap();
    // While the ranks train (after their first checkpoint), every socket of the cluster's processes is on loopback.
    let started = Instant::now();
    let mut listening = Vec::new();
    let status = loop {
        if let Some(status) = srun.try_wait().unwrap() {
            break status;
        }
        if listening.is_empty() && by_srun.join("last").exists() {
            listening = cluster.assert_loopback_only();
        }
        assert!(
            started.elapsed() < Duration::from_secs(300),
            "srun ran past 300 s{}",
            cluster.log_tails()
        );
        std::thread::sleep(Duration::from_millis(20));
    };
    let stderr = std::fs::read_to_string(tmp.path().join("srun.err")).unwrap_or_default();
    assert!(
        status.success(),
        "srun --mpi=pmix -n 2 failed ({status}):\n{stderr}{}",
        cluster.log_tails()
    );
    assert!(
        !listening.is_empty(),
        "the step ended before its sockets were checked"
    );
    println!("listening on loopback while the step ran: {listening:?}");
    assert!(
        stderr.contains("joined MPI rank=1 world=2"),
        "srun did not start two ranks of one MPI job:\n{stderr}{}",
        cluster.log_tails()
    );

    let cfg = config();
    // Parameter ids are drawn per process: compare by field path.
    let values = |run: &Path| -> Vec<(String, Vec<f64>)> {
        tensors(&load(run, &cfg))
            .into_iter()
            .map(|(path, _, values)| (path, values))
            .collect()
    };
    let (srun_values, mpirun_values) = (values(&by_srun), values(&by_mpirun));
    assert_eq!(srun_values.len(), mpirun_values.len());
    for (a, b) in srun_values.iter().zip(&mpirun_values) {
        assert!(
            a == b,
            "{}: srun's ranks took other steps than mpirun's",
            a.0
        );
    }

    // Two tasks without an MPI bootstrap (`srun --mpi=none`) would be two unrelated copies: each refuses in one
    // line before MPI starts, and nothing is written.
    let refused = tmp.path().join("refused");
    let out = cluster
        .client("srun")
        .args(["--mpi=none", "-n", "2", "--cpus-per-task=1"])
        .arg(bin)
        .args(fit_args(tmp.path(), &refused))
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "srun --mpi=none ran:\n{stderr}");
    assert_eq!(
        stderr
            .lines()
            .filter(|l| l.starts_with("error:") && l.contains("without an MPI bootstrap"))
            .count(),
        2,
        "{stderr}"
    );
    assert!(
        !refused.exists(),
        "a refused fit wrote {}",
        refused.display()
    );

    let (marker, namespace) = (cluster.marker().to_string(), cluster.namespace());
    drop(cluster);
    let mut left = marked_processes(&marker);
    left.extend(processes_in_namespace(&namespace));
    assert_eq!(
        left,
        Vec::<i32>::new(),
        "processes of the cluster outlived it"
    );
}

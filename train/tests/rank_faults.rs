//! Ranks that die or hang mid-fit (`mpirun -np 2 g2r-train fit`, [`train::data_parallel`]): the job ends, every
//! process with it, non-zero and within a stated time; the last checkpoint stays whole, and `fit --resume`
//! continues from it. Needs the `mpi` feature and Open MPI's `mpirun`; loopback only.
#![cfg(feature = "mpi")]

use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

mod support;

use support::mpi::{fit_args as launcher_fit_args, mpirun, Job};

/// The watchdog's limit these runs are given (`--collective-timeout`).
const COLLECTIVE_TIMEOUT_S: u64 = 6;
/// Long enough that the faults land mid-fit.
const EPOCHS: usize = 1000;

fn fit_args(data: &Path, run: &Path) -> Vec<String> {
    launcher_fit_args(data, run, EPOCHS, COLLECTIVE_TIMEOUT_S)
}

/// How long the launcher may take to end the job once a rank is gone, or once the watchdog fired.
const END_WITHIN: Duration = Duration::from_secs(20);

fn checkpoint_step(run: &Path) -> Option<u64> {
    let text = std::fs::read_to_string(run.join("last/cursor.json")).ok()?;
    let cursor: serde_json::Value = serde_json::from_str(&text).ok()?;
    cursor["step"].as_u64()
}

/// Start a two-rank fit and return it once its first checkpoint is written and rank 1 is known.
fn two_rank_fit_past_a_checkpoint(data: &Path, run: &Path) -> (Job, i32) {
    let job = Job::start(
        mpirun(2)
            .arg(env!("CARGO_BIN_EXE_g2r-train"))
            .args(fit_args(data, run)),
    );
    let started = Instant::now();
    loop {
        if let (Some(_), Some(pid)) = (checkpoint_step(run), job.rank_pid(1)) {
            return (job, pid);
        }
        assert!(
            started.elapsed() < Duration::from_secs(120),
            "no checkpoint after 120 s:\n{}",
            job.log()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// The job ended: non-zero, within [`END_WITHIN`] of `since` (plus `allowance`), with no process left.
fn assert_ended(mut job: Job, since: Instant, allowance: Duration) -> String {
    let (status, log) = job.wait(allowance + END_WITHIN + Duration::from_secs(60));
    let took = since.elapsed();
    assert!(!status.success(), "the job ended successfully:\n{log}");
    assert!(
        took <= allowance + END_WITHIN,
        "the job took {took:?} to end:\n{log}"
    );
    // The launcher reaps its ranks before it exits; a moment's grace for the kernel to finish the killed ones.
    let reaped = Instant::now();
    while !job.processes().is_empty() && reaped.elapsed() < Duration::from_secs(2) {
        std::thread::sleep(Duration::from_millis(50));
    }
    assert_eq!(
        job.processes(),
        Vec::<i32>::new(),
        "processes outlived the job:\n{log}"
    );
    println!(
        "the job ended {:.1} s after the fault ({status})",
        took.as_secs_f64()
    );
    log
}

/// `fit --resume` from the run's last checkpoint, in one process, takes two more steps.
fn assert_resumes(data: &Path, run: &Path) {
    let step = checkpoint_step(run).expect("an intact checkpoint");
    let output = Command::new(env!("CARGO_BIN_EXE_g2r-train"))
        .args(fit_args(data, run))
        .args(["--resume", "--stop-after-steps", &(step + 2).to_string()])
        .env("RAYON_NUM_THREADS", "1")
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "resume failed: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    assert_eq!(checkpoint_step(run), Some(step + 2));
}

#[test]
fn a_rank_killed_mid_fit_ends_the_job_and_the_last_checkpoint_resumes() {
    let tmp = tempfile::tempdir().unwrap();
    let _ = train::testing::synthetic_source(tmp.path(), 40, 4);
    let run = tmp.path().join("run");
    let (job, rank1) = two_rank_fit_past_a_checkpoint(tmp.path(), &run);
    // SAFETY: a signal to a rank of this test's own job.
    unsafe { libc::kill(rank1, libc::SIGKILL) };
    assert_ended(job, Instant::now(), Duration::ZERO);
    assert_resumes(tmp.path(), &run);
}

#[test]
fn a_stopped_rank_is_caught_by_the_watchdog_and_the_last_checkpoint_resumes() {
    let tmp = tempfile::tempdir().unwrap();
    let _ = train::testing::synthetic_source(tmp.path(), 40, 4);
    let run = tmp.path().join("run");
    let (job, rank1) = two_rank_fit_past_a_checkpoint(tmp.path(), &run);
    // SAFETY: a signal to a rank of this test's own job.
    unsafe { libc::kill(rank1, libc::SIGSTOP) };
    let log = assert_ended(
        job,
        Instant::now(),
        Duration::from_secs(COLLECTIVE_TIMEOUT_S),
    );
    assert!(
        log.contains("rank 0 of 2") && log.contains("--collective-timeout"),
        "the watchdog did not say which collective timed out:\n{log}"
    );
    assert_resumes(tmp.path(), &run);
}

//! The test cluster ([`dataset::testing::slurm`]) leaves nothing running when the test process that owns it is
//! killed mid-job: another test starts a cluster with a running job in a child test process, kills that process
//! with SIGKILL (no destructor runs), and then finds no process of the cluster alive: no slurmctld, slurmd,
//! slurmstepd or job task. Needs Slurm (`.ci/setup`).

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use dataset::testing::slurm::{marked_processes, processes_in_namespace, Cluster};

/// The child: a cluster with a job running, its marker and PID namespace written to `$G2R_TEST_READY` once the job
/// runs; then it waits to be killed.
#[test]
#[ignore = "a test process that another test kills"]
fn a_cluster_with_a_running_job_until_killed() {
    let ready = std::env::var("G2R_TEST_READY").expect("started by the kill test");
    let dir = Path::new(&ready).with_extension("cluster");
    let cluster = Cluster::start(&dir);
    let job = cluster.command(
        "sbatch",
        &["--parsable", "--output=/dev/null", "--wrap", "sleep 600"],
    );
    let job = job.trim().to_string();
    let started = Instant::now();
    while !cluster.state(&job).starts_with("JobState=RUNNING") {
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "{}",
            cluster.state(&job)
        );
        std::thread::sleep(Duration::from_millis(200));
    }
    std::fs::write(
        &ready,
        format!("{}\n{}", cluster.marker(), cluster.namespace()),
    )
    .unwrap();
    std::thread::sleep(Duration::from_secs(600));
}

#[test]
fn a_killed_test_process_leaves_no_process_of_its_cluster_alive() {
    let tmp = tempfile::tempdir().unwrap();
    let ready = tmp.path().join("ready");
    let mut child = Command::new(std::env::current_exe().unwrap())
        .args([
            "--ignored",
            "--exact",
            "a_cluster_with_a_running_job_until_killed",
        ])
        .args(["--test-threads=1", "--nocapture"])
        .env("G2R_TEST_READY", &ready)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let started = Instant::now();
    let (marker, namespace) = loop {
        if let Some((marker, namespace)) = std::fs::read_to_string(&ready).ok().and_then(|t| {
            t.split_once('\n')
                .map(|(m, n)| (m.to_string(), n.to_string()))
        }) {
            break (marker, namespace);
        }
        if let Some(status) = child.try_wait().unwrap() {
            panic!("the cluster's test process ended ({status}) before its job ran");
        }
        assert!(
            started.elapsed() < Duration::from_secs(120),
            "no running job in 120 s"
        );
        std::thread::sleep(Duration::from_millis(200));
    };
    // The cluster is whole: daemons, the job's step daemon and its task (which carries the marker; slurmstepd
    // does not, but is in the cluster's namespace).
    let of_cluster = || {
        let mut pids = marked_processes(&marker);
        pids.extend(processes_in_namespace(&namespace));
        pids.sort_unstable();
        pids.dedup();
        pids
    };
    let names = |pids: &[i32]| -> Vec<String> {
        pids.iter()
            .filter_map(|pid| std::fs::read_to_string(format!("/proc/{pid}/comm")).ok())
            .map(|c| c.trim().to_string())
            .collect()
    };
    let alive = names(&of_cluster());
    for program in ["slurmctld", "slurmd", "slurmstepd", "sleep"] {
        assert!(
            alive.iter().any(|n| n == program),
            "no {program} among {alive:?}"
        );
    }
    child.kill().unwrap(); // SIGKILL: no destructor runs
    child.wait().unwrap();
    let killed = Instant::now();
    while !of_cluster().is_empty() && killed.elapsed() < Duration::from_secs(10) {
        std::thread::sleep(Duration::from_millis(100));
    }
    let left = of_cluster();
    assert!(
        left.is_empty(),
        "alive after the test process was killed: {:?}",
        names(&left)
    );
    println!(
        "{} processes of the cluster ({alive:?}) gone {:.2} s after the kill",
        alive.len(),
        killed.elapsed().as_secs_f64()
    );
}

//! The pipeline as a Slurm job array, with the scripts users submit (docs/slurm/): a one-node cluster from Debian's
//! packages on 127.0.0.1 runs the demo manifest as a 4-, 2- and 1-task map array plus the publish job, and every
//! published byte equals the single-process build's. A cancelled map task cancels the publish (nothing published), and
//! submitting again resumes to the same bytes.
//!
//! Needs `slurmctld`, `slurmd` and the client commands (`.ci/setup` installs them). The daemons run in the
//! foreground under this test, with `auth/none` and their state in a temporary directory, and are stopped by PID.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// A one-node Slurm cluster on 127.0.0.1 whose daemons this process owns.
struct Cluster {
    conf: PathBuf,
    daemons: Vec<Child>,
}

impl Cluster {
    fn start(dir: &Path) -> Self {
        for daemon in ["slurmctld", "slurmd", "sbatch"] {
            let found = Command::new("sh")
                .args(["-c", &format!("command -v {daemon}")])
                .output()
                .unwrap();
            assert!(
                found.status.success(),
                "{daemon} not found: run .ci/setup (installs slurmctld, slurmd and slurm-client)"
            );
        }
        let host = String::from_utf8(Command::new("hostname").arg("-s").output().unwrap().stdout)
            .unwrap()
            .trim()
            .to_string();
        let port = || {
            std::net::TcpListener::bind("127.0.0.1:0")
                .unwrap()
                .local_addr()
                .unwrap()
                .port()
        };
        let (ctld_port, d_port) = (port(), port());
        let user = String::from_utf8(Command::new("id").arg("-un").output().unwrap().stdout)
            .unwrap()
            .trim()
            .to_string();
        for sub in ["state", "spool"] {
            std::fs::create_dir_all(dir.join(sub)).unwrap();
        }
        let d = dir.display();
        let conf = dir.join("slurm.conf");
        // auth/none and cred/none: a test cluster on loopback needs no munge key; linuxproc and task/none: no
        // cgroups inside a container. Memory is declared so that the scripts' --mem requests fit.
        std::fs::write(
            &conf,
            format!(
                "ClusterName=g2rtest\nSlurmctldHost={host}(127.0.0.1)\nSlurmctldPort={ctld_port}\n\
                 SlurmdPort={d_port}\nAuthType=auth/none\nCredType=cred/none\n\
                 ProctrackType=proctrack/linuxproc\nTaskPlugin=task/none\nSlurmUser={user}\nSlurmdUser={user}\n\
                 StateSaveLocation={d}/state\nSlurmdSpoolDir={d}/spool\nSlurmctldPidFile={d}/slurmctld.pid\n\
                 SlurmdPidFile={d}/slurmd.pid\nSlurmctldLogFile={d}/slurmctld.log\nSlurmdLogFile={d}/slurmd.log\n\
                 ReturnToService=2\nSchedulerType=sched/builtin\nSelectType=select/cons_tres\n\
                 SelectTypeParameters=CR_CPU\nMpiDefault=none\nJobCompType=jobcomp/none\n\
                 AccountingStorageType=accounting_storage/none\n\
                 NodeName={host} NodeAddr=127.0.0.1 CPUs=2 RealMemory=8192 State=UNKNOWN\n\
                 PartitionName=local Nodes={host} Default=YES MaxTime=INFINITE State=UP\n"
            ),
        )
        .unwrap();
        let spawn = |daemon: &str| {
            Command::new(daemon)
                .args(["-D", "-f"])
                .arg(&conf)
                .stdout(Stdio::null())
                .stderr(Stdio::null())
                .spawn()
                .unwrap()
        };
        let cluster = Cluster {
            daemons: vec![spawn("slurmctld"), spawn("slurmd")],
            conf,
        };
        let started = Instant::now();
        loop {
            let state = cluster.command("sinfo", &["-h", "-o", "%T"]);
            if state.trim() == "idle" {
                break;
            }
            assert!(
                started.elapsed() < Duration::from_secs(60),
                "the node did not come up (sinfo: {state:?}); see {d}/slurmctld.log and {d}/slurmd.log"
            );
            std::thread::sleep(Duration::from_millis(500));
        }
        cluster
    }

    /// Run a Slurm client command against this cluster; its stdout.
    fn command(&self, program: &str, args: &[&str]) -> String {
        let out = Command::new(program)
            .args(args)
            .env("SLURM_CONF", &self.conf)
            .output()
            .unwrap();
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    /// `docs/slurm/submit.sh MANIFEST N EXTRA…` from `dir`: the map array and publish job ids.
    fn submit(
        &self,
        dir: &Path,
        manifest: &Path,
        partitions: usize,
        extra: &[&str],
    ) -> (String, String) {
        let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/slurm/submit.sh");
        let out = Command::new("bash")
            .arg(script)
            .arg(manifest)
            .arg(partitions.to_string())
            .args(extra)
            .current_dir(dir)
            .env("SLURM_CONF", &self.conf)
            .env("G2R_PIPELINE", env!("CARGO_BIN_EXE_g2r-pipeline"))
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "submit.sh: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let ids = String::from_utf8(out.stdout).unwrap();
        let mut ids = ids.split_whitespace().map(str::to_string);
        (ids.next().unwrap(), ids.next().unwrap())
    }

    /// Wait until none of `jobs` is pending or running.
    fn wait(&self, jobs: &[&str]) {
        let started = Instant::now();
        while !self
            .command("squeue", &["-h", "-o", "%i", "-j", &jobs.join(",")])
            .trim()
            .is_empty()
        {
            assert!(
                started.elapsed() < Duration::from_secs(1800),
                "jobs {jobs:?} did not finish in 30 min"
            );
            std::thread::sleep(Duration::from_secs(1));
        }
    }

    /// A finished job's state (COMPLETED, CANCELLED, FAILED…) and why.
    fn state(&self, job: &str) -> String {
        let text = self.command("scontrol", &["show", "job", job]);
        text.split_whitespace()
            .filter(|field| field.starts_with("JobState=") || field.starts_with("Reason="))
            .collect::<Vec<_>>()
            .join(" ")
    }
}

impl Drop for Cluster {
    fn drop(&mut self) {
        for daemon in &mut self.daemons {
            let _ = daemon.kill();
            let _ = daemon.wait();
        }
    }
}

/// A build directory laid out like the repository (`manifests/demo.toml`, `out/demo-world`), so every build's
/// lock keys and published manifest are the same.
fn build_dir(root: &Path, world: &Path, name: &str) -> PathBuf {
    let build = root.join(name);
    std::fs::create_dir_all(build.join("manifests")).unwrap();
    std::fs::create_dir_all(build.join("out")).unwrap();
    std::os::unix::fs::symlink(world, build.join("out/demo-world")).unwrap();
    let manifest = build.join("manifests/demo.toml");
    std::fs::copy(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../manifests/demo.toml"),
        &manifest,
    )
    .unwrap();
    manifest
}

/// Every published file's bytes.
fn published(build: &Path) -> BTreeMap<String, Vec<u8>> {
    let dir = build.join("out/demo-dataset/dataset");
    std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .flatten()
        .map(|e| {
            (
                e.file_name().to_string_lossy().into_owned(),
                std::fs::read(e.path()).unwrap(),
            )
        })
        .collect()
}

fn assert_same(reference: &BTreeMap<String, Vec<u8>>, build: &Path, what: &str) {
    let got = published(build);
    assert_eq!(
        got.keys().collect::<Vec<_>>(),
        reference.keys().collect::<Vec<_>>(),
        "{what}"
    );
    for (name, bytes) in reference {
        assert!(
            bytes == &got[name],
            "{what}: {name} differs from the single-process build"
        );
    }
}

#[test]
fn a_slurm_array_publishes_the_same_bytes_and_a_failed_task_publishes_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let preset = pipeline::synth::config::preset("demo").unwrap();
    let world = pipeline::synth::generate(
        &pipeline::synth::WorldConfig::from_toml(preset).unwrap(),
        42,
        &root.join("demo-world"),
        false,
    )
    .unwrap();

    let single = build_dir(root, &world, "single");
    let status = Command::new(env!("CARGO_BIN_EXE_g2r-pipeline"))
        .arg("run")
        .arg(&single)
        .status()
        .unwrap();
    assert!(status.success());
    let reference = published(&root.join("single"));
    assert!(reference.contains_key("manifest.json"));

    let cluster = Cluster::start(&root.join("slurm"));
    // Four, two and one partitions, two tasks at a time on the node's two CPUs.
    for partitions in [4, 2, 1] {
        let name = format!("array-{partitions}");
        let manifest = build_dir(root, &world, &name);
        let (map, publish) = cluster.submit(
            &root.join(&name),
            &manifest,
            partitions,
            &["--cpus-per-task=1"],
        );
        cluster.wait(&[&map, &publish]);
        assert!(
            cluster.state(&publish).starts_with("JobState=COMPLETED"),
            "{}",
            cluster.state(&publish)
        );
        assert_same(
            &reference,
            &root.join(&name),
            &format!("{partitions}-task array"),
        );
    }

    // One map task cancelled before it ran: the publish job is cancelled (not left pending) and nothing is
    // published; submitting again finishes that partition only and publishes the same bytes.
    let manifest = build_dir(root, &world, "cancelled");
    let dir = root.join("cancelled");
    let (map, publish) = cluster.submit(&dir, &manifest, 4, &["--cpus-per-task=1", "--hold"]);
    cluster.command("scancel", &[&format!("{map}_3")]);
    cluster.command("scontrol", &["release", &map]);
    cluster.wait(&[&map, &publish]);
    let state = cluster.state(&publish);
    assert!(
        state.contains("JobState=CANCELLED") && state.contains("DependencyNeverSatisfied"),
        "{state}"
    );
    assert!(
        !dir.join("out/demo-dataset/dataset/manifest.json").exists(),
        "nothing published"
    );
    assert!(dir
        .join("out/demo-dataset/partitions/4/2/pipeline.lock.json")
        .exists());
    assert!(
        !dir.join("out/demo-dataset/partitions/4/3").exists(),
        "task 3 never ran"
    );
    let (map, publish) = cluster.submit(&dir, &manifest, 4, &["--cpus-per-task=1"]);
    cluster.wait(&[&map, &publish]);
    assert!(
        cluster.state(&publish).starts_with("JobState=COMPLETED"),
        "{}",
        cluster.state(&publish)
    );
    assert_same(&reference, &dir, "resubmitted after a cancelled task");
}

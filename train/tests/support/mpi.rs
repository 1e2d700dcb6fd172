//! `mpirun` for tests: loopback only, as root in a container, one thread per rank; and a job that leaves nothing
//! running, whether it ends, times out, or the test panics or is killed.

use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus};
use std::time::{Duration, Instant};

/// The transports of every rank a test starts, `mpirun`'s or `srun`'s (`OMPI_MCA_*` variables): shared memory
/// and self only, so that ranks open no TCP socket (Open MPI's TCP transport listens on every interface whatever
/// `btl_tcp_if_include` says); shared memory without the single-copy mechanism, which containers often forbid.
/// Out-of-band messages on loopback.
pub const LOOPBACK_ONLY: [(&str, &str); 3] = [
    ("OMPI_MCA_btl", "self,vader"),
    ("OMPI_MCA_btl_vader_single_copy_mechanism", "none"),
    ("OMPI_MCA_oob_tcp_if_include", "lo"),
];

/// `mpirun -np N` with [`LOOPBACK_ONLY`] ranks, no core binding, and root allowed; in a network namespace whose
/// only interface is loopback (mpirun's out-of-band listener binds every interface, `oob_tcp_if_include`
/// notwithstanding), and in a PID namespace of its own (`unshare --pid --kill-child`), so that no rank outlives
/// it whatever kills it.
pub fn mpirun(np: usize) -> Command {
    let mut command = Command::new("unshare");
    command
        .args([
            "--net",
            "--pid",
            "--fork",
            "--kill-child=SIGKILL",
            "sh",
            "-c",
        ])
        .arg(r#"ip link set lo up && exec mpirun "$@""#)
        .arg("sh")
        .args([
            "-np",
            &np.to_string(),
            "--oversubscribe",
            "--bind-to",
            "none",
        ])
        .envs(LOOPBACK_ONLY)
        .env("OMPI_ALLOW_RUN_AS_ROOT", "1")
        .env("OMPI_ALLOW_RUN_AS_ROOT_CONFIRM", "1")
        .env("RAYON_NUM_THREADS", "1");
    command
}

/// A launcher and everything it starts, each process marked by an environment variable of its own (Open MPI puts
/// ranks in process groups of their own): all are killed when the job is dropped (a panicking test included), and
/// the launcher by the kernel when the test process dies (`PR_SET_PDEATHSIG`; [`mpirun`]'s namespace then takes
/// the ranks with it).
pub struct Job {
    child: Child,
    marker: String,
    log: PathBuf,
    _dir: tempfile::TempDir,
}

impl Job {
    pub fn start(command: &mut Command) -> Job {
        let dir = tempfile::tempdir().unwrap();
        let log = dir.path().join("job.log");
        let file = std::fs::File::create(&log).unwrap();
        static JOBS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
        let marker = format!(
            "{}-{}",
            std::process::id(),
            JOBS.fetch_add(1, std::sync::atomic::Ordering::SeqCst)
        );
        // Each job its own Open MPI session directory and shared-memory files. Two `mpirun`s in PID namespaces of
        // their own both run as pid 1, so Open MPI derives the same job id for both, and with shared defaults their
        // ranks map each other's shared-memory segments (a test binary runs its tests at once: segfaults).
        command
            .stdout(file.try_clone().unwrap())
            .stderr(file)
            .env(MARKER, &marker)
            .env("TMPDIR", dir.path())
            .env("OMPI_MCA_orte_tmpdir_base", dir.path())
            .env("OMPI_MCA_btl_vader_backing_directory", dir.path());
        // SAFETY: prctl is async-signal-safe, and nothing else runs between fork and exec.
        unsafe {
            command.pre_exec(|| {
                libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
                Ok(())
            });
        }
        let child = command.spawn().unwrap_or_else(|e| {
            panic!(
                "cannot start {:?} (is Open MPI installed? .ci/setup): {e}",
                command.get_program()
            )
        });
        Job {
            child,
            marker,
            log,
            _dir: dir,
        }
    }

    /// The live processes of this job (the launcher and the ranks), wherever they have been reparented.
    pub fn processes(&self) -> Vec<i32> {
        marked(&self.marker, None)
    }

    pub fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// The exit status, if the launcher has ended.
    pub fn try_wait(&mut self) -> Option<ExitStatus> {
        self.child.try_wait().unwrap()
    }

    /// Wait for the launcher to end, at most `limit` (then the test fails with its log).
    pub fn wait(&mut self, limit: Duration) -> (ExitStatus, String) {
        let started = Instant::now();
        loop {
            if let Some(status) = self.try_wait() {
                return (status, self.log());
            }
            assert!(
                started.elapsed() < limit,
                "the job ran past {limit:?}:\n{}",
                self.log()
            );
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// The pid of rank `rank` of this job, once it is running.
    pub fn rank_pid(&self, rank: usize) -> Option<i32> {
        marked(&self.marker, Some(&format!("OMPI_COMM_WORLD_RANK={rank}")))
            .into_iter()
            .next()
    }
}

impl Drop for Job {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        for pid in self.processes() {
            // SAFETY: a signal to a process this job started (it carries the job's marker).
            unsafe {
                libc::kill(pid, libc::SIGKILL);
            }
        }
    }
}

/// The variable that marks a job's processes.
const MARKER: &str = "G2R_TEST_JOB";

/// The live processes (not zombies) whose environment holds `MARKER=marker`, and `also` when given.
fn marked(marker: &str, also: Option<&str>) -> Vec<i32> {
    let mark = format!("{MARKER}={marker}");
    let mut found = Vec::new();
    for entry in std::fs::read_dir("/proc").unwrap().flatten() {
        let Ok(pid) = entry.file_name().to_string_lossy().parse::<i32>() else {
            continue;
        };
        let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else {
            continue;
        };
        // pid (comm) state ...: comm may hold spaces, so split after its closing parenthesis.
        let Some(rest) = stat.rsplit_once(')').map(|(_, r)| r) else {
            continue;
        };
        if rest.split_whitespace().next() == Some("Z") {
            continue;
        }
        let Ok(env) = std::fs::read(format!("/proc/{pid}/environ")) else {
            continue;
        };
        let has = |wanted: &str| env.split(|&b| b == 0).any(|v| v == wanted.as_bytes());
        if has(&mark) && also.is_none_or(has) {
            found.push(pid);
        }
    }
    found
}

/// `g2r-train fit` arguments for the launcher tests: [`super::config`]'s run (M2, width 4, batch 4, four steps an
/// epoch, seed 5, no dropout) on `data` into `run`, for `epochs` epochs, each all-reduce waiting at most
/// `collective_timeout_s`.
pub fn fit_args(data: &Path, run: &Path, epochs: usize, collective_timeout_s: u64) -> Vec<String> {
    let mut args: Vec<String> = vec!["fit".into(), "--data".into(), data.display().to_string()];
    args.extend(["--out".into(), run.display().to_string()]);
    args.extend(
        [
            "--model",
            "m2",
            "--width",
            "4",
            "--batch",
            "4",
            "--max-train-samples",
            "16",
            "--max-val-samples",
            "4",
            "--no-dropout",
            "--seed",
            "5",
        ]
        .map(String::from),
    );
    args.extend(["--epochs".into(), epochs.to_string()]);
    args.extend([
        "--collective-timeout".into(),
        collective_timeout_s.to_string(),
    ]);
    args
}

//! A one-node Slurm cluster on 127.0.0.1 for tests, from Debian's packages (`.ci/setup` installs slurmctld, slurmd
//! and the client commands). The daemons run in the foreground under the test, with `auth/none` and their state in
//! a temporary directory, and listen on loopback only (checked at start, and by [`Cluster::assert_loopback_only`]
//! while jobs run).
//!
//! Nothing outlives the test. The daemons run in a PID namespace of their own (`unshare --pid`), so every job step
//! they start (slurmstepd, which Slurm double-forks away from slurmd, and its tasks) dies with the namespace. The
//! namespace ends when the cluster is dropped (after its jobs are cancelled), or, if the test process dies first,
//! by the kernel: `PR_SET_PDEATHSIG` on `unshare`, whose `--kill-child` takes the namespace down with it. Every
//! process the cluster starts carries [`Cluster::marker`] in its environment, so a test can look for survivors.

use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

/// The variable that marks a cluster's processes (daemons, and the jobs submitted through [`Cluster::client`]).
pub const MARKER: &str = "G2R_TEST_CLUSTER";

pub struct Cluster {
    conf: PathBuf,
    dir: PathBuf,
    marker: String,
    /// `unshare`, whose child is the namespace's first process: the shell that waits for the daemons.
    namespace: Child,
}

impl Cluster {
    /// Start the daemons with their state under `dir` and wait (at most a minute) until the node is idle.
    pub fn start(dir: &Path) -> Self {
        for program in ["slurmctld", "slurmd", "sbatch", "ss", "unshare"] {
            let found = Command::new("sh")
                .args(["-c", &format!("command -v {program}")])
                .output()
                .expect("sh");
            assert!(
                found.status.success(),
                "{program} not found: run .ci/setup (installs slurmctld, slurmd, slurm-client, iproute2, util-linux)"
            );
        }
        let host = text(
            Command::new("hostname")
                .arg("-s")
                .output()
                .expect("hostname"),
        )
        .trim()
        .to_string();
        let user = text(Command::new("id").arg("-un").output().expect("id"))
            .trim()
            .to_string();
        let port = || {
            std::net::TcpListener::bind("127.0.0.1:0")
                .and_then(|l| l.local_addr())
                .expect("a free loopback port")
                .port()
        };
        let (ctld_port, d_port) = (port(), port());
        for sub in ["state", "spool"] {
            std::fs::create_dir_all(dir.join(sub)).expect("creating the cluster's state");
        }
        let d = dir.display();
        let conf = dir.join("slurm.conf");
        // auth/none and cred/none: a test cluster needs no munge key, so it must take messages from loopback only:
        // CommunicationParameters binds slurmctld and slurmd to their 127.0.0.1 addresses instead of every
        // interface (checked below). linuxproc and task/none: no cgroups inside a container. Memory is declared
        // so that the scripts' --mem requests fit. pmix: `srun --mpi=pmix` starts MPI ranks.
        std::fs::write(
            &conf,
            format!(
                "ClusterName=g2rtest\nSlurmctldHost={host}(127.0.0.1)\nSlurmctldPort={ctld_port}\n\
                 SlurmdPort={d_port}\nAuthType=auth/none\nCredType=cred/none\n\
                 CommunicationParameters=NoInAddrAny,NoCtldInAddrAny\n\
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
        .expect("writing slurm.conf");
        let marker = format!("{}-{ctld_port}", std::process::id());
        let mut command = Command::new("unshare");
        command
            .args(["--pid", "--fork", "--kill-child=SIGKILL", "sh", "-c"])
            .arg(r#"slurmctld -D -f "$1" & slurmd -D -f "$1" & wait"#)
            .arg("sh")
            .arg(&conf)
            .env(MARKER, &marker)
            .stdout(Stdio::null())
            .stderr(Stdio::null());
        die_with_parent(&mut command);
        let namespace = command.spawn().unwrap_or_else(|e| {
            panic!("starting the Slurm daemons in a PID namespace (unshare --pid, needs root): {e}")
        });
        let cluster = Cluster {
            namespace,
            conf,
            dir: dir.to_path_buf(),
            marker,
        };
        let started = Instant::now();
        loop {
            let state = cluster.command("sinfo", &["-h", "-o", "%T"]);
            if state.trim() == "idle" {
                break;
            }
            assert!(
                started.elapsed() < Duration::from_secs(60),
                "the node did not come up (sinfo: {state:?}){}",
                cluster.log_tails()
            );
            std::thread::sleep(Duration::from_millis(500));
        }
        // An idle node may still refuse its first job step ("task launch failed", with srun exiting 0): wait until
        // a step runs and prints.
        loop {
            let out = cluster.try_command("srun", &["-n", "1", "echo", "ready"]);
            if text(out).trim() == "ready" {
                break;
            }
            assert!(
                started.elapsed() < Duration::from_secs(60),
                "the node does not run job steps{}",
                cluster.log_tails()
            );
            std::thread::sleep(Duration::from_millis(500));
        }
        cluster.assert_loopback_only();
        cluster
    }

    /// The cluster's `slurm.conf` (clients find it through `SLURM_CONF`).
    pub fn conf(&self) -> &Path {
        &self.conf
    }

    /// The value of [`MARKER`] in every process this cluster starts.
    pub fn marker(&self) -> &str {
        &self.marker
    }

    /// The cluster's PID namespace (`pid:[inode]`), which every daemon and job step of it is in (slurmd hands
    /// its job steps a cleaned environment, without [`MARKER`]).
    pub fn namespace(&self) -> String {
        self.find_namespace().expect("slurmctld runs")
    }

    /// [`Cluster::namespace`], or `None` once slurmctld is gone.
    fn find_namespace(&self) -> Option<String> {
        marked_processes(&self.marker)
            .into_iter()
            .find(|pid| {
                std::fs::read_to_string(format!("/proc/{pid}/comm"))
                    .is_ok_and(|c| c.trim() == "slurmctld")
            })
            .and_then(|pid| std::fs::read_link(format!("/proc/{pid}/ns/pid")).ok())
            .map(|link| link.display().to_string())
    }

    /// A Slurm client command (sbatch, srun, squeue…) against this cluster, its jobs marked as the cluster's; it
    /// dies with the test process.
    pub fn client(&self, program: impl AsRef<std::ffi::OsStr>) -> Command {
        let mut command = Command::new(program);
        command
            .env("SLURM_CONF", &self.conf)
            .env(MARKER, &self.marker);
        die_with_parent(&mut command);
        command
    }

    /// Run a client command; its stdout, or a failed test with its stderr and the daemons' logs.
    pub fn command(&self, program: &str, args: &[&str]) -> String {
        let out = self.try_command(program, args);
        assert!(
            out.status.success(),
            "{program} {args:?} failed: {}{}",
            String::from_utf8_lossy(&out.stderr).trim(),
            self.log_tails()
        );
        text(out)
    }

    fn try_command(&self, program: &str, args: &[&str]) -> Output {
        self.client(program)
            .args(args)
            .output()
            .unwrap_or_else(|e| panic!("{program}: {e}"))
    }

    /// Wait until none of `jobs` is pending or running (at most `limit`). A failing `squeue` is never read as
    /// "no jobs left": it fails the wait once it has failed for ten seconds running.
    pub fn wait(&self, jobs: &[&str], limit: Duration) {
        let started = Instant::now();
        let mut failing_since: Option<Instant> = None;
        loop {
            let out = self.try_command("squeue", &["-h", "-o", "%i", "-j", &jobs.join(",")]);
            if out.status.success() {
                failing_since = None;
                if text(out).trim().is_empty() {
                    return;
                }
            } else {
                let since = *failing_since.get_or_insert_with(Instant::now);
                assert!(
                    since.elapsed() < Duration::from_secs(10),
                    "squeue keeps failing: {}{}",
                    String::from_utf8_lossy(&out.stderr).trim(),
                    self.log_tails()
                );
            }
            assert!(
                started.elapsed() < limit,
                "jobs {jobs:?} did not finish in {limit:?}{}",
                self.log_tails()
            );
            std::thread::sleep(Duration::from_millis(500));
        }
    }

    /// A finished job's state (COMPLETED, CANCELLED, FAILED…) and why.
    pub fn state(&self, job: &str) -> String {
        let text = self.command("scontrol", &["show", "job", job]);
        text.split_whitespace()
            .filter(|field| field.starts_with("JobState=") || field.starts_with("Reason="))
            .collect::<Vec<_>>()
            .join(" ")
    }

    /// The last lines of the daemons' logs, for a failure message (the directory goes with the test).
    pub fn log_tails(&self) -> String {
        let mut tails = String::new();
        for log in ["slurmctld.log", "slurmd.log"] {
            let text = std::fs::read_to_string(self.dir.join(log)).unwrap_or_default();
            let lines: Vec<&str> = text.lines().collect();
            tails.push_str(&format!("\n--- last lines of {log}:\n"));
            for line in &lines[lines.len().saturating_sub(20)..] {
                tails.push_str(line);
                tails.push('\n');
            }
        }
        tails
    }

    /// Every socket this cluster's processes listen on (the daemons, job steps, srun, MPI ranks) is on 127.0.0.1
    /// (`ss`, from iproute2): with `auth/none`, a daemon listening on another interface would run anyone's jobs.
    /// Returns the names of the programs seen listening.
    pub fn assert_loopback_only(&self) -> Vec<String> {
        let listing = text(Command::new("ss").args(["-Hltnp"]).output().expect("ss"));
        let ours = marked_processes(&self.marker);
        let mut programs = Vec::new();
        for line in listing.lines() {
            let Some(local) = line.split_whitespace().nth(3) else {
                continue;
            };
            // users:(("slurmd",pid=123,fd=5),...)
            let owners: Vec<(String, i32)> = line
                .split("((\"")
                .nth(1)
                .map(|users| {
                    users
                        .split("),(\"")
                        .filter_map(|u| {
                            let name = u.split('"').next()?.to_string();
                            let pid = u.split("pid=").nth(1)?.split(',').next()?.parse().ok()?;
                            Some((name, pid))
                        })
                        .collect()
                })
                .unwrap_or_default();
            for (name, pid) in owners {
                if ours.contains(&pid) {
                    assert!(
                        local.starts_with("127.0.0.1:"),
                        "{name} (pid {pid}) listens on {local}, beyond loopback:\n{listing}"
                    );
                    if !programs.contains(&name) {
                        programs.push(name);
                    }
                }
            }
        }
        for daemon in ["slurmctld", "slurmd"] {
            assert!(
                programs.iter().any(|p| p == daemon),
                "{daemon} listens nowhere:\n{listing}"
            );
        }
        programs
    }
}

impl Drop for Cluster {
    /// Cancel every job and wait (at most 30 s) until none is left; then end the namespace, and with it the
    /// daemons and anything a job left.
    fn drop(&mut self) {
        let _ = self.try_command("scancel", &["--full", "--user", &whoami()]);
        let started = Instant::now();
        while started.elapsed() < Duration::from_secs(30) {
            let out = self.try_command("squeue", &["-h", "-o", "%i"]);
            if !out.status.success() || text(out).trim().is_empty() {
                break;
            }
            std::thread::sleep(Duration::from_millis(200));
        }
        let namespace = self.find_namespace();
        let _ = self.namespace.kill();
        let _ = self.namespace.wait();
        // The kernel kills the namespace's other processes once its first is gone, but not at once (a loaded
        // machine took long enough for a test to see them): wait, at most 10 s, until none is left, so that whoever
        // dropped the cluster finds nothing of it running.
        let started = Instant::now();
        while started.elapsed() < Duration::from_secs(10)
            && !(marked_processes(&self.marker).is_empty()
                && namespace
                    .as_deref()
                    .is_none_or(|ns| processes_in_namespace(ns).is_empty()))
        {
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

/// Have the kernel kill the process started by `command` when the thread that started it dies.
fn die_with_parent(command: &mut Command) {
    // SAFETY: prctl is async-signal-safe, and nothing else runs between fork and exec.
    unsafe {
        command.pre_exec(|| {
            libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
            Ok(())
        });
    }
}

/// The live processes (not zombies) whose environment holds `MARKER=marker`.
pub fn marked_processes(marker: &str) -> Vec<i32> {
    let mark = format!("{MARKER}={marker}");
    live_processes(|pid| {
        std::fs::read(format!("/proc/{pid}/environ"))
            .is_ok_and(|env| env.split(|&b| b == 0).any(|v| v == mark.as_bytes()))
    })
}

/// The live processes in PID namespace `namespace` ([`Cluster::namespace`]).
pub fn processes_in_namespace(namespace: &str) -> Vec<i32> {
    live_processes(|pid| {
        std::fs::read_link(format!("/proc/{pid}/ns/pid"))
            .is_ok_and(|link| link.display().to_string() == namespace)
    })
}

/// The live processes (not zombies) for which `wanted` holds.
fn live_processes(wanted: impl Fn(i32) -> bool) -> Vec<i32> {
    let mut found = Vec::new();
    let Ok(entries) = std::fs::read_dir("/proc") else {
        return found;
    };
    for entry in entries.flatten() {
        let Ok(pid) = entry.file_name().to_string_lossy().parse::<i32>() else {
            continue;
        };
        let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else {
            continue;
        };
        // pid (comm) state ...: comm may hold spaces, so read the state after its closing parenthesis.
        if stat
            .rsplit_once(')')
            .and_then(|(_, r)| r.split_whitespace().next())
            == Some("Z")
        {
            continue;
        }
        if wanted(pid) {
            found.push(pid);
        }
    }
    found
}

fn whoami() -> String {
    text(Command::new("id").arg("-un").output().expect("id"))
        .trim()
        .to_string()
}

fn text(out: Output) -> String {
    String::from_utf8_lossy(&out.stdout).into_owned()
}

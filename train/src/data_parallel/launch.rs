//! Where a fit's ranks come from: the launcher's environment, checked against MPI's own count. A launcher that
//! says N > 1 processes while MPI says 1 (`srun --mpi=none`, a binary built without the `mpi` feature, a
//! `torchrun`) would have N unrelated copies train into one directory: refused in one line.

use anyhow::{bail, Context, Result};

use super::Ranks;

/// The launcher variables that count a job's processes, and who sets them.
const LAUNCHER_WORLDS: [(&str, &str); 4] = [
    ("OMPI_COMM_WORLD_SIZE", "mpirun"),
    ("PMIX_SIZE", "a PMIx launcher"),
    ("SLURM_NTASKS", "Slurm"),
    ("WORLD_SIZE", "torchrun"),
];

/// Variables only an MPI launcher sets: `mpirun`'s, and PMIx's or PMI's (`srun --mpi=pmix|pmi2`).
#[cfg(feature = "mpi")]
const MPI_BOOTSTRAP: [&str; 3] = ["OMPI_COMM_WORLD_SIZE", "PMIX_RANK", "PMI_RANK"];

/// Reads a process's environment (a closure in tests).
pub type LaunchEnv<'a> = &'a dyn Fn(&str) -> Option<String>;

/// The largest process count a launcher variable states, with the variable, if any says more than one.
fn launcher_world(env: LaunchEnv) -> Result<Option<(usize, &'static str, &'static str)>> {
    let mut most = None;
    for (variable, launcher) in LAUNCHER_WORLDS {
        let Some(value) = env(variable) else { continue };
        let tasks: usize = value
            .trim()
            .parse()
            .with_context(|| format!("{variable}={value:?} is not a process count"))?;
        if tasks > 1 && most.is_none_or(|(n, _, _)| tasks > n) {
            most = Some((tasks, variable, launcher));
        }
    }
    Ok(most)
}

/// Refuse to run a command that is not data-parallel as one of several processes a launcher started: each would
/// do the same work into the same directory.
pub fn refuse_launcher_world(env: LaunchEnv, command: &str) -> Result<()> {
    if let Some((tasks, variable, launcher)) = launcher_world(env)? {
        bail!(
            "{launcher} started {tasks} processes ({variable}={tasks}), but {command} runs as one: start it as one \
             task (only `fit` trains across ranks)"
        );
    }
    Ok(())
}

/// This process's ranks: MPI's when the binary has the `mpi` feature and a launcher started it, else one rank.
/// `timeout` bounds every collective's wait (`--collective-timeout`).
pub fn launch(env: LaunchEnv, timeout: std::time::Duration) -> Result<Ranks> {
    let stated = launcher_world(env)?;
    #[cfg(feature = "mpi")]
    {
        // MPI is started only under an MPI launcher: a plain `g2r-train fit`, or `srun -n 1` on a site whose
        // default is `--mpi=none`, needs no MPI runtime (Open MPI aborts there).
        let bootstrap = MPI_BOOTSTRAP.iter().any(|v| env(v).is_some());
        if let (Some((tasks, variable, launcher)), false) = (stated, bootstrap) {
            // Several processes and no way for MPI to join them (`srun --mpi=none`): MPI_Init would abort each
            // with a page of its own text; say it in one line instead.
            bail!(
                "{launcher} started {tasks} processes ({variable}={tasks}) without an MPI bootstrap (no PMIx or \
                 mpirun in their environment), so they cannot join one fit: launch with `srun --mpi=pmix` or `mpirun`"
            );
        }
        if bootstrap {
            let ranks = super::mpi_world::join(timeout)?;
            if let Some((tasks, variable, launcher)) = stated {
                if ranks.world() != tasks {
                    bail!(
                        "{launcher} started {tasks} processes ({variable}={tasks}) but MPI joined {} of them: \
                         launch with `srun --mpi=pmix` or `mpirun` (a plain `srun --mpi=none` starts unrelated copies)",
                        ranks.world()
                    );
                }
            }
            return Ok(ranks);
        }
        Ok(Ranks::alone())
    }
    #[cfg(not(feature = "mpi"))]
    {
        let _ = timeout;
        if let Some((tasks, variable, launcher)) = stated {
            bail!(
                "{launcher} started {tasks} processes ({variable}={tasks}), but this g2r-train was built without \
                 MPI, so each would train its own copy: rebuild with `--features mpi` (docs/scale-out.md) or start \
                 one process"
            );
        }
        Ok(Ranks::alone())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn env(pairs: &'static [(&'static str, &'static str)]) -> impl Fn(&str) -> Option<String> {
        move |k: &str| {
            pairs
                .iter()
                .find(|(name, _)| *name == k)
                .map(|(_, v)| v.to_string())
        }
    }

    #[test]
    fn a_launcher_world_of_several_processes_is_refused_for_single_process_commands() {
        assert!(refuse_launcher_world(&env(&[]), "compare-models").is_ok());
        let one = env(&[("SLURM_NTASKS", "1"), ("WORLD_SIZE", "1")]);
        assert!(refuse_launcher_world(&one, "compare-models").is_ok());
        let err = refuse_launcher_world(&env(&[("SLURM_NTASKS", "4")]), "compare-models")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("Slurm started 4 processes") && err.contains("compare-models"),
            "{err}"
        );
        let err = refuse_launcher_world(
            &env(&[("WORLD_SIZE", "2"), ("OMPI_COMM_WORLD_SIZE", "3")]),
            "x",
        )
        .unwrap_err()
        .to_string();
        assert!(err.contains("mpirun started 3"), "{err}");
        assert!(refuse_launcher_world(&env(&[("WORLD_SIZE", "two")]), "x").is_err());
    }

    /// Without a launcher a fit is one rank and touches no MPI, with or without the feature.
    #[test]
    fn without_a_launcher_a_fit_is_one_rank() {
        let ranks = launch(&env(&[]), std::time::Duration::from_secs(1)).unwrap();
        assert_eq!((ranks.replica().rank, ranks.world()), (0, 1));
    }

    #[cfg(feature = "mpi")]
    #[test]
    fn several_tasks_without_an_mpi_bootstrap_are_refused_before_mpi_starts() {
        let err = launch(
            &env(&[("SLURM_NTASKS", "2"), ("SLURM_STEP_ID", "0")]),
            std::time::Duration::from_secs(1),
        )
        .err()
        .unwrap()
        .to_string();
        assert!(
            err.contains("Slurm started 2 processes") && err.contains("--mpi=pmix"),
            "{err}"
        );
    }

    #[cfg(not(feature = "mpi"))]
    #[test]
    fn a_launcher_world_without_mpi_is_refused() {
        let err = launch(
            &env(&[("SLURM_NTASKS", "2")]),
            std::time::Duration::from_secs(1),
        )
        .err()
        .unwrap()
        .to_string();
        assert!(err.contains("built without MPI"), "{err}");
    }
}

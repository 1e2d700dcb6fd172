//! The all-reduce on MPI (rsmpi over the site's MPI library). Tensors reach it through host memory: a GPU rank
//! copies its gradients down, sums them with the others' and copies the mean back up.

use anyhow::{bail, Result};
use mpi::collective::SystemOperation;
use mpi::environment::Universe;
use mpi::topology::SimpleCommunicator;
use mpi::traits::*;

use super::{Ranks, Replica, SumAllReduce};

struct MpiWorld {
    /// Finalises MPI when the fit's ranks are dropped.
    _universe: Universe,
    world: SimpleCommunicator,
}

impl SumAllReduce for MpiWorld {
    fn sum_f32(&self, values: &mut [f32]) {
        let local = values.to_vec();
        self.world
            .all_reduce_into(&local[..], values, SystemOperation::sum());
    }

    fn sum_f64(&self, values: &mut [f64]) {
        let local = values.to_vec();
        self.world
            .all_reduce_into(&local[..], values, SystemOperation::sum());
    }

    fn abort(&self, code: i32) -> ! {
        self.world.abort(code)
    }
}

/// Initialise MPI and join its world (once per process).
pub fn join(timeout: std::time::Duration) -> Result<Ranks> {
    // Funneled: only the training thread calls MPI; data loaders and the watchdog never do.
    let Some((universe, _threading)) = mpi::initialize_with_threading(mpi::Threading::Funneled)
    else {
        bail!("MPI was already initialised in this process: a fit joins MPI once");
    };
    let world = universe.world();
    let replica = Replica {
        rank: world.rank() as usize,
        world: world.size() as usize,
    };
    // The rank among those sharing this node's memory: which GPU of the node is this rank's.
    let local_rank = world.split_shared(world.rank()).rank() as usize;
    tracing::info!(
        rank = replica.rank,
        world = replica.world,
        local_rank,
        library = %mpi::environment::library_version().unwrap_or_default().lines().next().unwrap_or(""),
        "joined MPI"
    );
    if replica.world == 1 {
        return Ok(Ranks::alone());
    }
    Ok(Ranks::joined(
        replica,
        local_rank,
        Box::new(MpiWorld {
            _universe: universe,
            world,
        }),
        timeout,
    ))
}

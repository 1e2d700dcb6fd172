//! Data-parallel training in one process (`fit --replicas N`): one thread per replica, each on its own device,
//! each taking rank `r` of `N`'s stride of every epoch's rows ([`dataset::contract::planner`]), its gradients averaged with
//! the others' after every backward pass by burn-collective's all-reduce. Every replica starts from one network
//! (cloned, so parameter ids agree: the all-reduce pairs gradients by id), takes the same averaged step and so
//! holds the same weights and the same weight average; only the BatchNorm running statistics, which each replica
//! updates from its own batches, differ, and they are averaged before every validation and checkpoint. Replica 0
//! alone validates and writes.
//!
//! Across processes (Slurm tasks, `torchrun`) burn-collective 0.21 offers a global orchestrator, but its node
//! sync never clears the list of nodes that have synced (`global/node/sync.rs`), so the second all-reduce of a
//! session never returns; a fit is thousands of them. [`refuse_launcher_world`] stops a fit that a launcher
//! started as one of several processes, which would otherwise train several unrelated copies into one directory.

use anyhow::{bail, Context, Result};
use burn::collective::{
    all_reduce, finish_collective, register, reset_collective, CollectiveConfig, PeerId,
    ReduceOperation,
};
use burn::module::{ModuleMapper, Param};
use burn::optim::GradientsParams;
use burn::prelude::*;
use burn::tensor::backend::AutodiffBackend;
use burn::tensor::TensorPrimitive;

/// Which replica of a fit this is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Replica {
    pub rank: usize,
    pub world: usize,
}

impl Replica {
    /// The one replica of an ordinary fit: no collective calls at all.
    pub const SOLE: Self = Self { rank: 0, world: 1 };

    fn peer(self) -> PeerId {
        PeerId::from(self.rank)
    }

    /// Replica 0 validates, logs and writes checkpoints.
    pub fn leads(self) -> bool {
        self.rank == 0
    }

    /// Join the collective (a barrier: returns when every replica has joined). `B` is the inner backend, whose
    /// tensors the gradients are.
    pub fn join<B: Backend>(self, device: &B::Device) -> Result<()> {
        if self.world == 1 {
            return Ok(());
        }
        let config = CollectiveConfig::default().with_num_devices(self.world);
        register::<B>(self.peer(), device.clone(), config)
            .map_err(|e| anyhow::anyhow!("replica {} cannot join the all-reduce: {e:?}", self.rank))
    }

    /// Leave the collective at the end of a fit.
    pub fn leave<B: Backend>(self) -> Result<()> {
        if self.world == 1 {
            return Ok(());
        }
        finish_collective::<B>(self.peer()).map_err(|e| {
            anyhow::anyhow!("replica {} cannot leave the all-reduce: {e:?}", self.rank)
        })
    }

    /// The mean of every replica's gradients (`B` the inner backend).
    pub fn mean_gradients<B: Backend>(self, grads: GradientsParams) -> Result<GradientsParams> {
        if self.world == 1 {
            return Ok(grads);
        }
        grads
            .all_reduce::<B>(self.peer(), ReduceOperation::Mean)
            .map_err(|e| {
                anyhow::anyhow!("replica {}: gradient all-reduce failed: {e:?}", self.rank)
            })
    }

    /// The mean of a number over the replicas (the step's loss, so every replica logs and checks the same value).
    pub fn mean_scalar<B: Backend>(self, value: f64, device: &B::Device) -> Result<f64> {
        if self.world == 1 {
            return Ok(value);
        }
        let tensor = Tensor::<B, 1>::from_data(TensorData::new(vec![value], [1]), device);
        let mean = all_reduce::<B>(
            self.peer(),
            tensor.into_primitive().tensor(),
            ReduceOperation::Mean,
        )
        .map_err(|e| anyhow::anyhow!("replica {}: loss all-reduce failed: {e:?}", self.rank))?;
        let mean = Tensor::<B, 1>::from_primitive(TensorPrimitive::Float(mean));
        Ok(mean
            .into_data()
            .convert::<f64>()
            .to_vec::<f64>()
            .expect("f64")[0])
    }

    /// `module` with its BatchNorm running means and variances replaced by their mean over the replicas; every
    /// other tensor unchanged. For an autodiff module: the statistics go through the inner backend.
    pub fn mean_running_stats<A: AutodiffBackend, M: Module<A>>(self, module: M) -> Result<M> {
        self.map_running_stats::<A, A::InnerBackend, M>(module, Tensor::inner, Tensor::from_inner)
    }

    /// [`Replica::mean_running_stats`] for a module on the inner backend itself (the weight average).
    pub fn mean_running_stats_inner<B: Backend, M: Module<B>>(self, module: M) -> Result<M> {
        self.map_running_stats::<B, B, M>(module, |t| t, |t| t)
    }

    fn map_running_stats<B: Backend, C: Backend, M: Module<B>>(
        self,
        module: M,
        to_collective: fn(Tensor<B, 1>) -> Tensor<C, 1>,
        from_collective: fn(Tensor<C, 1>) -> Tensor<B, 1>,
    ) -> Result<M> {
        if self.world == 1 {
            return Ok(module);
        }
        let mut mapper = RunningStatMean {
            replica: self,
            path: Vec::new(),
            error: None,
            to_collective,
            from_collective,
        };
        let module = module.map(&mut mapper);
        match mapper.error {
            Some(e) => Err(e),
            None => Ok(module),
        }
    }
}

/// Averages the tensors under fields named `running_mean` / `running_var` (Burn's BatchNorm) over the replicas,
/// in the order the module lists them: the same on every replica, as the all-reduce needs. `C` is the backend
/// the collective runs on.
struct RunningStatMean<B: Backend, C: Backend> {
    replica: Replica,
    path: Vec<String>,
    error: Option<anyhow::Error>,
    to_collective: fn(Tensor<B, 1>) -> Tensor<C, 1>,
    from_collective: fn(Tensor<C, 1>) -> Tensor<B, 1>,
}

impl<B: Backend, C: Backend> ModuleMapper<B> for RunningStatMean<B, C> {
    fn enter_module(&mut self, name: &str, _container_type: &str) {
        self.path.push(name.to_string());
    }

    fn exit_module(&mut self, _name: &str, _container_type: &str) {
        self.path.pop();
    }

    fn map_float<const D: usize>(&mut self, param: Param<Tensor<B, D>>) -> Param<Tensor<B, D>> {
        let running = matches!(
            self.path.last().map(String::as_str),
            Some("running_mean" | "running_var")
        );
        if !running || self.error.is_some() {
            return param;
        }
        let (id, tensor, mapper) = param.consume();
        let shape = tensor.shape();
        let flat = (self.to_collective)(tensor.reshape([shape.num_elements()]));
        let mean = all_reduce::<C>(
            self.replica.peer(),
            flat.clone().into_primitive().tensor(),
            ReduceOperation::Mean,
        );
        let flat = match mean {
            Ok(mean) => Tensor::from_primitive(TensorPrimitive::Float(mean)),
            Err(e) => {
                self.error = Some(anyhow::anyhow!(
                    "replica {}: BatchNorm statistics all-reduce failed: {e:?}",
                    self.replica.rank
                ));
                flat
            }
        };
        Param::from_mapped_value(id, (self.from_collective)(flat).reshape(shape), mapper)
    }
}

/// Clear what an earlier fit in this process left in the collective (a test binary runs several).
pub fn reset<B: Backend>() {
    reset_collective::<B>();
}

/// Refuse to run as one of several processes a launcher started (Slurm's `SLURM_NTASKS`, `torchrun`'s
/// `WORLD_SIZE`): each would train its own copy into the same run directory.
pub fn refuse_launcher_world(env: impl Fn(&str) -> Option<String>) -> Result<()> {
    for (variable, launcher) in [("SLURM_NTASKS", "Slurm"), ("WORLD_SIZE", "torchrun")] {
        let Some(value) = env(variable) else { continue };
        let tasks: usize = value
            .trim()
            .parse()
            .with_context(|| format!("{variable}={value:?} is not a task count"))?;
        if tasks > 1 {
            bail!(
                "{launcher} started {tasks} processes ({variable}={tasks}), but g2r-train trains data-parallel only \
                 within one process (burn-collective 0.21's multi-node all-reduce hangs after its first call): \
                 start one task per node with --replicas N (docs/scale-out.md)"
            );
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_launcher_world_of_several_processes_is_refused_and_one_is_accepted() {
        let env = |pairs: &'static [(&'static str, &'static str)]| {
            move |k: &str| {
                pairs
                    .iter()
                    .find(|(name, _)| *name == k)
                    .map(|(_, v)| v.to_string())
            }
        };
        assert!(refuse_launcher_world(env(&[])).is_ok());
        assert!(refuse_launcher_world(env(&[("SLURM_NTASKS", "1"), ("WORLD_SIZE", "1")])).is_ok());
        let err = refuse_launcher_world(env(&[("SLURM_NTASKS", "4")]))
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("Slurm started 4 processes") && err.contains("--replicas"),
            "{err}"
        );
        let err = refuse_launcher_world(env(&[("WORLD_SIZE", "2")]))
            .unwrap_err()
            .to_string();
        assert!(err.contains("torchrun"), "{err}");
        assert!(refuse_launcher_world(env(&[("WORLD_SIZE", "two")])).is_err());
    }
}

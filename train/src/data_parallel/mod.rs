//! Data-parallel training across processes: one process per device, launched by `mpirun` or `srun --mpi=pmix`,
//! its rank and world size from MPI ([`launch`]). Each rank takes its stride of every epoch's rows
//! ([`dataset::contract::planner`]); after every backward pass the ranks' gradients are averaged by one all-reduce
//! over host memory ([`Ranks::mean_gradients`]). Every rank starts from the same checkpoint (or the same seeded
//! initialisation), takes the same averaged step and so holds the same weights and weight average; only the
//! BatchNorm running statistics, which each rank updates from its own batches, differ, and they are averaged
//! before every validation and checkpoint. Rank 0 alone validates and writes.
//!
//! Every collective runs under a watchdog (`watchdog`): a rank that waits longer than `--collective-timeout`
//! (a peer hung, or stopped) logs which collective at which step and exits non-zero, and the launcher ends the
//! rest. A rank that dies is the launcher's to notice (`mpirun` aborts the job; `srun -K1`).

mod launch;
#[cfg(feature = "mpi")]
mod mpi_world;
mod watchdog;

pub use launch::{launch, refuse_launcher_world, LaunchEnv};

use anyhow::Result;
use burn::module::{AutodiffModule, ModuleMapper, ModuleVisitor, Param, ParamId};
use burn::optim::GradientsParams;
use burn::prelude::*;
use burn::tensor::backend::AutodiffBackend;

use watchdog::Watchdog;

/// Which rank of a data-parallel fit this process is: which stride of every epoch's rows it reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Replica {
    pub rank: usize,
    pub world: usize,
}

impl Replica {
    /// The one rank of an ordinary fit.
    pub const SOLE: Self = Self { rank: 0, world: 1 };

    /// Rank 0 validates, logs and writes checkpoints.
    pub fn leads(self) -> bool {
        self.rank == 0
    }
}

/// The element-wise sum over every rank, in place (the same length on every rank, in the same call order).
/// Blocking; an implementation may not return when a peer is gone, which is what the watchdog is for.
pub trait SumAllReduce {
    fn sum_f32(&self, values: &mut [f32]);
    fn sum_f64(&self, values: &mut [f64]);
    /// End every rank of the job with `code` (the others may be waiting in an all-reduce this rank never joins).
    fn abort(&self, code: i32) -> !;
}

/// This process's place in a data-parallel fit and the all-reduce that joins it to the other ranks.
pub struct Ranks {
    replica: Replica,
    /// The device index on this node (a GPU per rank).
    local_rank: usize,
    reduce: Option<Box<dyn SumAllReduce>>,
    watchdog: Option<Watchdog>,
}

impl Ranks {
    /// An ordinary fit: one rank, no collective at all.
    pub fn alone() -> Self {
        Self {
            replica: Replica::SOLE,
            local_rank: 0,
            reduce: None,
            watchdog: None,
        }
    }

    /// `world` ranks joined by `reduce`, each collective guarded by a watchdog of `timeout`.
    pub fn joined(
        replica: Replica,
        local_rank: usize,
        reduce: Box<dyn SumAllReduce>,
        timeout: std::time::Duration,
    ) -> Self {
        Self {
            replica,
            local_rank,
            reduce: Some(reduce),
            watchdog: Some(Watchdog::start(replica, timeout)),
        }
    }

    pub fn replica(&self) -> Replica {
        self.replica
    }

    pub fn world(&self) -> usize {
        self.replica.world
    }

    pub fn leads(&self) -> bool {
        self.replica.leads()
    }

    /// End the job after this rank failed with `error`: alone, return it; among ranks, print it and abort every
    /// rank (the others would wait for this one in their next all-reduce), without writing anything more.
    pub fn end_on_error(&self, error: anyhow::Error) -> anyhow::Error {
        let Some(reduce) = &self.reduce else {
            return error;
        };
        eprintln!(
            "error: rank {} of {}: {error:#}",
            self.replica.rank, self.replica.world
        );
        reduce.abort(1)
    }

    /// This rank's device index on its node.
    pub fn local_rank(&self) -> usize {
        self.local_rank
    }

    /// The mean over the ranks of `values`, in place; `what` and `step` name the collective for the watchdog.
    fn mean_f32(&self, values: &mut [f32], what: &'static str, step: u64) {
        let Some(reduce) = &self.reduce else { return };
        let _guard = self.watchdog.as_ref().map(|w| w.guard(what, step));
        reduce.sum_f32(values);
        let world = self.replica.world as f32;
        values.iter_mut().for_each(|v| *v /= world);
    }

    /// The mean of a number over the ranks (the step's loss, so every rank logs and checks the same value).
    pub fn mean_scalar(&self, value: f64, what: &'static str, step: u64) -> f64 {
        let Some(reduce) = &self.reduce else {
            return value;
        };
        let _guard = self.watchdog.as_ref().map(|w| w.guard(what, step));
        let mut values = [value];
        reduce.sum_f64(&mut values);
        values[0] / self.replica.world as f64
    }

    /// Wait for every rank (e.g. for the lead's validation and checkpoint), under the watchdog.
    pub fn barrier(&self, what: &'static str, step: u64) {
        let _ = self.mean_scalar(0.0, what, step);
    }

    /// The mean of every rank's gradients: all of `module`'s gradients flattened into one host buffer, in the
    /// order the module lists its parameters (the same on every rank), and averaged by one all-reduce.
    pub fn mean_gradients<B: AutodiffBackend, M: AutodiffModule<B>>(
        &self,
        module: &M,
        grads: GradientsParams,
        step: u64,
    ) -> Result<GradientsParams> {
        if self.reduce.is_none() {
            return Ok(grads);
        }
        let mut gather = GatherGradients::<B> {
            grads,
            flat: Vec::new(),
            parts: Vec::new(),
            device: None,
        };
        module.visit(&mut gather);
        let GatherGradients {
            mut grads,
            mut flat,
            parts,
            device,
        } = gather;
        self.mean_f32(&mut flat, "gradients", step);
        let Some(device) = device else {
            return Ok(grads);
        };
        let mut offset = 0;
        for part in parts {
            let len: usize = part.shape.iter().product();
            let data = TensorData::new(flat[offset..offset + len].to_vec(), part.shape.clone());
            offset += len;
            part.register(&mut grads, data, &device);
        }
        Ok(grads)
    }

    /// `module` with its BatchNorm running means and variances replaced by their mean over the ranks; every other
    /// tensor unchanged. For an autodiff module the statistics go through the inner backend.
    pub fn mean_running_stats<B: Backend, M: Module<B>>(&self, module: M, step: u64) -> M {
        if self.reduce.is_none() {
            return module;
        }
        let mut mapper = RunningStatMean {
            ranks: self,
            path: Vec::new(),
            step,
        };
        module.map(&mut mapper)
    }
}

/// One gradient tensor's place in the flat buffer, and how to put it back.
struct GradientPart<B: Backend> {
    shape: Vec<usize>,
    /// `register_gradient` at the tensor's rank, which the visitor knew and the buffer forgets.
    put_back: fn(&mut GradientsParams, ParamId, TensorData, &B::Device),
    id: ParamId,
}

impl<B: Backend> GradientPart<B> {
    fn register(self, grads: &mut GradientsParams, data: TensorData, device: &B::Device) {
        (self.put_back)(grads, self.id, data, device)
    }
}

fn register_gradient<B: Backend, const D: usize>(
    grads: &mut GradientsParams,
    id: ParamId,
    data: TensorData,
    device: &B::Device,
) {
    grads.register::<B, D>(id, Tensor::from_data(data, device));
}

/// Takes every gradient out of a `GradientsParams` into one host buffer, in module order.
struct GatherGradients<B: AutodiffBackend> {
    grads: GradientsParams,
    flat: Vec<f32>,
    parts: Vec<GradientPart<B::InnerBackend>>,
    device: Option<burn::tensor::Device<B::InnerBackend>>,
}

impl<B: AutodiffBackend> ModuleVisitor<B> for GatherGradients<B> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) {
        let Some(grad) = self.grads.remove::<B::InnerBackend, D>(param.id) else {
            return;
        };
        self.device.get_or_insert_with(|| grad.device());
        let shape = grad.dims().to_vec();
        let values = grad
            .into_data()
            .convert::<f32>()
            .into_vec::<f32>()
            .expect("f32 gradient");
        self.flat.extend_from_slice(&values);
        self.parts.push(GradientPart {
            shape,
            put_back: register_gradient::<B::InnerBackend, D>,
            id: param.id,
        });
    }
}

/// Averages the tensors under fields named `running_mean` / `running_var` (Burn's BatchNorm) over the ranks, in
/// the order the module lists them: the same on every rank, as the all-reduce needs.
struct RunningStatMean<'a> {
    ranks: &'a Ranks,
    path: Vec<String>,
    step: u64,
}

impl<B: Backend> ModuleMapper<B> for RunningStatMean<'_> {
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
        if !running {
            return param;
        }
        let (id, tensor, mapper) = param.consume();
        let shape = tensor.shape();
        let device = tensor.device();
        let mut values = tensor
            .into_data()
            .convert::<f32>()
            .into_vec::<f32>()
            .expect("f32 statistics");
        self.ranks
            .mean_f32(&mut values, "BatchNorm statistics", self.step);
        let mean = Tensor::from_data(TensorData::new(values, shape), &device);
        Param::from_mapped_value(id, mean, mapper)
    }
}

//! Which Burn backend runs a job: the `--backend` choice, and [`with_backend!`](crate::with_backend) binding a
//! type to it, one arm per backend this build compiled.

/// A backend `g2r-train` can run on.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum BackendKind {
    /// Burn's CPU backend (always built).
    Flex,
    /// NVIDIA GPU (build with `--features cuda`; needs only the driver at run time).
    Cuda,
    /// Any GPU wgpu reaches: Vulkan, Metal or DX12 (build with `--features wgpu`). The same CubeCL operations as
    /// CUDA; on Mesa's software Vulkan (lavapipe) a CPU runs them, slowly: a check of the GPU path, not a speed.
    Wgpu,
}

impl BackendKind {
    /// The name `--backend` takes and reports carry.
    pub fn name(self) -> &'static str {
        match self {
            Self::Flex => "flex",
            Self::Cuda => "cuda",
            Self::Wgpu => "wgpu",
        }
    }

    /// Where the PyTorch peer of `bench --torch` runs to compare like with like.
    pub fn torch_device(self) -> &'static str {
        match self {
            Self::Flex => "cpu",
            Self::Cuda => "cuda",
            // PyTorch has no wgpu device: on an NVIDIA card compare with `--backend cuda`; elsewhere the CPU.
            Self::Wgpu => "cpu",
        }
    }
}

/// What asking for a backend this build left out (CUDA or wgpu) says.
pub fn not_built(kind: BackendKind) -> anyhow::Error {
    let name = kind.name();
    anyhow::anyhow!(
        "this g2r-train was built without {name}: rebuild with `cargo build --release -p g2r-train --features {name}`"
    )
}

/// Whether the NVIDIA driver library loads, checked before the first CUDA call: cudarc loads it lazily on a
/// worker thread and panics there with a backtrace when it is missing (a machine without an NVIDIA driver).
/// The names are the first ones cudarc itself tries.
#[cfg(feature = "cuda")]
pub fn cuda_driver() -> anyhow::Result<()> {
    let names: &[&str] = if cfg!(windows) {
        &["nvcuda.dll"]
    } else {
        &["libcuda.so", "libcuda.so.1"]
    };
    let mut last = String::new();
    for name in names {
        // SAFETY: loading the driver runs only its library initialisers, as cudarc's own load of it does next; no
        // symbol is called through this handle, which is dropped at once.
        match unsafe { libloading::Library::new(name) } {
            Ok(_) => return Ok(()),
            Err(e) => last = format!("{name}: {e}"),
        }
    }
    Err(anyhow::anyhow!(
        "--backend cuda: cannot load the NVIDIA driver ({last}); run on a machine with an NVIDIA GPU and its \
         driver, or add the driver's folder to LD_LIBRARY_PATH"
    ))
}

/// The inference backend under an autodiff backend `B`.
pub type Inner<B> = <B as burn::tensor::backend::AutodiffBackend>::InnerBackend;

/// Evaluate `$body` (a `Result`) with `$B` bound to the chosen autodiff backend (a [`BackendKind`]): one arm per
/// compiled backend; CUDA or wgpu in a build without its feature is an error ([`not_built`]).
#[macro_export]
macro_rules! with_backend {
    ($kind:expr, $B:ident => $body:expr) => {
        match $kind {
            $crate::backend::BackendKind::Flex => {
                type $B = burn::backend::Autodiff<burn::backend::Flex>;
                $body
            }
            #[cfg(feature = "cuda")]
            $crate::backend::BackendKind::Cuda => match $crate::backend::cuda_driver() {
                Err(e) => Err(e),
                Ok(()) => {
                    type $B = burn::backend::Autodiff<burn::backend::Cuda>;
                    $body
                }
            },
            #[cfg(not(feature = "cuda"))]
            $crate::backend::BackendKind::Cuda => Err($crate::backend::not_built(
                $crate::backend::BackendKind::Cuda,
            )),
            #[cfg(feature = "wgpu")]
            $crate::backend::BackendKind::Wgpu => {
                type $B = burn::backend::Autodiff<burn::backend::Wgpu>;
                $body
            }
            #[cfg(not(feature = "wgpu"))]
            $crate::backend::BackendKind::Wgpu => Err($crate::backend::not_built(
                $crate::backend::BackendKind::Wgpu,
            )),
        }
    };
}

/// The device of a data-parallel fit's rank, from its index among the ranks on its node.
pub trait RankDevice: burn::tensor::backend::Backend {
    fn rank_device(local_rank: usize) -> Self::Device;
}

/// The CPU: each rank a process on its share of the cores.
impl RankDevice for burn::backend::Autodiff<burn::backend::Flex> {
    fn rank_device(_local_rank: usize) -> Self::Device {
        Default::default()
    }
}

/// The node's GPU `local_rank` (CUDA ordinal): one GPU per rank.
#[cfg(feature = "cuda")]
impl RankDevice for burn::backend::Autodiff<burn::backend::Cuda> {
    fn rank_device(local_rank: usize) -> Self::Device {
        burn::backend::cuda::CudaDevice { index: local_rank }
    }
}

/// wgpu's default adapter for every rank: adapters are not numbered alike on every platform.
#[cfg(feature = "wgpu")]
impl RankDevice for burn::backend::Autodiff<burn::backend::Wgpu> {
    fn rank_device(_local_rank: usize) -> Self::Device {
        Default::default()
    }
}

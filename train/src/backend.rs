//! Which Burn backend runs a job: the `--backend` choice, and [`with_backend!`](crate::with_backend) binding a
//! type to it, one arm per backend this build compiled.

/// A backend `g2r-train` can run on.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum BackendKind {
    /// Burn's CPU backend (always built).
    Flex,
    /// NVIDIA GPU (build with `--features cuda`; needs only the driver at run time).
    Cuda,
}

impl BackendKind {
    /// The name `--backend` takes and reports carry.
    pub fn name(self) -> &'static str {
        match self {
            Self::Flex => "flex",
            Self::Cuda => "cuda",
        }
    }

    /// Where the PyTorch peer of `bench --torch` runs to compare like with like.
    pub fn torch_device(self) -> &'static str {
        match self {
            Self::Flex => "cpu",
            Self::Cuda => "cuda",
        }
    }
}

/// What asking for CUDA from a build without it says.
pub fn no_cuda() -> anyhow::Error {
    anyhow::anyhow!(
        "this g2r-train was built without CUDA: rebuild with `cargo build --release -p g2r-train --features cuda`"
    )
}

/// The inference backend under an autodiff backend `B`.
pub type Inner<B> = <B as burn::tensor::backend::AutodiffBackend>::InnerBackend;

/// Evaluate `$body` (a `Result`) with `$B` bound to the chosen autodiff backend (a [`BackendKind`]): one arm per
/// compiled backend; CUDA in a build without the `cuda` feature is an error ([`no_cuda`]).
#[macro_export]
macro_rules! with_backend {
    ($kind:expr, $B:ident => $body:expr) => {
        match $kind {
            $crate::backend::BackendKind::Flex => {
                type $B = burn::backend::Autodiff<burn::backend::Flex>;
                $body
            }
            #[cfg(feature = "cuda")]
            $crate::backend::BackendKind::Cuda => {
                type $B = burn::backend::Autodiff<burn::backend::Cuda>;
                $body
            }
            #[cfg(not(feature = "cuda"))]
            $crate::backend::BackendKind::Cuda => Err($crate::backend::no_cuda()),
        }
    };
}

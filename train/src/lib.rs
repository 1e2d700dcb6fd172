//! `train`: the Burn side. Read in data-flow order:
//! - [`data`] (shards → host batches, epoch order, prefetch) with [`augment`];
//! - [`model`] (U-Net, its hot operations in [`kernels`]) → [`renderer_layer`] (the differentiable renderer layer,
//!   the batched twin of `dataset::science::brdf`) → [`metrics`];
//! - [`training`] (the fit loop; every model under one budget in [`model_comparison`]) writing a run directory ([`run_dir`]: history, checkpoints, loading; what defines
//!   the run in [`fit_config`]), with
//!   [`weight_average`] and [`uniform_fit`] (uniform least-squares fits of a model);
//! - [`prediction`] (inference-mode renderings, symmetry means, ensembles), with [`crater_level`] (each crater
//!   crop's brightness level, fitted beside an H1 run by [`crater_level_fit`]) → [`evaluation`] (against baselines,
//!   [`baseline`], and the oracle; [`feature_matching`]) and [`inference`] (parameter GeoTIFFs from a DEM);
//! - [`data_parallel`]: fits across MPI ranks (`mpirun`, `srun --mpi=pmix`) over the same loop;
//! - [`report`] (speed against error), [`mod@bench`];
//! - [`synthetic`] crops with a known answer (for `bench`; test fixtures behind the `testing` feature);
//!   [`backend`]: which Burn backend a job runs on.

/// Names for enums chosen on command lines and in configs: `NAMES[i]` is `ALL[i]`'s, and `FromStr` accepts them.
macro_rules! named_enum {
    ($ty:ident { $($variant:ident => $name:literal),+ $(,)? }) => {
        impl $ty {
            pub const ALL: &'static [$ty] = &[$($ty::$variant),+];
            pub const NAMES: &'static [&'static str] = &[$($name),+];

            pub fn name(self) -> &'static str {
                match self {
                    $($ty::$variant => $name),+
                }
            }
        }

        impl std::str::FromStr for $ty {
            type Err = String;
            fn from_str(text: &str) -> Result<Self, String> {
                Self::ALL
                    .iter()
                    .copied()
                    .find(|v| v.name() == text)
                    .ok_or_else(|| format!("unknown value '{text}': use one of {}", Self::NAMES.join(", ")))
            }
        }
    };
}

pub mod augment;
pub mod backend;
pub mod baseline;
pub mod bench;
pub mod crater_level;
pub mod crater_level_fit;
pub mod data;
pub mod data_parallel;
pub mod evaluation;
pub mod feature_matching;
pub mod fit_config;
pub mod inference;
pub mod kernels;
pub mod metrics;
pub mod model;
pub mod model_comparison;
pub mod prediction;
pub mod renderer_layer;
pub mod uniform_fit;
pub mod weight_average;

pub mod report;
pub mod run_dir;
pub mod synthetic;
#[cfg(any(test, feature = "testing"))]
pub mod testing;
pub mod training;

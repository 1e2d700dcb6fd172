//! `pipeline`: the stages that turn a lunar DEM + orthoimages into DEM–image pair shards, and the synthetic
//! lunar world that stands in for real LRO data here: [`manifest`] (its inputs local or fetched from object
//! storage by [`inputs`]) → [`stages`] run by [`runner`], in one process or as
//! [`partition`]s merged at the end (on machines without a shared file system, through an object-storage
//! [`exchange`]); the world is in
//! [`synth`]. [`jobs`] is what each command of the `g2r-pipeline` binary does, so the binary only parses.

pub mod exchange;
pub mod import;
pub mod inputs;
pub mod jobs;
pub mod manifest;
pub mod partition;
/// Keyed ChaCha streams live in the data contract (the trainer's epoch planner uses them too).
pub use dataset::contract::rng;
pub mod runner;
pub mod stages;
pub mod synth;

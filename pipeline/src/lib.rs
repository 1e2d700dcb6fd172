//! `pipeline`: the stages that turn a lunar DEM + orthoimages into DEM–image pair shards, and the synthetic
//! lunar world that stands in for real LRO data here. Stages arrive with the pipeline issue; the world is in [`synth`].

pub mod rng;
pub mod runner;
pub mod stages;
pub mod synth;

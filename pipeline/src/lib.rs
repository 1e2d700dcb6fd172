//! `pipeline`: the stages that turn a lunar DEM + orthoimages into DEM–image pair shards, and the synthetic
//! lunar world that stands in for real LRO data here: [`manifest`] → [`stages`] run by [`runner`]; the world is in
//! [`synth`].

pub mod manifest;
pub mod rng;
pub mod runner;
pub mod stages;
pub mod synth;

//! Pipeline stages (DESIGN §7). Built so far: the erosion, sampling, projection and split algorithms; the runner, file IO and the
//! ingest / project / split / publish stages follow in the pipeline issue.

pub mod erode;
pub mod project;
pub mod sample;
pub mod split;

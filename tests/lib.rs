//! Workspace-level integration tests live in `tests/*.rs` next to this file:
//! - `world_credibility.rs`: the demo world against lunar facts (SFD slope, d/D, shadows, brightness vs DEM R²)
//!   and GDAL georeferencing;
//! - `world_reproducible.rs`: same config + seed ⇒ byte-identical files; bad worlds are refused;
//! - `shard_interop.rs`: shards read back with pyarrow and no custom code.

//! Workspace-level integration tests live in `tests/*.rs` next to this file:
//! - `world_credibility.rs`: the demo world against lunar facts (SFD slope, d/D, shadows, brightness vs DEM R²)
//!   and GDAL georeferencing;
//! - `world_reproducible.rs`: same config + seed ⇒ byte-identical files; bad worlds are refused;
//! - `shard_interop.rs`: shards read back with pyarrow and no custom code;
//! - `pipeline_e2e.rs`: the stage pipeline on a tiny world: reproducible bytes, incremental runs, readers.

/// The tiny world of `pipeline::synth::config::tiny` (4 × 4 km, three strips).
pub fn tiny_world_config() -> pipeline::synth::WorldConfig {
    pipeline::synth::config::tiny()
}

/// The interpreter with pyarrow/polars: $G2R_PYTHON, else the project's .venv (made by .ci/setup), else python3.
pub fn python() -> std::path::PathBuf {
    if let Some(p) = std::env::var_os("G2R_PYTHON") {
        return p.into();
    }
    let venv = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../.venv/bin/python");
    if venv.exists() {
        venv
    } else {
        "python3".into()
    }
}

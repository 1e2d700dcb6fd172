//! Workspace-level integration tests live in `tests/*.rs` next to this file:
//! - `world_credibility.rs`: the demo world against lunar facts (SFD slope, d/D, shadows, brightness vs DEM R²)
//!   and GDAL georeferencing;
//! - `world_reproducible.rs`: same config + seed ⇒ byte-identical files; bad worlds are refused;
//! - `shard_interop.rs`: shards read back with pyarrow and no custom code;
//! - `pipeline_e2e.rs`: the stage pipeline on a tiny world: reproducible bytes, incremental runs, readers.

use pipeline::synth::{config, WorldConfig};

/// A tiny world (4 × 4 km, three 2 km strips, no complex crater): generates in seconds.
pub fn tiny_world_config() -> WorldConfig {
    let mut cfg = WorldConfig::from_toml(config::preset("demo").expect("demo preset"))
        .expect("demo preset parses");
    cfg.world.width_m = 4000.0;
    cfg.world.height_m = 4000.0;
    cfg.terrain.crater_max_diameter_m = 300.0;
    cfg.terrain.fbm_largest_wavelength_m = 2000.0;
    cfg.complex_crater = None;
    cfg.acquisitions.count = 3;
    cfg.acquisitions.strip_width_m = 2000.0;
    cfg
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

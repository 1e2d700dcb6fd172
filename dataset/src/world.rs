//! The synthetic world's directory layout: one home for the paths that `g2r-pipeline synth` writes and that
//! evaluation (the oracle rows) and the tests read. Paths are relative to the world directory.

/// The delivered DEM (what a real user has).
pub const DEM: &str = "dem/dem.tif";
/// Orthoimages (`{ID}.tif`) and their acquisition metadata (`{ID}.json`).
pub const ORTHO_DIR: &str = "ortho";
/// Each ortho's geometry as USGS ALE image support data (`{ID}.json`).
pub const ISD_DIR: &str = "isd";
/// The orthos' rows of an LROC-style cumulative index, and its PDS3 label.
pub const INDEX_TABLE: &str = "index/CUMINDEX.TAB";
pub const INDEX_LABEL: &str = "index/CUMINDEX.LBL";
/// The true fine DEM (evaluation only).
pub const TRUE_DEM: &str = "truth/dem_true.tif";
/// The true Hapke parameter maps: w, b, c, B_S0, h_S, θ̄ in degrees (evaluation only).
pub const TRUE_HAPKE: &str = "truth/hapke_params.tif";
/// w without its independent albedo component, on the Hapke maps' grid (evaluation only).
pub const TRUE_W_MORPHOLOGY: &str = "truth/w_morphology.tif";
/// The crater catalogue (evaluation only).
pub const TRUE_CRATERS: &str = "truth/craters.json";
/// The world's manifest: config echo, grids, per-ortho facts, every file with its blake3.
pub const MANIFEST: &str = "world.json";

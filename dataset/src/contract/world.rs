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
/// A mare (0) / highland (1) unit map on its own grid (`[unit_map]` worlds only): delivered, not truth, as coarse
/// and displaced as a real site's; the pipeline reads it as `inputs.unit_map`.
pub const UNIT_MAP: &str = "map/units.tif";
/// The true fine DEM (evaluation only).
pub const TRUE_DEM: &str = "truth/dem_true.tif";
/// The true Hapke parameter maps: w, b, c, B_S0, h_S, θ̄ in degrees (evaluation only).
pub const TRUE_HAPKE: &str = "truth/hapke_params.tif";
/// w without its independent albedo component, on the Hapke maps' grid (evaluation only).
pub const TRUE_W_MORPHOLOGY: &str = "truth/w_morphology.tif";
/// The crater catalogue (evaluation only).
pub const TRUE_CRATERS: &str = "truth/craters.json";
/// The complex craters a world drew (`[complex_craters]` worlds only): a crater catalogue CSV (`lon_deg`, `lat_deg`,
/// `diameter_m`, plus `degradation` and `terraces`) the pipeline reads as `inputs.crater_catalogue`. Exact: a real
/// catalogue's errors are the user's to add.
pub const TRUE_COMPLEX_CRATERS: &str = "truth/complex_craters.csv";
/// Terrain class per delivered-DEM cell (evaluation only): band 1 the [`TerrainClass`] code, band 2 the highland
/// fraction (0 mare, 1 highland). Lets evaluation report its errors by kind of ground.
pub const TRUE_TERRAIN_CLASS: &str = "truth/terrain_class.tif";
/// The world's manifest: config echo, grids, per-ortho facts, every file with its blake3.
pub const MANIFEST: &str = "world.json";

/// The generator's version, written to `world.json` as `world_version`. It changes whenever the same config and
/// seed would give other truth or other images, so figures measured on one version are never read as another's.
/// v3: ejecta freshness fades to 0 at its cutoff instead of stopping in a step; `truth/terrain_class.tif`.
pub const WORLD_VERSION: u32 = 3;

/// Kinds of ground by position relative to the world's nearest complex crater (normalised radius ρ = r / R, the
/// crater with the least), as `truth/terrain_class.tif` codes them. Worlds without a complex crater are plains
/// throughout.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum TerrainClass {
    /// ρ below the floor radius: flat melt floor, hummocks and the central peak.
    MeltFloor = 1,
    /// From the floor's edge to the rim crest (ρ ≤ 1): the terraced wall.
    TerracedWall = 2,
    /// 1 < ρ ≤ 1.5: the raised rim and the thick near ejecta.
    Rim = 3,
    /// 1.5 < ρ < 3: the thinning ejecta blanket.
    Ejecta = 4,
    /// Everything else: cratered plains, mare or highland.
    Plains = 5,
}

impl TerrainClass {
    pub const ALL: [Self; 5] = [
        Self::MeltFloor,
        Self::TerracedWall,
        Self::Rim,
        Self::Ejecta,
        Self::Plains,
    ];

    /// Class at normalised radius `rho` from the complex crater's centre (`None`: the world has none), with the
    /// melt floor inside `floor_rho`.
    pub fn at_radius(rho: Option<f64>, floor_rho: f64) -> Self {
        match rho {
            Some(r) if r < floor_rho => Self::MeltFloor,
            Some(r) if r <= 1.0 => Self::TerracedWall,
            Some(r) if r <= 1.5 => Self::Rim,
            Some(r) if r < 3.0 => Self::Ejecta,
            _ => Self::Plains,
        }
    }

    /// The raster code (band 1 of `truth/terrain_class.tif`).
    pub fn code(self) -> u8 {
        self as u8
    }

    pub fn from_code(code: f64) -> Option<Self> {
        Self::ALL.into_iter().find(|c| c.code() as f64 == code)
    }

    /// Snake-case name used in reports.
    pub fn name(self) -> &'static str {
        match self {
            Self::MeltFloor => "melt_floor",
            Self::TerracedWall => "terraced_wall",
            Self::Rim => "rim",
            Self::Ejecta => "ejecta",
            Self::Plains => "plains",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn terrain_classes_round_trip_their_codes_and_follow_the_radius() {
        for class in TerrainClass::ALL {
            assert_eq!(TerrainClass::from_code(class.code() as f64), Some(class));
        }
        assert_eq!(TerrainClass::from_code(0.0), None);
        let at = |rho| TerrainClass::at_radius(rho, 0.45);
        assert_eq!(at(Some(0.1)), TerrainClass::MeltFloor);
        assert_eq!(at(Some(0.45)), TerrainClass::TerracedWall);
        assert_eq!(at(Some(1.0)), TerrainClass::TerracedWall);
        assert_eq!(at(Some(1.2)), TerrainClass::Rim);
        assert_eq!(at(Some(2.0)), TerrainClass::Ejecta);
        assert_eq!(at(Some(3.0)), TerrainClass::Plains);
        assert_eq!(at(None), TerrainClass::Plains);
    }
}

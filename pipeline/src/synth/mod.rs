//! The seeded synthetic lunar world (docs/design.md, Synthetic world): writes exactly what a real user has — a GeoTIFF DEM, GeoTIFF
//! ortho strips with nodata borders, per-ortho acquisition metadata — plus `truth/` that only evaluation may read.
//!
//! Data flow: [`geologic_units`] (mare/highland) → [`terrain`] (fBm + craters → true DEM, freshness, melt) → [`reflectance`] (true Hapke maps) →
//! [`acquisition`] (strip plans + metadata) → [`orthos`] (orthos from the truth) → [`dem_product`] (degraded DEM).

pub mod acquisition;
pub mod config;
pub mod dem_product;
pub mod geologic_units;
pub mod lroc_products;
pub mod noise;
pub mod orthos;
pub mod reflectance;
pub mod terrain;

use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use dataset::contract::manifest::FileEntry;
use dataset::contract::world as layout;
use dataset::files::write_json_atomic;
use dataset::progress::Progress;
use dataset::science::crs::LunarCrs;
use dataset::science::raster::{write_geotiff, BandOut, BandValues, GeoTransform, RasterLayout};
use serde::Serialize;
use tracing::info;

pub use config::WorldConfig;

/// A north-up map grid: top-left corner (min_x, max_y), square pixels.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Grid {
    pub min_x: f64,
    pub max_y: f64,
    pub gsd_m: f64,
    pub width: usize,
    pub height: usize,
}

impl Grid {
    pub fn max_x(&self) -> f64 {
        self.min_x + self.width as f64 * self.gsd_m
    }
    pub fn min_y(&self) -> f64 {
        self.max_y - self.height as f64 * self.gsd_m
    }
    pub fn transform(&self) -> GeoTransform {
        GeoTransform::north_up(self.min_x, self.max_y, self.gsd_m)
    }
    /// GeoTIFF layout of this grid in `crs` with the given nodata value.
    pub fn layout<'a>(&self, crs: &'a LunarCrs, nodata: f32) -> RasterLayout<'a> {
        RasterLayout {
            width: self.width,
            height: self.height,
            transform: self.transform(),
            crs,
            nodata,
        }
    }
    /// Map coordinates of the centre of pixel (col, row).
    #[inline]
    pub fn center(&self, col: usize, row: usize) -> (f64, f64) {
        self.transform().pixel_center(col as f64, row as f64)
    }
    /// Continuous (col, row) whose centre is at (x, y).
    #[inline]
    pub fn to_pixel(&self, x: f64, y: f64) -> (f64, f64) {
        self.transform().map_to_pixel(x, y)
    }
    /// Pixel range [c0, c1) × [r0, r1) within `reach` metres of (x, y), or None if it misses the grid.
    pub fn window(&self, x: f64, y: f64, reach: f64) -> Option<(usize, usize, usize, usize)> {
        let (c, r) = self.to_pixel(x, y);
        let reach_px = reach / self.gsd_m;
        let c0 = (c - reach_px).floor().max(0.0) as usize;
        let r0 = (r - reach_px).floor().max(0.0) as usize;
        let c1 = ((c + reach_px).ceil() + 1.0).min(self.width as f64);
        let r1 = ((r + reach_px).ceil() + 1.0).min(self.height as f64);
        if c1 <= 0.0 || r1 <= 0.0 || c0 as f64 >= c1 || r0 as f64 >= r1 {
            return None;
        }
        Some((c0, c1 as usize, r0, r1 as usize))
    }
}

/// Per-ortho facts reported in `world.json` (handy for tests and for reading the world).
#[derive(Debug, Clone, Serialize)]
pub struct OrthoSummary {
    pub ortho_id: String,
    pub incidence_deg: f64,
    pub roll_deg: f64,
    pub width: usize,
    pub height: usize,
    pub stats: orthos::RenderStats,
}

#[derive(Serialize)]
struct WorldManifest<'a> {
    name: &'a str,
    /// [`layout::WORLD_VERSION`]: which generator's truth and images these are.
    world_version: u32,
    seed: u64,
    generator: String,
    crs: &'a str,
    dem_grid: Grid,
    fine_grid: Grid,
    crater_count: usize,
    orthos: Vec<OrthoSummary>,
    config: &'a WorldConfig,
    files: Vec<FileEntry>,
}

/// Progress of one phase of the generation (phases run one after another, so one bar shows at a time).
fn phase(what: &str, unit: &str, total: u64) -> Progress {
    Progress::start(&format!("synth {what}"), unit, total)
}

/// Generate the world into `out` (built under `out.partial`, renamed when complete).
pub fn generate(
    config: &WorldConfig,
    seed: u64,
    out: &Path,
    force: bool,
) -> anyhow::Result<PathBuf> {
    config
        .validate()
        .map_err(|e| anyhow::anyhow!("world config: {e}"))?;
    let config = &config.with_drawn_acquisitions(seed);
    if config.acquisition_draws.is_some() {
        let a = &config.acquisitions;
        info!(
            count = a.count,
            incidence_min_deg = a.incidence_min_deg,
            incidence_max_deg = a.incidence_max_deg,
            "acquisitions drawn for this world"
        );
    }
    if out.exists() {
        if !force {
            bail!(
                "{} already exists: choose another --out or pass --force to replace it",
                out.display()
            );
        }
        std::fs::remove_dir_all(out).with_context(|| format!("removing {}", out.display()))?;
    }
    let partial = PathBuf::from(format!("{}.partial", out.display()));
    if partial.exists() {
        std::fs::remove_dir_all(&partial)?;
    }
    for sub in ["dem", "ortho", "isd", "index", "truth", "map"] {
        std::fs::create_dir_all(partial.join(sub))
            .with_context(|| format!("creating {}", partial.display()))?;
    }

    let w = &config.world;
    let crs = LunarCrs::equirectangular(w.center_lat_deg, w.center_lon_deg);
    let (cx, cy) = crs.from_lonlat_deg(w.center_lon_deg, w.center_lat_deg)?;
    // Snap the scene to the DEM grid so every grid (fine, DEM, ortho) shares pixel edges.
    let snap = |v: f64| (v / w.dem_gsd_m).round() * w.dem_gsd_m;
    let (min_x, max_y) = (snap(cx - w.width_m / 2.0), snap(cy + w.height_m / 2.0));
    let dem_grid = Grid {
        min_x,
        max_y,
        gsd_m: w.dem_gsd_m,
        width: (w.width_m / w.dem_gsd_m).round() as usize,
        height: (w.height_m / w.dem_gsd_m).round() as usize,
    };
    let factor = (w.dem_gsd_m / w.fine_gsd_m).round() as usize;
    let fine = Grid {
        min_x,
        max_y,
        gsd_m: w.fine_gsd_m,
        width: dem_grid.width * factor,
        height: dem_grid.height * factor,
    };
    info!(world = %w.name, seed, fine_px = fine.width * fine.height, dem_px = dem_grid.width * dem_grid.height, "generating synthetic lunar world");

    // Terrain.
    let units = geologic_units::Units::new(&config.reflectance, seed);
    let background = phase("background terrain", "grids", 1);
    let mut heights = terrain::background(&config.terrain, &fine, &units, w.base_height_m, seed);
    background.inc(1);
    background.finish();
    let craters = terrain::crater_catalogue(&config.terrain, &fine, &units, seed);
    let mut freshness = vec![0f32; fine.width * fine.height];
    let mut melt = vec![0f32; fine.width * fine.height];
    let stamping = phase("craters", "craters", craters.len() as u64);
    for (i, chunk) in craters.chunks(1000).enumerate() {
        terrain::stamp_craters(
            &config.terrain,
            &fine,
            chunk,
            i * 1000,
            &mut heights,
            &mut freshness,
            seed,
        );
        stamping.inc(chunk.len() as u64);
    }
    stamping.finish();
    let complex_craters = match (&config.complex_crater, &config.complex_craters) {
        (Some(cc), _) => vec![terrain::PlacedComplexCrater {
            center: (cx + cc.offset_east_m, cy + cc.offset_north_m),
            shape: cc.clone(),
        }],
        (None, Some(population)) => {
            terrain::draw_complex_craters(population, (cx, cy), (w.width_m, w.height_m), seed)
                .map_err(|e| anyhow::anyhow!("world config: {e}"))?
        }
        (None, None) => Vec::new(),
    };
    for (index, crater) in complex_craters.iter().enumerate() {
        terrain::stamp_complex_crater(
            &crater.shape,
            index as u64,
            &fine,
            crater.center,
            &mut heights,
            &mut freshness,
            &mut melt,
            seed,
        );
    }
    let complex_rings: Vec<((f64, f64), f64)> = complex_craters
        .iter()
        .map(|c| (c.center, c.shape.diameter_m / 2.0))
        .collect();
    info!(craters = craters.len(), "terrain done");

    // True reflectance.
    let reflectance_phase = phase("true reflectance", "maps", 1);
    let maps = reflectance::hapke_maps(
        &config.reflectance,
        &fine,
        &units,
        &heights,
        &freshness,
        &melt,
        seed,
    );
    drop(freshness);
    drop(melt);
    reflectance_phase.inc(1);
    reflectance_phase.finish();

    // Acquisitions and orthos.
    let strips = acquisition::plan(&config.acquisitions, &fine, &crs, w.base_height_m, seed);
    let scene = orthos::TruthScene::new(&crs, &fine, &heights, &maps);
    let mut orthos = Vec::new();
    let mut index_rows = Vec::new();
    for (k, strip) in strips.iter().enumerate() {
        let progress = phase(&strip.meta.ortho_id, "tiles", 0);
        let (image, stats) = orthos::render_ortho(
            &scene,
            &config.reflectance,
            &config.acquisitions,
            strip,
            k,
            seed,
            progress.bar(),
        );
        progress.finish();
        let g = &strip.grid;
        let path = partial.join(layout::ORTHO_DIR).join(&strip.meta.image_file);
        write_geotiff(
            &path,
            &g.layout(&crs, -1.0),
            &[BandOut {
                values: BandValues::Grid(&image),
                description: "I/F (radiance factor)",
            }],
            &[
                ("CAMERA_ID", strip.meta.camera_id.clone()),
                ("START_TIME", strip.meta.start_time_utc.clone()),
            ],
        )?;
        write_json_atomic(
            &partial
                .join(layout::ORTHO_DIR)
                .join(format!("{}.json", strip.meta.ortho_id)),
            &strip.meta,
        )?;
        let gsd = strip.grid.gsd_m;
        write_json_atomic(
            &partial
                .join(layout::ISD_DIR)
                .join(format!("{}.json", strip.meta.ortho_id)),
            &lroc_products::isd(
                &strip.meta,
                (strip.length_m / gsd).round() as usize,
                (strip.width_m / gsd).round() as usize,
            ),
        )?;
        index_rows.push(lroc_products::index_row(strip, &crs, w.base_height_m));
        info!(ortho = %strip.meta.ortho_id, incidence_deg = format!("{:.1}", strip.incidence_deg), roll_deg = format!("{:.1}", strip.meta.roll_deg), valid = stats.valid, shadowed = stats.shadowed, occluded = stats.occluded, "ortho rendered");
        orthos.push(OrthoSummary {
            ortho_id: strip.meta.ortho_id.clone(),
            incidence_deg: strip.incidence_deg,
            roll_deg: strip.meta.roll_deg,
            width: g.width,
            height: g.height,
            stats,
        });
    }

    // Delivered DEM and truth: five rasters, the crater list and the terrain classes, each a step.
    let truth_phase = phase("DEM product and truth", "files", 7);
    truth_phase.set_message(layout::DEM);
    let dem = dem_product::degrade(&config.dem_product, &fine, &heights, &dem_grid, seed);
    let height_desc = "height_m above the 1737400 m lunar sphere";
    write_geotiff(
        &partial.join(layout::DEM),
        &dem_grid.layout(&crs, -32768.0),
        &[BandOut {
            values: BandValues::Grid(&dem),
            description: height_desc,
        }],
        &[("PRODUCT", "stereo-like DEM (synthetic)".into())],
    )?;
    drop(dem);
    truth_phase.inc(1);
    truth_phase.set_message(layout::TRUE_DEM);
    write_geotiff(
        &partial.join(layout::TRUE_DEM),
        &fine.layout(&crs, -32768.0),
        &[BandOut {
            values: BandValues::Grid(&heights),
            description: height_desc,
        }],
        &[],
    )?;
    drop(heights);
    let r = &config.reflectance;
    let bands = [
        BandOut {
            values: BandValues::Grid(&maps.w),
            description: "w (single-scattering albedo)",
        },
        BandOut {
            values: BandValues::Grid(&maps.b),
            description: "b (double-HG asymmetry)",
        },
        BandOut {
            values: BandValues::Constant(r.c as f32),
            description: "c (double-HG partition, c>0 back-scattering)",
        },
        BandOut {
            values: BandValues::Constant(r.b_s0 as f32),
            description: "B_S0 (shadow-hiding amplitude)",
        },
        BandOut {
            values: BandValues::Constant(r.h_s as f32),
            description: "h_S (shadow-hiding width)",
        },
        BandOut {
            values: BandValues::Constant(r.theta_bar_deg as f32),
            description: "theta_bar_deg (macroscopic roughness)",
        },
    ];
    truth_phase.inc(1);
    truth_phase.set_message(layout::TRUE_HAPKE);
    write_geotiff(
        &partial.join(layout::TRUE_HAPKE),
        &fine.layout(&crs, -1.0),
        &bands,
        &[("HAPKE_FORM", "Hapke 2012 IMSA, H-function 2002, K=1".into())],
    )?;
    truth_phase.inc(1);
    truth_phase.set_message(layout::TRUE_W_MORPHOLOGY);
    write_geotiff(
        &partial.join(layout::TRUE_W_MORPHOLOGY),
        &fine.layout(&crs, -1.0),
        &[BandOut {
            values: BandValues::Grid(&maps.w_morphology),
            description:
                "w without the independent albedo component (units, freshness, slope, melt)",
        }],
        &[],
    )?;
    truth_phase.inc(1);
    truth_phase.set_message(layout::TRUE_CRATERS);
    write_json_atomic(&partial.join(layout::TRUE_CRATERS), &craters)?;
    truth_phase.inc(1);
    truth_phase.set_message("terrain classes");
    // On the delivered DEM's grid: evaluation classifies crops, which live on that grid.
    let (class, highland) = terrain::terrain_classes(&dem_grid, &units, &complex_rings);
    truth_phase.inc(1);
    truth_phase.set_message(layout::TRUE_TERRAIN_CLASS);
    write_geotiff(
        &partial.join(layout::TRUE_TERRAIN_CLASS),
        &dem_grid.layout(&crs, -1.0),
        &[
            BandOut {
                values: BandValues::Grid(&class),
                description:
                    "terrain class: 1 melt floor, 2 terraced wall, 3 rim, 4 ejecta, 5 plains",
            },
            BandOut {
                values: BandValues::Grid(&highland),
                description: "highland fraction (0 mare, 1 highland)",
            },
        ],
        &[],
    )?;
    drop((class, highland));
    truth_phase.inc(1);
    truth_phase.finish();

    if let Some(map_cfg) = &config.unit_map {
        let map_grid = Grid {
            min_x,
            max_y,
            gsd_m: map_cfg.gsd_m,
            width: (w.width_m / map_cfg.gsd_m).ceil() as usize,
            height: (w.height_m / map_cfg.gsd_m).ceil() as usize,
        };
        let map = geologic_units::unit_map(&units, map_cfg, &map_grid, seed);
        write_geotiff(
            &partial.join(layout::UNIT_MAP),
            &map_grid.layout(&crs, -1.0),
            &[BandOut {
                values: BandValues::Grid(&map),
                description: "unit: 0 mare, 1 highland",
            }],
            &[("PRODUCT", "mare/highland unit map (synthetic)".into())],
        )?;
    } else {
        std::fs::remove_dir(partial.join("map"))?;
    }
    let mut files = Vec::new();
    if config.complex_craters.is_some() {
        // The drawn craters as a catalogue the pipeline reads (`inputs.crater_catalogue`): exact, as a truth file.
        let mut csv = String::from("lon_deg,lat_deg,diameter_m,degradation,terraces\n");
        for c in &complex_craters {
            let (lon, lat) = crs.to_lonlat_deg(c.center.0, c.center.1)?;
            csv += &format!(
                "{lon:.9},{lat:.9},{:.3},{:.4},{}\n",
                c.shape.diameter_m, c.shape.degradation, c.shape.terraces
            );
        }
        dataset::files::write_text_atomic(&partial.join(layout::TRUE_COMPLEX_CRATERS), &csv)?;
    }
    let mut relative: Vec<String> = vec![
        layout::DEM.into(),
        layout::TRUE_DEM.into(),
        layout::TRUE_HAPKE.into(),
        layout::TRUE_W_MORPHOLOGY.into(),
        layout::TRUE_CRATERS.into(),
        layout::TRUE_TERRAIN_CLASS.into(),
    ];
    let (label, table) = lroc_products::index_files(&index_rows);
    std::fs::write(partial.join(layout::INDEX_LABEL), label)?;
    std::fs::write(partial.join(layout::INDEX_TABLE), table)?;
    relative.extend([layout::INDEX_LABEL.into(), layout::INDEX_TABLE.into()]);
    if config.complex_craters.is_some() {
        relative.push(layout::TRUE_COMPLEX_CRATERS.into());
    }
    if config.unit_map.is_some() {
        relative.push(layout::UNIT_MAP.into());
    }
    for s in &strips {
        relative.push(format!("{}/{}", layout::ORTHO_DIR, s.meta.image_file));
        relative.push(format!("{}/{}.json", layout::ORTHO_DIR, s.meta.ortho_id));
        relative.push(format!("{}/{}.json", layout::ISD_DIR, s.meta.ortho_id));
    }
    relative.sort();
    let hashing = phase("file hashes", "files", relative.len() as u64);
    for rel in &relative {
        hashing.set_message(rel.clone());
        files.push(FileEntry::of(&partial, rel)?);
        hashing.inc(1);
    }
    hashing.finish();
    let manifest = WorldManifest {
        name: &w.name,
        world_version: layout::WORLD_VERSION,
        seed,
        generator: format!("g2r-pipeline {}", env!("CARGO_PKG_VERSION")),
        crs: &crs.definition,
        dem_grid,
        fine_grid: fine,
        crater_count: craters.len(),
        orthos,
        config,
        files,
    };
    write_json_atomic(&partial.join(layout::MANIFEST), &manifest)?;
    std::fs::rename(&partial, out)
        .with_context(|| format!("renaming {} to {}", partial.display(), out.display()))?;
    Ok(out.to_path_buf())
}

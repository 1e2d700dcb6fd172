//! Pipeline stages (docs/design.md, Pipeline stages), in data-flow order: [`ingest`] → [`erode`] → [`sample`] → [`split`] →
//! [`project`] → ([`merge`] of a partitioned build's partitions →) [`publish`]. Split runs on the sampled footprints, before projection: assignment needs only a
//! crop's centre and size, and crops straddling two splits (17 % on tycho-full) are then never projected. [`pipeline`] declares them to the [`crate::runner`] with their inputs, params and
//! outputs; each module holds the algorithm (tested on its own) and the stage function that does the file IO.

pub mod erode;
pub mod ingest;
pub mod merge;
pub mod project;
pub mod publish;
pub mod sample;
pub mod split;
pub mod table;

use std::path::PathBuf;

use anyhow::Context;
use dataset::contract::catalogue_error::FramedCatalogue;
use dataset::contract::manifest::CraterFrameSource;
use dataset::contract::publication::{DOCUMENT_FILES, MANIFEST_FILE};
use dataset::science::raster::Raster;

use crate::manifest::PipelineManifest;
use crate::runner::{Runner, Stage};

/// Stage names in order.
pub const STAGES: [&str; 6] = ["ingest", "erode", "sample", "split", "project", "publish"];

/// Rows per row group of the projected split files and the shards cut from them: the default 256, or the whole
/// shard when shards are smaller (the manifest requires `rows_per_shard` ≤ 256 or a multiple of 256).
pub fn row_group_rows(rows_per_shard: usize) -> usize {
    rows_per_shard.min(dataset::contract::shard::ROW_GROUP_ROWS)
}

/// Outputs of each stage, under the manifest's output directory (or a partition's, [`crate::partition`]).
#[derive(Clone)]
pub struct Layout {
    pub orthos: PathBuf,
    pub runs: PathBuf,
    pub positions: PathBuf,
    pub assignment: PathBuf,
    pub split_summary: PathBuf,
    /// One sample file per split, in [`split::Split::ALL`] order.
    pub split_samples: [PathBuf; 3],
    pub rejections: PathBuf,
    pub train_dem: PathBuf,
    pub dataset: PathBuf,
}

impl Layout {
    pub fn of(manifest: &PipelineManifest) -> Self {
        Self::at(&manifest.stage_dir(), manifest.dataset_dir())
    }

    /// Stage outputs under `stage_dir`, the published dataset in `dataset`.
    pub fn at(stage_dir: &std::path::Path, dataset: PathBuf) -> Self {
        let s = stage_dir;
        Self {
            orthos: s.join("ingest/orthos.parquet"),
            runs: s.join("erode/runs.parquet"),
            positions: s.join("sample/positions.parquet"),
            assignment: s.join("split/assignment.parquet"),
            split_summary: s.join("split/summary.json"),
            split_samples: split::Split::ALL
                .map(|split| s.join(format!("project/{}.parquet", split.name()))),
            rejections: s.join("project/rejections.json"),
            train_dem: s.join("project/train_dem.json"),
            dataset,
        }
    }
}

/// Loads the DEM once, on first use by a stage that needs it (status never reads rasters).
struct LazyDem {
    path: PathBuf,
    cell: std::sync::OnceLock<Raster>,
}

impl LazyDem {
    fn get(&self) -> anyhow::Result<&Raster> {
        if let Some(dem) = self.cell.get() {
            return Ok(dem);
        }
        let dem = dataset::science::raster::read_raster(&self.path)?;
        Ok(self.cell.get_or_init(|| dem))
    }
}

/// Which share of a manifest's work a runner does.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Scope {
    /// Every ortho, through publish: the single-process build.
    Whole,
    /// One partition's run of orthos, ingest through project, in its own directory and lock; publishing waits
    /// for the merge of all partitions ([`merge`]).
    Partition(crate::partition::Partition),
}

/// Declare the six stages of `manifest` to a runner.
pub fn pipeline(
    manifest: &PipelineManifest,
    progress: indicatif::ProgressBar,
) -> anyhow::Result<Runner<'static>> {
    pipeline_scoped(manifest, Scope::Whole, progress)
}

/// Declare the stages of `scope`'s share of `manifest` to a runner: all six for [`Scope::Whole`], ingest through
/// project over the partition's orthos for [`Scope::Partition`].
pub fn pipeline_scoped(
    manifest: &PipelineManifest,
    scope: Scope,
    progress: indicatif::ProgressBar,
) -> anyhow::Result<Runner<'static>> {
    let m = manifest.clone();
    let dem_path = crate::inputs::dem_path(&m);
    let ortho_dir = crate::inputs::ortho_dir(&m);
    if let Some((field, url)) = crate::inputs::urls(&m).into_iter().find(|(field, _)| {
        !(if *field == "inputs.dem" {
            &dem_path
        } else {
            &ortho_dir
        })
        .exists()
    }) {
        anyhow::bail!("{field} = \"{url}\": not fetched yet; `g2r-pipeline run` copies inputs given as URLs to {} first", crate::inputs::cache_dir(&m).display());
    }
    if !dem_path.exists() {
        anyhow::bail!("{}: DEM not found; check inputs.dem in the manifest (paths are relative to the manifest)", dem_path.display());
    }
    let mut metadata = ingest::metadata_files(&ortho_dir)?;
    let mut images: Vec<PathBuf> = metadata
        .iter()
        .map(|p| -> anyhow::Result<PathBuf> {
            let meta = dataset::contract::acquisition::AcquisitionMetadata::load(p)?;
            Ok(p.with_file_name(meta.image_file))
        })
        .collect::<anyhow::Result<_>>()?;
    let (layout, lock_path) = match scope {
        Scope::Whole => (Layout::of(&m), m.out_dir().join("pipeline.lock.json")),
        Scope::Partition(part) => {
            let orthos =
                crate::partition::plan(&dem_path, &images, part.count)?.swap_remove(part.index);
            metadata = metadata[orthos.clone()].to_vec();
            images = images[orthos].to_vec();
            let dir = crate::partition::dir(&m, part);
            (
                Layout::at(&dir.join("stages"), m.dataset_dir()),
                dir.join("pipeline.lock.json"),
            )
        }
    };
    let dem = std::sync::Arc::new(LazyDem {
        path: dem_path.clone(),
        cell: Default::default(),
    });
    let provenance = format!("g2r-pipeline {}", env!("CARGO_PKG_VERSION"));
    // The footprint a split must contain: the whole DEM tensor, crop + apron (130 cells), not just the image.
    let crop_half_m =
        |dem: &Raster| dataset::contract::schema::DEM_PX as f64 / 2.0 * dem.transform.gsd_m();
    let seed = m.dataset.seed;

    let (md, l, dem_input) = (metadata.clone(), layout.clone(), dem_path.clone());
    let ingest = Stage {
        name: "ingest",
        code_version: "1",
        inputs: std::iter::once(dem_path.clone())
            .chain(metadata.iter().cloned())
            .chain(images.iter().cloned())
            .collect(),
        params: serde_json::json!({}),
        outputs: vec![layout.orthos.clone()],
        run: Box::new(move |out| ingest::run(&dem_path, &md, &out.paths[0]).context("ingest")),
        check: None,
    };
    let (od, l2, dem2) = (ortho_dir.clone(), layout.clone(), dem.clone());
    let erode = Stage {
        name: "erode",
        code_version: "1",
        inputs: [l.orthos.clone(), dem_input.clone()]
            .into_iter()
            .chain(images.iter().cloned())
            .collect(),
        params: serde_json::json!({ "crop_with_apron_px": dataset::contract::schema::DEM_PX }),
        outputs: vec![layout.runs.clone()],
        run: Box::new(move |out| {
            erode::run(dem2.get()?, &ingest::read(&l2.orthos, &od)?, &out.paths[0])
        }),
        check: None,
    };
    let (l3, dem3, coverage) = (layout.clone(), dem.clone(), m.sample.coverage);
    let sample = Stage {
        name: "sample",
        code_version: "1",
        inputs: vec![layout.runs.clone(), dem_input.clone()],
        params: serde_json::json!({ "coverage": coverage, "seed": seed }),
        outputs: vec![layout.positions.clone()],
        run: Box::new(move |out| {
            sample::run(
                &l3.runs,
                coverage,
                dem3.get()?.transform.gsd_m(),
                seed,
                &out.paths[0],
            )
        }),
        check: None,
    };
    let (l4, dem4, sp) = (layout.clone(), dem.clone(), m.split.clone());
    let split = Stage {
        name: "split",
        // 3: assigns sampled positions (before projection) instead of projected samples.
        code_version: "3",
        inputs: vec![layout.positions.clone(), dem_input.clone()],
        params: serde_json::json!({ "split": serde_json::to_value(&m.split)?, "seed": seed }),
        outputs: vec![layout.assignment.clone(), layout.split_summary.clone()],
        run: Box::new(move |out| {
            let dem = dem4.get()?;
            split::run(
                &l4.positions,
                &dem.transform,
                crop_half_m(dem),
                seed,
                &sp,
                &out.paths[0],
                &out.paths[1],
            )
        }),
        check: None,
    };
    let (od, l5, dem5, pp, prov) = (
        ortho_dir.clone(),
        layout.clone(),
        dem.clone(),
        m.project.clone(),
        provenance.clone(),
    );
    let catalogue = m.inputs.crater_catalogue.as_ref().map(|p| m.resolve(p));
    if let Some(path) = catalogue.as_ref().filter(|p| !p.exists()) {
        anyhow::bail!("{}: crater catalogue not found; check inputs.crater_catalogue in the manifest (paths are relative to the manifest)", path.display());
    }
    let unit_map = m.inputs.unit_map.as_ref().map(|p| m.resolve(p));
    if let Some(path) = unit_map.as_ref().filter(|p| !p.exists()) {
        anyhow::bail!("{}: unit map not found; check inputs.unit_map in the manifest (paths are relative to the manifest)", path.display());
    }
    let (catalogue5, unit_map5) = (catalogue.clone(), unit_map.clone());
    let group_rows = row_group_rows(m.publish.rows_per_shard);
    let progress5 = progress.clone();
    let project = Stage {
        name: "project",
        // 2: projects assigned positions only, into one file per split. 3: every sample carries its context
        // window (schema 1.2). 4: context cells average blocks of pixels (dataset::contract::context), not single pixels.
        // 5: the train DEM statistic is summed per ortho (partitions merge to the same bits). 6: every sample
        // carries its crater frame, NaN without a catalogue (schema 1.3). 7: tensor pages of at most
        // `TENSOR_PAGE_BYTES` (same values, other bytes: a one-row read decompresses an eighth of what it did).
        // 8: the crater frame carries its crater's relief over diameter (schema 1.4). 9: the context window carries
        // its cells' highland fraction, NaN without a unit map (schema 1.6). 10: the crater's relief read along
        // rays from rim crest to floor, not from the ring medians (dataset::contract::crater_frame); a crater with
        // too little DEM on its rim and floor is no longer framed.
        code_version: "10",
        // Everything projection reads: assigned positions, the DEM, and each ortho's image and metadata.
        inputs: [
            layout.assignment.clone(),
            layout.orthos.clone(),
            dem_input.clone(),
        ]
        .into_iter()
        .chain(catalogue.clone())
        .chain(unit_map.clone())
        .chain(images.iter().cloned())
        .chain(metadata.iter().cloned())
        .collect(),
        // The row-group size is the shards' (publish copies whole groups), so it is a projection parameter too.
        // The seed draws the catalogue's simulated errors; without them it does not enter, and the lock of a
        // dataset framed by the catalogue as it is stays as it was.
        params: {
            let mut params = serde_json::json!({
                "project": serde_json::to_value(&m.project)?,
                "row_group_rows": group_rows,
            });
            if m.project.crater_catalogue_error.is_some() {
                params["seed"] = serde_json::json!(seed);
            }
            params
        },
        outputs: layout
            .split_samples
            .iter()
            .cloned()
            .chain([layout.rejections.clone(), layout.train_dem.clone()])
            .collect(),
        run: Box::new(move |out| {
            let orthos = ingest::read(&l5.orthos, &od)?;
            let p = &out.paths;
            let dem = dem5.get()?;
            let crater_frames = catalogue5
                .as_ref()
                .map(|path| {
                    FramedCatalogue::new(
                        dem,
                        path,
                        pp.crater_frame_min_diameter_m,
                        pp.crater_catalogue_error.as_ref(),
                        seed,
                    )
                })
                .transpose()?;
            let unit_map = unit_map5
                .as_ref()
                .map(|path| dataset::contract::context::read_unit_map(path, dem))
                .transpose()?;
            project::run(
                (dem, crater_frames.as_ref(), unit_map.as_ref()),
                &orthos,
                &l5.assignment,
                &pp,
                (&prov, group_rows),
                &project::ProjectOutputs {
                    split_samples: [&p[0], &p[1], &p[2]],
                    rejections: &p[3],
                    train_dem: &p[4],
                },
                &progress5,
            )
        }),
        check: None,
    };
    let (l6, dem6, m6, lock6) = (layout.clone(), dem.clone(), m.clone(), lock_path.clone());
    let (catalogue6, min_diameter6, error6) = (
        catalogue.clone(),
        m.project.crater_frame_min_diameter_m,
        m.project.crater_catalogue_error,
    );
    let check_dir = layout.dataset.clone();
    let publish = Stage {
        name: "publish",
        // 2: card and Croissant written by dataset::contract::publication. 3: shards copied from per-split files.
        code_version: "3",
        inputs: layout
            .split_samples
            .iter()
            .cloned()
            .chain([
                layout.train_dem.clone(),
                layout.rejections.clone(),
                layout.split_summary.clone(),
                dem_input,
            ])
            .collect(),
        // The split parameters shape the card and the map, so they are publish parameters too.
        params: serde_json::json!({
            "dataset": serde_json::to_value(&m.dataset)?,
            "publish": serde_json::to_value(&m.publish)?,
            "split": serde_json::to_value(&m.split)?,
        }),
        // manifest.json last: the runner renames in this order, and the manifest is what makes a dataset finished.
        outputs: DOCUMENT_FILES
            .iter()
            .chain([&MANIFEST_FILE])
            .map(|f| layout.dataset.join(f))
            .collect(),
        run: Box::new(move |out| {
            let dem = dem6.get()?;
            let bounds = dem.transform.bounds(dem.width, dem.height);
            // The lock entries of the five upstream stages (not publish's own previous entry): ties the dataset to
            // exactly those inputs and stays the same across re-publishing.
            let text = std::fs::read_to_string(&lock6)
                .with_context(|| format!("{}: lock missing", lock6.display()))?;
            let mut lock: crate::runner::Lock = serde_json::from_str(&text)?;
            lock.stages.remove("publish");
            let lock_blake3 = blake3::hash(serde_json::to_string(&lock)?.as_bytes())
                .to_hex()
                .to_string();
            let ctx = publish::PublishContext {
                name: &m6.dataset.name,
                license: &m6.dataset.license,
                seed,
                crs: &dem.crs.definition,
                rows_per_shard: m6.publish.rows_per_shard,
                split_params: &m6.split,
                dem_bounds: bounds,
                lock_blake3,
                crater_frame: catalogue6
                    .as_deref()
                    .map(|path| CraterFrameSource::of(path, min_diameter6, error6))
                    .transpose()?,
            };
            let p = &out.paths;
            let outputs = publish::PublishOutputs {
                card: &p[0],
                croissant: &p[1],
                summary: &p[2],
                map: &p[3],
                manifest: &p[4],
            };
            std::fs::create_dir_all(&l6.dataset)?;
            let [train, val, test] = &l6.split_samples;
            let projected = publish::ProjectedInputs {
                split_samples: [train, val, test],
                train_dem: &l6.train_dem,
                rejections: &l6.rejections,
            };
            publish::run(&ctx, &projected, &l6.split_summary, &l6.dataset, &outputs)
        }),
        // Shards are listed by manifest.json, not declared up front: a missing or altered shard makes publish stale.
        check: Some(Box::new(move || {
            let manifest =
                dataset::contract::manifest::DatasetManifest::load_dir(&check_dir).ok()?;
            manifest.verify(&check_dir).into_iter().next()
        })),
    };
    let mut stages = vec![ingest, erode, sample, split, project];
    if scope == Scope::Whole {
        stages.push(publish);
    }
    Ok(Runner {
        root: m.base_dir.clone(),
        fetched_from: crate::inputs::fetched_from(&m),
        lock_path,
        stages,
        hash_memo: std::sync::Arc::new(crate::runner::HashMemo::per_call()),
    })
}

//! Publish: cut each split's sample file into shards `{split}-{i:05}-of-{n:05}.parquet` by copying its encoded
//! row groups (no decode, no re-encode), then write `manifest.json` (every shard with size, rows, row groups and
//! blake3; split counts; the train-only DEM std), a dataset card, Croissant JSON-LD, a summary (counts per split /
//! ortho / tile, rejections by reason) and a PNG map of tiles coloured by split with the sample centres.

use std::collections::BTreeMap;
use std::path::Path;

use dataset::contract::manifest::{DatasetManifest, ShardEntry};
use dataset::contract::publication::{croissant, dataset_card};
use dataset::files::write_json_atomic;

use dataset::contract::schema::SCHEMA_VERSION;
use dataset::contract::shard::{shard_name, EncodedRowGroups, ShardWriter};

use super::project::TrainDemStatistic;
use super::split::{split_of_tile, tile_of, Split, SplitParams};

/// Inputs the publish stage needs besides the files.
pub struct PublishContext<'a> {
    pub name: &'a str,
    pub license: &'a str,
    pub seed: u64,
    pub crs: &'a str,
    pub rows_per_shard: usize,
    pub split_params: &'a SplitParams,
    pub dem_bounds: (f64, f64, f64, f64),
    pub lock_blake3: String,
    /// What framed the samples, recorded in the manifest.
    pub crater_frame: Option<dataset::contract::manifest::CraterFrameSource>,
}

pub struct PublishOutputs<'a> {
    pub manifest: &'a Path,
    pub card: &'a Path,
    pub croissant: &'a Path,
    pub summary: &'a Path,
    pub map: &'a Path,
}

/// The project stage's outputs that publish reads.
pub struct ProjectedInputs<'a> {
    /// One sample file per split, in [`Split::ALL`] order.
    pub split_samples: [&'a Path; 3],
    pub train_dem: &'a Path,
    pub rejections: &'a Path,
}

/// Rows per ortho and split, rows per tile, and every sample centre: the summary's tables and the map's dots.
#[derive(Default)]
struct Tally {
    per_ortho: BTreeMap<String, BTreeMap<String, u64>>,
    per_tile: BTreeMap<String, u64>,
    centres: Vec<(f64, f64)>,
}

/// Tally the published rows with polars: a lazy scan of the split files reads only the four scalar columns it needs
/// (no tensor page is decoded), then two group-bys count rows per (ortho, split) and per tile.
fn tally_splits(files: &[(Split, &Path)]) -> anyhow::Result<Tally> {
    use polars::prelude::*;
    let frames = files
        .iter()
        .map(|(split, path)| {
            Ok(LazyFrame::scan_parquet(
                PlRefPath::try_from_path(path)?,
                ScanArgsParquet::default(),
            )?
            .select([
                col("ortho_id"),
                col("tile_id"),
                col("center_x"),
                col("center_y"),
            ])
            .with_column(lit(split.name()).alias("split")))
        })
        .collect::<PolarsResult<Vec<_>>>()?;
    let rows = concat(frames, UnionArgs::default())?.collect()?;
    let count = |keys: &[&str]| -> PolarsResult<DataFrame> {
        rows.clone()
            .lazy()
            .group_by(keys.iter().map(|k| col(*k)).collect::<Vec<_>>())
            .agg([len().cast(DataType::UInt64).alias("rows")])
            .collect()
    };
    // The columns are non-null (written from Rust values), so a null would only read as "".
    let strings = |df: &DataFrame, name: &str| -> PolarsResult<Vec<String>> {
        Ok(df
            .column(name)?
            .str()?
            .iter()
            .map(|v| v.unwrap_or_default().to_string())
            .collect())
    };
    let mut tally = Tally::default();
    let per_ortho = count(&["ortho_id", "split"])?;
    for ((ortho, split), n) in strings(&per_ortho, "ortho_id")?
        .into_iter()
        .zip(strings(&per_ortho, "split")?)
        .zip(per_ortho.column("rows")?.u64()?.into_no_null_iter())
    {
        tally.per_ortho.entry(ortho).or_default().insert(split, n);
    }
    let per_tile = count(&["tile_id"])?;
    for (tile, n) in strings(&per_tile, "tile_id")?
        .into_iter()
        .zip(per_tile.column("rows")?.u64()?.into_no_null_iter())
    {
        tally.per_tile.insert(tile, n);
    }
    tally.centres = rows
        .column("center_x")?
        .f64()?
        .into_no_null_iter()
        .zip(rows.column("center_y")?.f64()?.into_no_null_iter())
        .collect();
    Ok(tally)
}

pub fn run(
    ctx: &PublishContext,
    projected: &ProjectedInputs,
    split_summary_path: &Path,
    dataset_dir: &Path,
    out: &PublishOutputs,
) -> anyhow::Result<()> {
    // The dataset stops looking finished before any shard changes: its manifest goes first (written back last).
    let published = dataset_dir.join(dataset::contract::publication::MANIFEST_FILE);
    if published.exists() {
        std::fs::remove_file(&published)?;
    }
    // Remove shards of an earlier publish (their count may differ) and leftovers of a killed one.
    for entry in std::fs::read_dir(dataset_dir)?.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        if name.ends_with(".parquet") || name.ends_with(".parquet.tmp") {
            std::fs::remove_file(entry.path())?;
        }
    }
    // One thread per split: copying is disk and blake3 work, and the splits are independent.
    let results: Vec<anyhow::Result<Vec<ShardEntry>>> = std::thread::scope(|scope| {
        let handles: Vec<_> = Split::ALL
            .iter()
            .zip(projected.split_samples)
            .map(|(split, path)| {
                scope.spawn(move || publish_split(dataset_dir, split.name(), path, ctx))
            })
            .collect();
        handles
            .into_iter()
            .map(|h| {
                h.join()
                    .unwrap_or_else(|_| Err(anyhow::anyhow!("shard writer thread panicked")))
            })
            .collect()
    });
    let mut split_counts: BTreeMap<String, u64> = BTreeMap::new();
    let mut shards: Vec<ShardEntry> = Vec::new();
    for (split, result) in Split::ALL.iter().zip(results) {
        let split_shards = result?;
        split_counts.insert(
            split.name().to_string(),
            split_shards.iter().map(|s| s.rows).sum(),
        );
        shards.extend(split_shards);
    }
    let files: Vec<(Split, &Path)> = Split::ALL
        .into_iter()
        .zip(projected.split_samples)
        .collect();
    let Tally {
        per_ortho,
        per_tile,
        centres,
    } = tally_splits(&files)?;
    shards.sort_by(|a, b| a.path.cmp(&b.path));
    let train_dem: TrainDemStatistic =
        serde_json::from_str(&std::fs::read_to_string(projected.train_dem)?)?;
    let manifest = DatasetManifest {
        schema_version: SCHEMA_VERSION.into(),
        name: ctx.name.into(),
        license: ctx.license.into(),
        seed: ctx.seed,
        crs: ctx.crs.into(),
        split_counts: split_counts.clone(),
        shards: shards.clone(),
        dem_std_m: train_dem.std_m(),
        pipeline_lock_blake3: ctx.lock_blake3.clone(),
        crater_frame: ctx.crater_frame.clone(),
    };
    let rejections: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(projected.rejections)?)?;
    let split_summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(split_summary_path)?)?;
    let summary = serde_json::json!({
        "split_counts": split_counts,
        "per_ortho": per_ortho,
        "per_tile": per_tile,
        "rejections_by_ortho": rejections,
        "split": split_summary,
    });
    write_json_atomic(out.summary, &summary)?;
    std::fs::write(out.card, dataset_card(&manifest, &summary))?;
    write_json_atomic(out.croissant, &croissant(&manifest))?;
    draw_map(ctx, &centres, out.map)?;
    write_json_atomic(out.manifest, &manifest)?;
    Ok(())
}

/// Cut one split's sample file into shards of `rows_per_shard` rows by copying whole encoded row groups.
fn publish_split(
    dataset_dir: &Path,
    split: &str,
    path: &Path,
    ctx: &PublishContext,
) -> anyhow::Result<Vec<ShardEntry>> {
    let source = EncodedRowGroups::open(path)?;
    let sizes = source.row_group_sizes();
    let rows: usize = sizes.iter().sum();
    let group_rows = super::row_group_rows(ctx.rows_per_shard);
    // A shard is a whole number of row groups: every group but the last must be full.
    if let Some(g) = sizes[..sizes.len().saturating_sub(1)]
        .iter()
        .position(|&n| n != group_rows)
    {
        anyhow::bail!(
            "{}: row group {g} has {} rows, expected {group_rows} (written for another publish.rows_per_shard); re-run the project stage",
            path.display(),
            sizes[g]
        );
    }
    let groups_per_shard = ctx.rows_per_shard / group_rows;
    let count = rows.div_ceil(ctx.rows_per_shard).max(1);
    let mut shards = Vec::new();
    for (i, first) in (0..sizes.len()).step_by(groups_per_shard).enumerate() {
        let mut writer = ShardWriter::create(&dataset_dir.join(shard_name(split, i, count)))?;
        for g in first..(first + groups_per_shard).min(sizes.len()) {
            writer.append_encoded_row_group(&source, g)?;
        }
        shards.push(writer.finish()?);
    }
    Ok(shards)
}

/// Tiles coloured by split (train grey, val blue, test orange) with sample centres as dark dots; north up.
fn draw_map(ctx: &PublishContext, centres: &[(f64, f64)], path: &Path) -> anyhow::Result<()> {
    let (x0, y0, x1, y1) = ctx.dem_bounds;
    let scale = ((x1 - x0).max(y1 - y0) / 800.0).max(1.0); // metres per map pixel
    let (w, h) = (
        ((x1 - x0) / scale).ceil() as u32,
        ((y1 - y0) / scale).ceil() as u32,
    );
    let colour = |s: Split| match s {
        Split::Train => image::Rgb([200, 200, 200]),
        Split::Val => image::Rgb([110, 160, 230]),
        Split::Test => image::Rgb([240, 160, 80]),
    };
    let mut img = image::RgbImage::from_fn(w, h, |px, py| {
        let (x, y) = (
            x0 + (px as f64 + 0.5) * scale,
            y1 - (py as f64 + 0.5) * scale,
        );
        let tile = tile_of(x, y, ctx.split_params.tile_size_m);
        let edge = |v: f64| {
            (v / ctx.split_params.tile_size_m).fract().abs() * ctx.split_params.tile_size_m < scale
        };
        if edge(x) || edge(y) {
            image::Rgb([90, 90, 90])
        } else {
            colour(split_of_tile(tile, ctx.seed, ctx.split_params))
        }
    });
    for &(x, y) in centres {
        let (px, py) = (((x - x0) / scale) as i64, ((y1 - y) / scale) as i64);
        if px >= 0 && py >= 0 && (px as u32) < w && (py as u32) < h {
            img.put_pixel(px as u32, py as u32, image::Rgb([20, 20, 20]));
        }
    }
    img.save_with_format(path, image::ImageFormat::Png)?;
    Ok(())
}

//! Publish: cut each split's sample file into shards `{split}-{i:05}-of-{n:05}.parquet` by copying its encoded
//! row groups (no decode, no re-encode), then write `manifest.json` (every shard with size, rows, row groups and
//! blake3; split counts; the train-only DEM std), a dataset card, Croissant JSON-LD, a summary (counts per split /
//! ortho / tile, rejections by reason) and a PNG map of tiles coloured by split with the sample centres.

use std::collections::BTreeMap;
use std::path::Path;

use dataset::manifest::{write_json_atomic, DatasetManifest, ShardEntry};
use dataset::publication::{croissant, dataset_card};

use arrow::array::{AsArray, RecordBatch};
use arrow::datatypes::Float64Type;
use dataset::schema::SCHEMA_VERSION;
use dataset::shard::{shard_name, EncodedRowGroups, ShardFile, ShardWriter};

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

/// What one split contributes to the summary and the map.
#[derive(Default)]
struct SplitTally {
    per_ortho: BTreeMap<String, u64>,
    per_tile: BTreeMap<String, u64>,
    centres: Vec<(f64, f64)>,
}

pub fn run(
    ctx: &PublishContext,
    projected: &ProjectedInputs,
    split_summary_path: &Path,
    dataset_dir: &Path,
    out: &PublishOutputs,
) -> anyhow::Result<()> {
    // The dataset stops looking finished before any shard changes: its manifest goes first (written back last).
    let published = dataset_dir.join("manifest.json");
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
    let results: Vec<anyhow::Result<(Vec<ShardEntry>, SplitTally)>> = std::thread::scope(|scope| {
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
    let mut per_ortho: BTreeMap<String, BTreeMap<String, u64>> = BTreeMap::new();
    let mut per_tile: BTreeMap<String, u64> = BTreeMap::new();
    let mut centres: Vec<(f64, f64)> = Vec::new();
    for (split, result) in Split::ALL.iter().zip(results) {
        let (split_shards, tally) = result?;
        split_counts.insert(
            split.name().to_string(),
            split_shards.iter().map(|s| s.rows).sum(),
        );
        shards.extend(split_shards);
        for (ortho, n) in tally.per_ortho {
            per_ortho
                .entry(ortho)
                .or_default()
                .insert(split.name().to_string(), n);
        }
        for (tile, n) in tally.per_tile {
            *per_tile.entry(tile).or_default() += n;
        }
        centres.extend(tally.centres);
    }
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

/// Cut one split's sample file into shards of `rows_per_shard` rows by copying whole encoded row groups, and
/// tally its rows per ortho and tile from the scalar columns (no tensor is decoded).
fn publish_split(
    dataset_dir: &Path,
    split: &str,
    path: &Path,
    ctx: &PublishContext,
) -> anyhow::Result<(Vec<ShardEntry>, SplitTally)> {
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
    for (i, groups) in (0..sizes.len())
        .collect::<Vec<_>>()
        .chunks(groups_per_shard)
        .enumerate()
    {
        let mut writer = ShardWriter::create(&dataset_dir.join(shard_name(split, i, count)))?;
        for &g in groups {
            writer.append_encoded_row_group(&source, g)?;
        }
        shards.push(writer.finish()?);
    }
    let mut tally = SplitTally::default();
    let file = ShardFile::open(path)?;
    for g in 0..sizes.len() {
        for batch in file.read_batches(g, None, false)? {
            let (orthos, tiles) = (
                string_column(&batch, "ortho_id", path)?,
                string_column(&batch, "tile_id", path)?,
            );
            let (xs, ys) = (
                f64_column(&batch, "center_x", path)?,
                f64_column(&batch, "center_y", path)?,
            );
            for i in 0..batch.num_rows() {
                *tally
                    .per_ortho
                    .entry(orthos.value(i).to_string())
                    .or_default() += 1;
                *tally
                    .per_tile
                    .entry(tiles.value(i).to_string())
                    .or_default() += 1;
                tally.centres.push((xs.value(i), ys.value(i)));
            }
        }
    }
    Ok((shards, tally))
}

fn string_column<'b>(
    batch: &'b RecordBatch,
    name: &str,
    path: &Path,
) -> anyhow::Result<&'b arrow::array::StringArray> {
    batch
        .column_by_name(name)
        .and_then(|c| c.as_string_opt::<i32>())
        .ok_or_else(|| anyhow::anyhow!("{}: no string column '{name}'", path.display()))
}

fn f64_column<'b>(
    batch: &'b RecordBatch,
    name: &str,
    path: &Path,
) -> anyhow::Result<&'b arrow::array::Float64Array> {
    batch
        .column_by_name(name)
        .and_then(|c| c.as_primitive_opt::<Float64Type>())
        .ok_or_else(|| anyhow::anyhow!("{}: no f64 column '{name}'", path.display()))
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

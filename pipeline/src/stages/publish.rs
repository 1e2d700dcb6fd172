//! Publish: stream the projected samples into per-split shards `{split}-{i:05}-of-{n:05}.parquet`, then write
//! `manifest.json` (every shard with size, rows, row groups and blake3; split counts; the train-only DEM std), a
//! dataset card, Croissant JSON-LD, a summary (counts per split / ortho / tile, rejections by reason) and a PNG map
//! of tiles coloured by split with the sample centres.

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use dataset::manifest::{write_json_atomic, DatasetManifest, ShardEntry};
use dataset::publication::{croissant, dataset_card};
use std::sync::Arc;

use arrow::array::{AsArray, Float64Array, RecordBatch, StringArray, UInt32Array};
use arrow::datatypes::{Float32Type, Float64Type};
use dataset::schema::{CROP_PX, DEM_PX, SCHEMA_VERSION};
use dataset::shard::{shard_name, ShardFile, ShardWriter};

use super::split::{split_of_tile, tile_of, Split, SplitParams};
use super::table::{read_table, strings};

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

#[allow(clippy::too_many_arguments)]
pub fn run(
    ctx: &PublishContext,
    samples_path: &Path,
    assignment_path: &Path,
    rejections_path: &Path,
    split_summary_path: &Path,
    dataset_dir: &Path,
    out: &PublishOutputs,
) -> anyhow::Result<()> {
    let batches = read_table(assignment_path)?;
    let (ids, splits, tiles) = (
        strings(&batches, "sample_id")?,
        strings(&batches, "split")?,
        strings(&batches, "tile_id")?,
    );
    let assignment: HashMap<String, (String, String)> =
        ids.into_iter().zip(splits.into_iter().zip(tiles)).collect();
    let mut split_counts: BTreeMap<String, u64> = Split::ALL
        .iter()
        .map(|s| (s.name().to_string(), 0))
        .collect();
    for (split, _) in assignment.values() {
        *split_counts.get_mut(split).expect("known split") += 1;
    }
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
    let shard_count = |split: &str| {
        (split_counts[split] as usize)
            .div_ceil(ctx.rows_per_shard)
            .max(1)
    };
    let mut shards: Vec<ShardEntry> = Vec::new();
    let (mut per_ortho, mut per_tile): (
        BTreeMap<String, BTreeMap<String, u64>>,
        BTreeMap<String, u64>,
    ) = Default::default();
    let (mut dem_sq_sum, mut dem_n) = (0f64, 0u64);
    let mut centres: Vec<(f64, f64)> = Vec::new();
    // Three kinds of thread, joined by bounded channels that keep row order: one decodes the projected row groups,
    // this one routes rows to splits (and gathers the summary), and one per split cuts its rows into shards and
    // encodes them (column chunks in parallel on the rayon pool). Routing and encoding then overlap; serially,
    // one core sat idle for most of the stage.
    // Rows stay in Arrow form end to end (take + column swap): converting each to a `Sample` and back cost a
    // copy of every tensor twice.
    let source = ShardFile::open(samples_path)?;
    let groups = source.row_group_sizes().len();
    std::thread::scope(|scope| -> anyhow::Result<()> {
        // Two decoders take alternate row groups (decoding FixedSizeList columns was the stage's longest serial
        // chain); taking from them in turn restores file order.
        const DECODERS: usize = 2;
        let mut decoded_groups = Vec::new();
        for first in 0..DECODERS {
            let (send, receive) =
                std::sync::mpsc::sync_channel::<anyhow::Result<Vec<RecordBatch>>>(1);
            decoded_groups.push(receive);
            let source = source.clone();
            scope.spawn(move || {
                for group in (first..groups).step_by(DECODERS) {
                    let decoded = source
                        .read_batches(group, None, true)
                        .map_err(anyhow::Error::from);
                    let failed = decoded.is_err();
                    if send.send(decoded).is_err() || failed {
                        break;
                    }
                }
            });
        }
        let receive = (0..groups).map(|group| {
            decoded_groups[group % DECODERS].recv().unwrap_or_else(|_| {
                Err(anyhow::anyhow!(
                    "row-group decoder stopped before group {group}"
                ))
            })
        });
        let mut to_split = Vec::new();
        let mut writers = Vec::new();
        for split in Split::ALL {
            let (send_rows, receive_rows) = std::sync::mpsc::sync_channel::<RecordBatch>(2);
            to_split.push(send_rows);
            let count = shard_count(split.name());
            writers.push(scope.spawn(move || {
                write_split_shards(
                    dataset_dir,
                    split.name(),
                    count,
                    ctx.rows_per_shard,
                    receive_rows,
                )
            }));
        }
        let routed_all = (|| -> anyhow::Result<()> {
            for decoded in receive {
                for batch in decoded? {
                    let ids = string_column(&batch, "sample_id")?;
                    let orthos = string_column(&batch, "ortho_id")?;
                    let (xs, ys) = (
                        f64_column(&batch, "center_x")?,
                        f64_column(&batch, "center_y")?,
                    );
                    let dem = batch
                        .column_by_name("dem")
                        .and_then(|c| c.as_fixed_size_list_opt())
                        .ok_or_else(|| {
                            anyhow::anyhow!("{}: no dem column", samples_path.display())
                        })?;
                    let routed: Vec<Option<&(String, String)>> = (0..batch.num_rows())
                        .map(|i| assignment.get(ids.value(i)))
                        .collect();
                    for (k, split) in Split::ALL.into_iter().enumerate() {
                        let rows: Vec<u32> = (0..batch.num_rows() as u32)
                            .filter(|&i| routed[i as usize].is_some_and(|(s, _)| s == split.name()))
                            .collect();
                        if rows.is_empty() {
                            continue;
                        }
                        for &i in &rows {
                            let i = i as usize;
                            let tile = &routed[i].expect("routed").1;
                            *per_ortho
                                .entry(orthos.value(i).to_string())
                                .or_default()
                                .entry(split.name().to_string())
                                .or_default() += 1;
                            *per_tile.entry(tile.clone()).or_default() += 1;
                            centres.push((xs.value(i), ys.value(i)));
                            if split == Split::Train {
                                // DEM normalisation statistic from the train split only: heights minus each crop's mean.
                                let heights = dem.value(i);
                                let interior =
                                    crop_interior(heights.as_primitive::<Float32Type>().values());
                                let n = (CROP_PX * CROP_PX) as f64;
                                let mean = interior.clone().sum::<f64>() / n;
                                dem_sq_sum +=
                                    interior.map(|h| (h - mean) * (h - mean)).sum::<f64>();
                                dem_n += (CROP_PX * CROP_PX) as u64;
                            }
                        }
                        let split_names = StringArray::from(vec![split.name(); rows.len()]);
                        let tile_ids: StringArray = rows
                            .iter()
                            .map(|&i| Some(routed[i as usize].expect("routed").1.as_str()))
                            .collect();
                        let taken =
                            arrow::compute::take_record_batch(&batch, &UInt32Array::from(rows))?;
                        let mut columns = taken.columns().to_vec();
                        let schema = taken.schema();
                        columns[schema.index_of("split")?] = Arc::new(split_names);
                        columns[schema.index_of("tile_id")?] = Arc::new(tile_ids);
                        let taken = RecordBatch::try_new(schema, columns)?;
                        if to_split[k].send(taken).is_err() {
                            return Ok(()); // that writer failed: its error is reported below
                        }
                    }
                }
            }
            Ok(())
        })();
        drop(to_split);
        for writer in writers {
            shards.extend(
                writer
                    .join()
                    .map_err(|_| anyhow::anyhow!("shard writer thread panicked"))??,
            );
        }
        routed_all
    })?;
    shards.sort_by(|a, b| a.path.cmp(&b.path));
    let dem_std_m = if dem_n > 0 {
        (dem_sq_sum / dem_n as f64).sqrt()
    } else {
        0.0
    };
    let manifest = DatasetManifest {
        schema_version: SCHEMA_VERSION.into(),
        name: ctx.name.into(),
        license: ctx.license.into(),
        seed: ctx.seed,
        crs: ctx.crs.into(),
        split_counts: split_counts.clone(),
        shards: shards.clone(),
        dem_std_m,
        pipeline_lock_blake3: ctx.lock_blake3.clone(),
    };
    let rejections: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(rejections_path)?)?;
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

/// Cut one split's rows (in arrival order) into `count` shards of `rows_per_shard` rows and write them.
fn write_split_shards(
    dataset_dir: &Path,
    split: &str,
    count: usize,
    rows_per_shard: usize,
    rows: std::sync::mpsc::Receiver<RecordBatch>,
) -> anyhow::Result<Vec<ShardEntry>> {
    let (mut shards, mut writer, mut in_shard) = (Vec::new(), None::<ShardWriter>, 0);
    for batch in rows {
        let mut start = 0;
        while start < batch.num_rows() {
            let shard = match writer.as_mut() {
                Some(shard) => shard,
                None => writer.insert(ShardWriter::create(&dataset_dir.join(shard_name(
                    split,
                    shards.len(),
                    count,
                )))?),
            };
            let len = (rows_per_shard - in_shard).min(batch.num_rows() - start);
            shard.write_batch(&batch.slice(start, len))?;
            in_shard += len;
            start += len;
            if in_shard == rows_per_shard {
                shards.push(writer.take().expect("open").finish()?);
                in_shard = 0;
            }
        }
    }
    if let Some(shard) = writer {
        shards.push(shard.finish()?);
    }
    Ok(shards)
}

/// The 128 × 128 crop heights (apron excluded) in f64, row-major, from a 130 × 130 DEM crop.
fn crop_interior(dem_m: &[f32]) -> impl Iterator<Item = f64> + Clone + '_ {
    (1..=CROP_PX).flat_map(move |r| {
        dem_m[r * DEM_PX + 1..=r * DEM_PX + CROP_PX]
            .iter()
            .map(|&h| h as f64)
    })
}

fn string_column<'b>(batch: &'b RecordBatch, name: &str) -> anyhow::Result<&'b StringArray> {
    batch
        .column_by_name(name)
        .and_then(|c| c.as_string_opt::<i32>())
        .ok_or_else(|| anyhow::anyhow!("projected samples have no string column '{name}'"))
}

fn f64_column<'b>(batch: &'b RecordBatch, name: &str) -> anyhow::Result<&'b Float64Array> {
    batch
        .column_by_name(name)
        .and_then(|c| c.as_primitive_opt::<Float64Type>())
        .ok_or_else(|| anyhow::anyhow!("projected samples have no f64 column '{name}'"))
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

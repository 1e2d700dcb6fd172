//! Publish: stream the projected samples into per-split shards `{split}-{i:05}-of-{n:05}.parquet`, then write
//! `manifest.json` (every shard with size, rows, row groups and blake3; split counts; the train-only DEM std), a
//! dataset card, Croissant JSON-LD, a summary (counts per split / ortho / tile, rejections by reason) and a PNG map
//! of tiles coloured by split with the sample centres.

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use dataset::manifest::{write_json_atomic, DatasetManifest, ShardEntry};
use dataset::publication::{croissant, dataset_card};
use dataset::schema::{Sample, CROP_PX, DEM_PX, SCHEMA_VERSION};
use dataset::shard::{read_row_group, row_group_sizes, shard_name, ShardWriter};

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
    struct Open {
        writer: Option<ShardWriter>,
        index: usize,
        rows: usize,
    }
    let mut open: BTreeMap<String, Open> = split_counts
        .keys()
        .map(|s| {
            (
                s.clone(),
                Open {
                    writer: None,
                    index: 0,
                    rows: 0,
                },
            )
        })
        .collect();
    let mut shards: Vec<ShardEntry> = Vec::new();
    let (mut per_ortho, mut per_tile): (
        BTreeMap<String, BTreeMap<String, u64>>,
        BTreeMap<String, u64>,
    ) = Default::default();
    let (mut dem_sq_sum, mut dem_n) = (0f64, 0u64);
    let mut centres: Vec<(f64, f64)> = Vec::new();
    // Decoding row groups runs on its own thread while this one routes and encodes: order is kept by the channel.
    let groups = row_group_sizes(samples_path)?.len();
    let (send, receive) = std::sync::mpsc::sync_channel::<anyhow::Result<Vec<Sample>>>(2);
    let reader = std::thread::spawn({
        let samples_path = samples_path.to_path_buf();
        move || {
            for group in 0..groups {
                let decoded = read_row_group(&samples_path, group).map_err(anyhow::Error::from);
                let failed = decoded.is_err();
                if send.send(decoded).is_err() || failed {
                    break;
                }
            }
        }
    });
    for decoded in receive {
        let group_samples = decoded?;
        for mut sample in group_samples {
            let Some((split, tile)) = assignment.get(&sample.sample_id) else {
                continue;
            };
            sample.split = split.clone();
            sample.tile_id = tile.clone();
            *per_ortho
                .entry(sample.ortho_id.clone())
                .or_default()
                .entry(split.clone())
                .or_default() += 1;
            *per_tile.entry(tile.clone()).or_default() += 1;
            centres.push((sample.center_x_m, sample.center_y_m));
            if split == "train" {
                // DEM normalisation statistic from the train split only: heights minus each crop's mean (f64).
                let interior = crop_interior(&sample);
                let mean = interior.iter().sum::<f64>() / interior.len() as f64;
                dem_sq_sum += interior
                    .iter()
                    .map(|h| (h - mean) * (h - mean))
                    .sum::<f64>();
                dem_n += interior.len() as u64;
            }
            let state = open.get_mut(split).expect("known split");
            if state.writer.is_none() {
                let path = dataset_dir.join(shard_name(split, state.index, shard_count(split)));
                state.writer = Some(ShardWriter::create(&path)?);
            }
            state
                .writer
                .as_mut()
                .expect("just opened")
                .write(std::slice::from_ref(&sample))?;
            state.rows += 1;
            if state.rows == ctx.rows_per_shard {
                shards.push(state.writer.take().expect("open").finish()?);
                state.index += 1;
                state.rows = 0;
            }
        }
    }
    reader
        .join()
        .map_err(|_| anyhow::anyhow!("row-group reader thread panicked"))?;
    for state in open.values_mut() {
        if let Some(writer) = state.writer.take() {
            shards.push(writer.finish()?);
        }
    }
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

/// The 128 × 128 crop heights (apron excluded) in f64.
fn crop_interior(sample: &Sample) -> Vec<f64> {
    (1..=CROP_PX)
        .flat_map(|r| (1..=CROP_PX).map(move |c| (r, c)))
        .map(|(r, c)| sample.dem_m[r * DEM_PX + c] as f64)
        .collect()
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

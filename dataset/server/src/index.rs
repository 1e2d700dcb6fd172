//! What the server knows about a published dataset, loaded once at start: the manifest, every shard's footer,
//! and every row's metadata (ids, splits, tiles, centres, geometry scalars; no rasters), so listings, filters and
//! id lookups never touch the shards and tensor reads go straight to the one row group they need.

use std::collections::{BTreeMap, HashMap};
use std::path::Path;
use std::sync::Arc;

use anyhow::{bail, Context, Result};

use dataset::contract::manifest::DatasetManifest;
use dataset::contract::planner::RowGroupRef;
use dataset::contract::publication::{CARD_FILE, MANIFEST_FILE, SUMMARY_FILE};
use dataset::contract::schema::Sample;
use dataset::contract::shard::ShardFile;
use dataset::storage::DatasetLocation;

use crate::cache::ServerCache;

/// One row: its metadata and where it lives.
pub struct RowEntry {
    /// Raster fields empty (see [`dataset::contract::schema::batch_to_sample_metadata`]).
    pub meta: Sample,
    pub shard: usize,
    pub row_group: usize,
    pub row: usize,
}

/// One geographic split tile, as the rows describe it.
#[derive(Debug, Clone, serde::Serialize)]
pub struct TileEntry {
    pub tile_id: String,
    pub split: String,
    pub count: u64,
    /// Bounds of the sample centres in map metres: [min_x, min_y, max_x, max_y].
    pub centres_bbox_m: [f64; 4],
    /// The tile's square in map metres, when `summary.json` states the tile size.
    pub rect_m: Option<[f64; 4]>,
}

pub struct DatasetIndex {
    /// The dataset's directory, or its prefix in object storage.
    pub location: DatasetLocation,
    pub manifest: DatasetManifest,
    pub manifest_bytes: Vec<u8>,
    pub manifest_blake3: String,
    pub card: String,
    pub croissant: serde_json::Value,
    pub shards: Vec<ShardFile>,
    pub shard_names: Vec<String>,
    pub rows: Vec<RowEntry>,
    /// Split → indices into `rows`, in the split's fixed order (sorted shard names, then file order).
    pub splits: BTreeMap<String, Vec<usize>>,
    pub row_groups: BTreeMap<String, Vec<RowGroupRef>>,
    pub tiles: Vec<TileEntry>,
    /// Decoded rows and previews kept between requests, within the `serve --cache-mib` budget.
    pub cache: ServerCache,
    by_id: HashMap<String, usize>,
}

/// `t_{col}_{row}` → (col, row).
fn parse_tile_id(tile_id: &str) -> Option<(i64, i64)> {
    let rest = tile_id.strip_prefix("t_")?;
    let (col, row) = rest.rsplit_once('_')?;
    Some((col.parse().ok()?, row.parse().ok()?))
}

impl DatasetIndex {
    /// Load `manifest.json` from a directory or a prefix in object storage, check every shard's size (and blake3
    /// when `verify_hashes`: every shard read once), read all footers and row metadata (from a bucket: only the
    /// metadata columns' bytes). Decoded rows and previews are then kept within `cache_bytes`.
    pub fn load(location: DatasetLocation, verify_hashes: bool, cache_bytes: u64) -> Result<Self> {
        let Some(manifest_bytes) = location.read_if_exists(MANIFEST_FILE)? else {
            bail!(
                "{}: no manifest.json: point at a published dataset, a directory or its object-storage URL (g2r-pipeline run writes OUT/dataset)",
                location.describe()
            );
        };
        let manifest_path = location.describe_file(MANIFEST_FILE);
        let manifest_text = std::str::from_utf8(&manifest_bytes)
            .with_context(|| format!("{manifest_path}: not UTF-8; re-publish the dataset"))?;
        let manifest = DatasetManifest::parse(manifest_text, Path::new(&manifest_path))?;
        let manifest_blake3 = blake3::hash(&manifest_bytes).to_hex().to_string();
        for shard in &manifest.shards {
            let path = location.describe_file(&shard.path);
            let bytes = location.size(&shard.path).with_context(|| {
                format!("{path}: listed in manifest.json but not readable (re-publish the dataset if it is missing)")
            })?;
            if bytes != shard.bytes {
                bail!(
                    "{path}: {bytes} bytes, manifest.json says {}; re-publish the dataset (or run g2r-dataset verify)",
                    shard.bytes
                );
            }
            if verify_hashes && location.blake3(&shard.path)? != shard.blake3 {
                bail!("{path}: blake3 does not match manifest.json; re-publish the dataset");
            }
        }
        let summary: serde_json::Value = location
            .read_if_exists(SUMMARY_FILE)?
            .and_then(|bytes| serde_json::from_slice(&bytes).ok())
            .unwrap_or(serde_json::Value::Null);
        let card = match location.read_if_exists(CARD_FILE)? {
            Some(bytes) => String::from_utf8_lossy(&bytes).into_owned(),
            None => dataset::contract::publication::dataset_card(&manifest, &summary),
        };
        let croissant = dataset::contract::publication::croissant(&manifest);

        let (mut shards, mut rows) = (Vec::new(), Vec::new());
        let mut splits: BTreeMap<String, Vec<usize>> = manifest
            .split_counts
            .keys()
            .map(|k| (k.clone(), Vec::new()))
            .collect();
        // Every split gets an entry, even one with no shard (publish lists empty splits with count 0).
        let mut row_groups: BTreeMap<String, Vec<RowGroupRef>> = manifest
            .split_counts
            .keys()
            .map(|k| (k.clone(), Vec::new()))
            .collect();
        for split in manifest.split_counts.keys() {
            for name in manifest.split_shards(split) {
                let file = dataset::contract::shard::ShardFile::open_in(&location, name)?;
                let shard = shards.len();
                let sizes = file.row_group_sizes();
                let metadata = file.read_metadata()?;
                let mut next = metadata.into_iter();
                for (row_group, &n) in sizes.iter().enumerate() {
                    row_groups
                        .entry(split.clone())
                        .or_default()
                        .push(RowGroupRef {
                            shard: name.to_string(),
                            row_group,
                            rows: n,
                        });
                    for row in 0..n {
                        let meta = next.next().with_context(|| {
                            format!(
                                "{}: row metadata shorter than the footer says; re-publish the dataset",
                                file.path().display()
                            )
                        })?;
                        if meta.split.name() != split.as_str() {
                            bail!(
                                "{}: row {row} of row group {row_group} says split '{}'; re-publish the dataset",
                                file.path().display(),
                                meta.split
                            );
                        }
                        splits.get_mut(split).expect("made above").push(rows.len());
                        rows.push(RowEntry {
                            meta,
                            shard,
                            row_group,
                            row,
                        });
                    }
                }
                if next.next().is_some() {
                    bail!(
                        "{}: more rows than the footer's row groups say; re-publish the dataset",
                        file.path().display()
                    );
                }
                shards.push(file);
            }
        }
        let listed: usize = splits.values().map(Vec::len).sum();
        if listed
            != manifest
                .shards
                .iter()
                .map(|s| s.rows as usize)
                .sum::<usize>()
        {
            bail!(
                "{}: shards hold {listed} rows of known splits, manifest.json lists {}; re-publish the dataset",
                location.describe(),
                manifest.shards.iter().map(|s| s.rows).sum::<u64>()
            );
        }
        let shard_names: Vec<String> = shards
            .iter()
            .map(|s| s.path().file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        let by_id = rows
            .iter()
            .enumerate()
            .map(|(i, r)| (r.meta.sample_id.clone(), i))
            .collect();
        let tile_size_m = summary["split"]["tile_size_m"].as_f64();
        let mut tiles: BTreeMap<String, TileEntry> = BTreeMap::new();
        for r in &rows {
            let (x, y) = (r.meta.center_x_m, r.meta.center_y_m);
            let t = tiles
                .entry(r.meta.tile_id.clone())
                .or_insert_with(|| TileEntry {
                    tile_id: r.meta.tile_id.clone(),
                    split: r.meta.split.name().to_string(),
                    count: 0,
                    centres_bbox_m: [x, y, x, y],
                    rect_m: tile_size_m.zip(parse_tile_id(&r.meta.tile_id)).map(
                        |(size, (c, rw))| {
                            [
                                c as f64 * size,
                                rw as f64 * size,
                                (c + 1) as f64 * size,
                                (rw + 1) as f64 * size,
                            ]
                        },
                    ),
                });
            t.count += 1;
            let b = &mut t.centres_bbox_m;
            *b = [b[0].min(x), b[1].min(y), b[2].max(x), b[3].max(y)];
        }
        Ok(Self {
            location,
            manifest,
            manifest_bytes,
            manifest_blake3,
            card,
            croissant,
            shards,
            shard_names,
            rows,
            splits,
            row_groups,
            tiles: tiles.into_values().collect(),
            cache: ServerCache::new(cache_bytes),
            by_id,
        })
    }

    /// Index into `rows` of a sample id.
    pub fn row_index(&self, sample_id: &str) -> Option<usize> {
        self.by_id.get(sample_id).copied()
    }

    /// Index of a shard by its file name, only for names the manifest lists (the server serves nothing else).
    pub fn shard_by_name(&self, name: &str) -> Option<usize> {
        self.shard_names.iter().position(|n| n == name)
    }

    /// Full samples (with rasters) of `rows`: from the cache, or their metadata from the index with the rasters
    /// read from their row groups (the tensor columns' pages of those rows only) and kept in the cache.
    pub fn read_full(&self, rows: &[usize]) -> Result<Vec<Arc<Sample>>> {
        let cached: Vec<Option<Arc<Sample>>> = rows.iter().map(|&i| self.cache.row(i)).collect();
        // The rows not cached, by (shard, row group), each row once, in file order.
        let mut groups: BTreeMap<(usize, usize), BTreeMap<usize, usize>> = BTreeMap::new();
        for (&i, kept) in rows.iter().zip(&cached) {
            if kept.is_none() {
                let r = &self.rows[i];
                groups
                    .entry((r.shard, r.row_group))
                    .or_default()
                    .insert(r.row, i);
            }
        }
        let mut read: HashMap<usize, Arc<Sample>> = HashMap::new();
        for ((shard, row_group), wanted) in groups {
            let file_rows: Vec<usize> = wanted.keys().copied().collect();
            let mut samples: Vec<Sample> = wanted
                .values()
                .map(|&i| self.rows[i].meta.clone())
                .collect();
            self.shards[shard].fill_tensors(row_group, &file_rows, &mut samples)?;
            for (&i, sample) in wanted.values().zip(samples) {
                let sample = Arc::new(sample);
                self.cache.keep_row(i, sample.clone());
                read.insert(i, sample);
            }
        }
        Ok(cached
            .into_iter()
            .zip(rows)
            .map(|(cached, i)| cached.unwrap_or_else(|| read[i].clone()))
            .collect())
    }
}

//! Fixtures for tests and benchmarks of this and the other crates: a varied synthetic sample and a published
//! dataset directory written exactly as the publish stage lays it out (shards, manifest, summary, card, Croissant);
//! an S3 server and a failing network link for the object-storage tests ([`s3`]); a one-node Slurm cluster on
//! loopback ([`slurm`]).

pub mod s3;
pub mod slurm;

use std::collections::BTreeMap;
use std::path::Path;

use crate::contract::crater_frame::CraterPosition;
use crate::contract::manifest::DatasetManifest;
use crate::contract::schema::{
    ContextWindow, Sample, Split, CONTEXT_PX, CROP_PX, DEM_PX, SCHEMA_VERSION,
};
use crate::contract::shard::{shard_name, ShardWriter};
use crate::files::write_json_atomic;

/// Sample `i`: every field set, rasters varying with `i` (split "train", tile "t_3_4").
pub fn synthetic_sample(i: usize) -> Sample {
    let n = CROP_PX * CROP_PX;
    Sample {
        sample_id: format!("ortho_{i}:{}:{}", 100 + i, 200 + i),
        split: Split::Train,
        tile_id: "t_3_4".into(),
        ortho_id: format!("ortho_{i}"),
        center_x_m: 1000.0 + i as f64,
        center_y_m: -1_300_000.0,
        center_lon_deg: -11.2,
        center_lat_deg: -43.3,
        footprint_lonlat_deg: [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0],
        dem_m: (0..DEM_PX * DEM_PX)
            .map(|k| (k as f32 * 0.01 + i as f32).sin() * 30.0 - 1500.0)
            .collect(),
        image: (0..n).map(|k| (k % 97) as f32 / 97.0).collect(),
        valid: (0..n).map(|k| (k % 13 != 0) as u8).collect(),
        sun_lit: (0..n).map(|k| ((k % 7) as f32 / 6.0).min(1.0)).collect(),
        sun_dir_enu: [0.5, 0.0, 0.866],
        camera_pos_enu_m: [10.0, -20.0, 50_000.0],
        enu_origin_height_m: -1200.0,
        map_to_en: [0.98, 0.01, -0.01, 1.0],
        camera_att: [1.0, 0.0, 0.0, 0.0],
        fov_deg: 2.85,
        gsd_m: 5.0,
        incidence_deg: 60.0,
        emission_deg: 1.0,
        phase_deg: 59.0,
        acq_time: "2011-05-01T12:00:00Z".into(),
        provenance: "test".into(),
        context: Some(ContextWindow {
            gsd_m: 512.0,
            heights_m: (0..CONTEXT_PX * CONTEXT_PX)
                .map(|k| (k as f32 * 0.05 + i as f32).cos() * 200.0 - 1400.0)
                .collect(),
            highland: Some(
                (0..CONTEXT_PX * CONTEXT_PX)
                    .map(|k| ((k + i) % 5) as f32 / 4.0)
                    .collect(),
            ),
        }),
        crater: Some(CraterPosition {
            rho: 0.25 * i as f64,
            relative_height_m: 10.0 * i as f64 - 40.0,
            relief_to_diameter: Some(0.06 + 0.005 * i as f64),
        }),
    }
}

/// Publish `splits` (split name → shards → rows) into `dir` with the given summary's split section (tile size etc.);
/// returns the manifest. Rows keep their own `split` field: set it to match.
pub fn write_dataset(
    dir: &Path,
    name: &str,
    splits: &[(&str, Vec<Vec<Sample>>)],
    split_summary: serde_json::Value,
) -> anyhow::Result<DatasetManifest> {
    std::fs::create_dir_all(dir)?;
    let (mut shards, mut counts) = (Vec::new(), BTreeMap::new());
    for (split, split_shards) in splits {
        for (k, rows) in split_shards.iter().enumerate() {
            let mut writer =
                ShardWriter::create(&dir.join(shard_name(split, k, split_shards.len())))?;
            writer.write(rows)?;
            shards.push(writer.finish()?);
        }
        counts.insert(
            split.to_string(),
            split_shards.iter().map(|s| s.len() as u64).sum(),
        );
    }
    shards.sort_by(|a, b| a.path.cmp(&b.path));
    let manifest = DatasetManifest {
        schema_version: SCHEMA_VERSION.into(),
        name: name.into(),
        license: "CC-BY-4.0".into(),
        seed: 9,
        crs: "fixture".into(),
        split_counts: counts,
        shards,
        dem_std_m: 20.0,
        pipeline_lock_blake3: String::new(),
        crater_frame: None,
    };
    let summary = serde_json::json!({ "split": split_summary, "rejections_by_ortho": {} });
    write_json_atomic(&dir.join("summary.json"), &summary)?;
    crate::contract::publication::write_descriptions(dir, &manifest)?;
    write_json_atomic(&dir.join("manifest.json"), &manifest)?;
    Ok(manifest)
}

/// Columns schema 1.1 did not have: the context window's (1.2, 1.6) and the crater frame's (1.3, 1.4).
pub fn is_newer_than_1_1(column: &str) -> bool {
    column.starts_with("context_") || column.starts_with("crater_")
}

/// Rewrite a dataset written by [`write_dataset`] as schema 1.1 wrote it: shards without the context and crater
/// columns ([`is_newer_than_1_1`]) and with version 1.1.0 in their metadata, and the manifest updated (version,
/// sizes, blake3). For tests that old datasets still read and serve.
pub fn downgrade_to_schema_1_1(dir: &Path) -> anyhow::Result<()> {
    use std::sync::Arc;
    let mut manifest = DatasetManifest::load_dir(dir)?;
    for shard in &mut manifest.shards {
        let path = dir.join(&shard.path);
        let file = crate::contract::shard::ShardFile::open(&path)?;
        let schema = file.schema();
        let keep: Vec<usize> = (0..schema.fields().len())
            .filter(|&k| !is_newer_than_1_1(schema.field(k).name()))
            .collect();
        let mut metadata = schema.metadata().clone();
        metadata.insert("g2r.schema_version".to_string(), "1.1.0".to_string());
        let old_schema = Arc::new(schema.project(&keep)?.with_metadata(metadata));
        let mut batches = Vec::new();
        for group in 0..file.row_group_sizes().len() {
            for batch in file.read_batches(group, None, true)? {
                batches.push(arrow::array::RecordBatch::try_new(
                    old_schema.clone(),
                    batch.project(&keep)?.columns().to_vec(),
                )?);
            }
        }
        let mut writer =
            parquet::arrow::ArrowWriter::try_new(std::fs::File::create(&path)?, old_schema, None)?;
        for batch in &batches {
            writer.write(batch)?;
        }
        writer.close()?;
        shard.bytes = std::fs::metadata(&path)?.len();
        shard.blake3 = crate::files::hash_file(&path)?;
    }
    manifest.schema_version = "1.1.0".into();
    write_json_atomic(&dir.join("manifest.json"), &manifest)?;
    Ok(())
}

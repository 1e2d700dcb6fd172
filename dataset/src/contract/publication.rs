//! The human- and machine-readable descriptions published next to the shards: the dataset card (`README.md`) and
//! Croissant JSON-LD (`croissant.json`). Both are pure functions of `manifest.json` and `summary.json`, so the
//! pipeline's publish stage and `g2r-dataset publish` (re)write the same bytes.

use std::collections::BTreeMap;
use std::path::Path;

use crate::contract::manifest::DatasetManifest;
use crate::contract::schema::{sample_schema, schema_markdown, SCHEMA_VERSION};
use crate::files::write_json_atomic;

/// The manifest's own name is defined beside the manifest (which loads itself by it) and listed here with the
/// rest of the published file names.
pub use crate::contract::manifest::MANIFEST_FILE;
/// The dataset card.
pub const CARD_FILE: &str = "README.md";
/// The Croissant JSON-LD description.
pub const CROISSANT_FILE: &str = "croissant.json";
/// The publish stage's counts: pairs per split, ortho and tile, rejections by reason.
pub const SUMMARY_FILE: &str = "summary.json";
/// Tiles coloured by split, with the sample centres.
pub const MAP_FILE: &str = "map.png";
/// Every document published beside the shards except the manifest, in the order publish writes them.
pub const DOCUMENT_FILES: [&str; 4] = [CARD_FILE, CROISSANT_FILE, SUMMARY_FILE, MAP_FILE];

/// Rejected crops summed over orthos, by reason, from `summary.json`'s `rejections_by_ortho`.
fn rejected_by_reason(summary: &serde_json::Value) -> BTreeMap<String, u64> {
    let mut rejected: BTreeMap<String, u64> = BTreeMap::new();
    let per_ortho = summary["rejections_by_ortho"].as_object();
    for reasons in per_ortho.into_iter().flat_map(|m| m.values()) {
        for (reason, n) in reasons.as_object().into_iter().flatten() {
            *rejected.entry(reason.clone()).or_default() += n.as_u64().unwrap_or(0);
        }
    }
    rejected
}

/// The dataset card (Markdown). `summary` is the publish stage's `summary.json` (`Null` if there is none).
pub fn dataset_card(m: &DatasetManifest, summary: &serde_json::Value) -> String {
    let total: u64 = m.split_counts.values().sum();
    let bytes: u64 = m.shards.iter().map(|s| s.bytes).sum();
    let split = &summary["split"];
    let how = if split.is_null() {
        "No `summary.json` was published with the shards: split and rejection details are unknown."
            .to_string()
    } else {
        format!(
            "Splits are geographic: tiles of {tile} m assigned by a keyed hash; a sample's whole footprint \
             (+ {guard} m guard band) lies in tiles of its split; {dropped} sampled crops straddling splits were dropped \
             before projection. Projected crops rejected by reason: {rej:?}.",
            tile = split["tile_size_m"],
            guard = split["guard_band_m"],
            dropped = split["dropped_straddling_splits"],
            rej = rejected_by_reason(summary),
        )
    };
    format!(
        "# {name}\n\nLunar DEM–image pairs for learning a spatially varying BRDF from terrain geometry.\n\n\
         - pairs: {total} ({splits})\n- shards: {n} Parquet files, {mib:.1} MiB\n- license: {license}\n- seed: {seed}\n\
         - schema version: {schema}\n- DEM std for normalisation (train split only, crop mean removed): {std:.3} m\n\n\
         ## How it was made\n\n`g2r-pipeline run` (ingest → erode → sample → split → project → publish). {how}\n\n\
         ## Schema\n\n{schema_table}\n\
         Read with pyarrow: `pyarrow.parquet.read_table(\"train-00000-of-NNNNN.parquet\")`; with polars: \
         `polars.read_parquet(...)`. Serve over HTTP: `g2r-dataset serve DIR`.\n",
        name = m.name,
        splits = m
            .split_counts
            .iter()
            .map(|(k, v)| format!("{k} {v}"))
            .collect::<Vec<_>>()
            .join(", "),
        n = m.shards.len(),
        mib = bytes as f64 / (1 << 20) as f64,
        license = m.license,
        seed = m.seed,
        schema = SCHEMA_VERSION,
        std = m.dem_std_m,
        schema_table = schema_markdown(),
    )
}

/// Croissant 1.0 JSON-LD: one FileObject per shard (blake3 alongside, as Croissant has no blake3 field) and one
/// RecordSet whose fields are the sample schema's columns.
pub fn croissant(m: &DatasetManifest) -> serde_json::Value {
    let files: Vec<serde_json::Value> = m
        .shards
        .iter()
        .map(|s| {
            serde_json::json!({
                "@type": "cr:FileObject", "@id": s.path, "name": s.path, "contentUrl": s.path,
                "encodingFormat": "application/x-parquet", "sha256": serde_json::Value::Null, "md5": serde_json::Value::Null,
                "contentSize": format!("{} B", s.bytes), "g2r:blake3": s.blake3,
            })
        })
        .collect();
    let fields: Vec<serde_json::Value> = sample_schema()
        .fields()
        .iter()
        .map(|f| serde_json::json!({ "@type": "cr:Field", "name": f.name(), "description": f.metadata().get("description"), "dataType": f.data_type().to_string() }))
        .collect();
    serde_json::json!({
        "@context": { "@vocab": "https://schema.org/", "cr": "http://mlcommons.org/croissant/", "g2r": "https://example.org/g2r#" },
        "@type": "Dataset",
        "conformsTo": "http://mlcommons.org/croissant/1.0",
        "name": m.name,
        "license": m.license,
        "description": "Lunar DEM crops (5 m, 130x130 with apron) paired with orthoimage reflectance and per-pixel geometry.",
        "distribution": files,
        "recordSet": [{ "@type": "cr:RecordSet", "name": "samples", "field": fields }],
    })
}

/// Write `README.md` and `croissant.json` into `dir` (atomically) from `manifest` and `dir/summary.json`.
pub fn write_descriptions(dir: &Path, manifest: &DatasetManifest) -> anyhow::Result<()> {
    let summary_path = dir.join(SUMMARY_FILE);
    let summary: serde_json::Value = match std::fs::read_to_string(&summary_path) {
        Ok(text) => serde_json::from_str(&text).map_err(|e| {
            anyhow::anyhow!(
                "{}: not valid JSON ({e}); re-run the pipeline's publish stage",
                summary_path.display()
            )
        })?,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => serde_json::Value::Null,
        Err(e) => return Err(anyhow::anyhow!("{}: {e}", summary_path.display())),
    };
    crate::files::write_text_atomic(&dir.join(CARD_FILE), &dataset_card(manifest, &summary))?;
    write_json_atomic(&dir.join(CROISSANT_FILE), &croissant(manifest))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::contract::manifest::ShardEntry;

    fn manifest() -> DatasetManifest {
        DatasetManifest {
            schema_version: SCHEMA_VERSION.into(),
            name: "card-test".into(),
            license: "CC-BY-4.0".into(),
            seed: 7,
            crs: "x".into(),
            split_counts: BTreeMap::from([("train".into(), 3), ("val".into(), 1)]),
            shards: vec![ShardEntry {
                path: "train-00000-of-00001.parquet".into(),
                bytes: 2 << 20,
                rows: 3,
                row_groups: 1,
                blake3: "ab".into(),
            }],
            dem_std_m: 12.5,
            pipeline_lock_blake3: String::new(),
            crater_frame: None,
        }
    }

    #[test]
    fn card_sums_rejections_and_states_split_rules() {
        let summary = serde_json::json!({
            "split": { "dropped_straddling_splits": 5, "tile_size_m": 2560.0, "guard_band_m": 0.0 },
            "rejections_by_ortho": { "A": { "too_shadowed": 2 }, "B": { "too_shadowed": 3, "camera_occluded": 1 } },
        });
        let card = dataset_card(&manifest(), &summary);
        assert!(card.contains("- pairs: 4 (train 3, val 1)"), "{card}");
        assert!(card.contains("2.0 MiB"));
        assert!(card.contains("tiles of 2560.0 m"));
        assert!(card.contains("5 sampled crops straddling"));
        assert!(
            card.contains(r#"{"camera_occluded": 1, "too_shadowed": 5}"#),
            "{card}"
        );
        let bare = dataset_card(&manifest(), &serde_json::Value::Null);
        assert!(bare.contains("No `summary.json`"));
    }

    #[test]
    fn croissant_lists_every_shard_and_column() {
        let c = croissant(&manifest());
        assert_eq!(
            c["distribution"][0]["contentUrl"],
            "train-00000-of-00001.parquet"
        );
        assert_eq!(
            c["recordSet"][0]["field"].as_array().unwrap().len(),
            sample_schema().fields().len()
        );
    }
}

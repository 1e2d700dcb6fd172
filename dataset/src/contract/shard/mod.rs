//! Parquet shard IO: float tensors with BYTE_STREAM_SPLIT + zstd, ~256-row row groups (one range read per random
//! access), written under a temporary name and renamed when complete.
//!
//! `write.rs`: [`ShardWriter`] (row groups encoded in parallel, hashed while written) and [`EncodedRowGroups`]
//! (row groups copied verbatim); `read.rs`: [`ShardFile`] (random access by row group or row, local or in object
//! storage) and the footer-only helpers.

mod read;
mod write;

pub use read::*;
pub use write::*;

use std::path::PathBuf;

use parquet::arrow::ArrowSchemaConverter;
use parquet::basic::{Compression, Encoding, Type as PhysicalType, ZstdLevel};
use parquet::file::properties::{EnabledStatistics, WriterProperties};

use crate::contract::schema::{
    sample_schema, SchemaError, FLOAT_TENSOR_COLUMNS, SCHEMA_VERSION, TENSOR_COLUMNS,
};

/// Rows per row group: ~256 samples ≈ 55 MB uncompressed, one HTTP range read for random access.
pub const ROW_GROUP_ROWS: usize = 256;

#[derive(Debug, thiserror::Error)]
pub enum ShardError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error(
        "{path}: Parquet error ({source}); the shard may be truncated: re-run the publish stage"
    )]
    Parquet {
        path: PathBuf,
        source: parquet::errors::ParquetError,
    },
    /// A remote shard's bytes did not arrive after object_store's retries: the network or the store failed, the
    /// shard itself may be whole.
    #[error("{path}: {message}; the network or the store failed: run again, or allow more retries (G2R_STORE_MAX_RETRIES, G2R_STORE_RETRY_TIMEOUT_S)")]
    Fetch { path: PathBuf, message: String },
    #[error("{path}: {source}")]
    Schema { path: PathBuf, source: SchemaError },
    #[error("{path}: no row group {row_group} (the shard has {count})")]
    RowGroup {
        path: PathBuf,
        row_group: usize,
        count: usize,
    },
    #[error("{path}: written with schema {found}, this build reads {SCHEMA_VERSION}; rebuild the dataset or use a matching g2r version")]
    SchemaVersion { path: PathBuf, found: String },
}

impl ShardError {
    /// A Parquet error while reading `path`, a remote object when `remote`. There an external error is a read that
    /// failed ([`crate::storage::RemoteObject::fetch`] is where one comes from): reported as such, not as a damaged
    /// shard. From a local file an external error is the file's own I/O error: a short read is a file cut short (a
    /// damaged shard), any other (a full descriptor table, a failing disk) is reported as itself.
    pub fn reading(
        path: &std::path::Path,
        source: parquet::errors::ParquetError,
        remote: bool,
    ) -> Self {
        use parquet::errors::ParquetError::External;
        match source {
            External(inner) if remote => ShardError::Fetch {
                path: path.to_path_buf(),
                message: inner.to_string(),
            },
            External(inner) => match inner.downcast::<std::io::Error>() {
                Ok(io) if io.kind() != std::io::ErrorKind::UnexpectedEof => ShardError::Io {
                    path: path.to_path_buf(),
                    source: *io,
                },
                Ok(io) => ShardError::Parquet {
                    path: path.to_path_buf(),
                    source: External(io),
                },
                Err(inner) => ShardError::Parquet {
                    path: path.to_path_buf(),
                    source: External(inner),
                },
            },
            source => ShardError::Parquet {
                path: path.to_path_buf(),
                source,
            },
        }
    }
}

/// Uncompressed bytes at which a tensor column's data page is closed: two rows of a 64 KiB raster. A reader that
/// wants one row (the server, a shuffled trainer) decompresses the whole page it lies on, and with the offset index
/// it decompresses no other; Parquet's default 1 MiB page made that 16 rows of each raster for every row read.
pub const TENSOR_PAGE_BYTES: usize = 128 << 10;

/// Writer properties: zstd everywhere; on the tensor leaves no dictionary (interning the 16k values per row of the
/// `valid` mask was ~9 % of the writer thread's time in the tycho-full project stage), no page statistics
/// (min/max of a tensor column helps no query), pages of [`TENSOR_PAGE_BYTES`], and BYTE_STREAM_SPLIT on the float
/// ones.
pub fn writer_properties() -> WriterProperties {
    let schema = sample_schema();
    let descriptor = ArrowSchemaConverter::new()
        .convert(&schema)
        .expect("the sample schema converts to Parquet");
    let mut builder = WriterProperties::builder()
        .set_compression(Compression::ZSTD(
            ZstdLevel::try_new(3).expect("valid zstd level"),
        ))
        .set_max_row_group_row_count(Some(ROW_GROUP_ROWS))
        .set_created_by(format!(
            "g2r-dataset {} (schema {SCHEMA_VERSION})",
            env!("CARGO_PKG_VERSION")
        ));
    for column in descriptor.columns() {
        let path = column.path().clone();
        let top = path.parts()[0].as_str();
        if !TENSOR_COLUMNS.contains(&top) {
            continue;
        }
        builder = builder
            .set_column_dictionary_enabled(path.clone(), false)
            .set_column_statistics_enabled(path.clone(), EnabledStatistics::None)
            .set_column_data_page_size_limit(path.clone(), TENSOR_PAGE_BYTES);
        if FLOAT_TENSOR_COLUMNS.contains(&top)
            && matches!(
                column.physical_type(),
                PhysicalType::FLOAT | PhysicalType::DOUBLE
            )
        {
            builder = builder.set_column_encoding(path, Encoding::BYTE_STREAM_SPLIT);
        }
    }
    builder.build()
}

/// Shard file name for index `i` of `n` in a split: `{split}-{i:05}-of-{n:05}.parquet`.
pub fn shard_name(split: &str, index: usize, count: usize) -> String {
    format!("{split}-{index:05}-of-{count:05}.parquet")
}

#[cfg(test)]
mod tests {
    use std::fs::File;

    use super::*;
    use crate::contract::schema::Sample;
    use crate::contract::wire::{ipc_stream_bytes, samples_from_ipc_stream};
    use crate::files::hash_file;
    use crate::testing::synthetic_sample;

    #[test]
    fn shard_roundtrip_with_row_groups_and_checksum() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(shard_name("train", 0, 1));
        let samples: Vec<Sample> = (0..300).map(synthetic_sample).collect();
        let mut w = ShardWriter::create(&path).unwrap();
        w.write(&samples[..100]).unwrap();
        assert!(!path.exists(), "nothing finished-looking before finish()");
        w.write(&samples[100..]).unwrap();
        let entry = w.finish().unwrap();
        assert_eq!((entry.rows, entry.row_groups), (300, 2));
        assert_eq!(row_group_sizes(&path).unwrap(), vec![256, 44]);
        assert_eq!(entry.blake3, hash_file(&path).unwrap());
        assert_eq!(read_shard(&path).unwrap(), samples);
        assert_eq!(read_row_group(&path, 1).unwrap(), samples[256..]);
    }

    #[test]
    fn shard_bytes_do_not_depend_on_how_rows_arrive() {
        // Project writes in rejection-thinned chunks of any size: row groups are cut at 256 rows and their columns
        // encoded in parallel, so every way of chunking must give the bytes of a single write.
        let dir = tempfile::tempdir().unwrap();
        let samples: Vec<Sample> = (0..530).map(synthetic_sample).collect();
        let write = |name: &str, chunks: &[usize]| {
            let path = dir.path().join(name);
            let mut w = ShardWriter::create(&path).unwrap();
            let mut start = 0;
            for &len in chunks {
                w.write(&samples[start..start + len]).unwrap();
                start += len;
            }
            assert_eq!(start, samples.len());
            w.finish().unwrap()
        };
        let whole = write("whole.parquet", &[530]);
        let singles = write("singles.parquet", &[1; 530]);
        let ragged = write("ragged.parquet", &[255, 2, 254, 19]);
        assert_eq!(whole.row_groups, 3);
        assert_eq!(singles.blake3, whole.blake3);
        assert_eq!(ragged.blake3, whole.blake3);
        // Unhashed while written (intermediate files), the checksum of `finish` is still the file's.
        let mut w = ShardWriter::create_unhashed(&dir.path().join("unhashed.parquet")).unwrap();
        w.write(&samples).unwrap();
        assert_eq!(w.finish().unwrap().blake3, whole.blake3);
        assert_eq!(
            read_shard(&dir.path().join("ragged.parquet")).unwrap(),
            samples
        );
    }

    #[test]
    fn copied_row_groups_give_the_bytes_of_encoding_the_same_rows() {
        // Publish cuts a split's file into shards by copying encoded row groups: each shard must be exactly the
        // file a writer encoding those rows would produce, footer and page index included.
        let dir = tempfile::tempdir().unwrap();
        let samples: Vec<Sample> = (0..530).map(synthetic_sample).collect();
        let encode = |name: &str, rows: &[Sample]| {
            let mut w = ShardWriter::create(&dir.path().join(name)).unwrap();
            w.write(rows).unwrap();
            w.finish().unwrap()
        };
        encode("split.parquet", &samples);
        let source = EncodedRowGroups::open(&dir.path().join("split.parquet")).unwrap();
        assert_eq!(source.row_group_sizes(), vec![256, 256, 18]);
        let copy = |name: &str, groups: &[usize]| {
            let mut w = ShardWriter::create(&dir.path().join(name)).unwrap();
            for &g in groups {
                w.append_encoded_row_group(&source, g).unwrap();
            }
            w.finish().unwrap()
        };
        let (first, rest) = (copy("a.parquet", &[0]), copy("b.parquet", &[1, 2]));
        let (first_encoded, rest_encoded) = (
            encode("a-enc.parquet", &samples[..256]),
            encode("b-enc.parquet", &samples[256..]),
        );
        assert_eq!((first.rows, first.row_groups), (256, 1));
        assert_eq!((rest.rows, rest.row_groups), (274, 2));
        assert_eq!(first.blake3, first_encoded.blake3);
        assert_eq!(rest.blake3, rest_encoded.blake3);
        assert_eq!(
            read_shard(&dir.path().join("b.parquet")).unwrap(),
            samples[256..]
        );
        // Rows already buffered would land after the copied group: refused.
        let mut w = ShardWriter::create(&dir.path().join("mixed.parquet")).unwrap();
        w.write(&samples[..3]).unwrap();
        assert!(w.append_encoded_row_group(&source, 0).is_err());
        assert!(matches!(
            ShardWriter::create(&dir.path().join("c.parquet"))
                .unwrap()
                .append_encoded_row_group(&source, 3),
            Err(ShardError::RowGroup { count: 3, .. })
        ));
    }

    #[test]
    fn a_tensor_page_holds_the_rows_of_its_byte_budget_and_no_more() {
        // One row read decompresses the pages it lies on: every raster's pages must hold as many rows as
        // TENSOR_PAGE_BYTES of it (the page is closed at the first row that reaches the budget), not Parquet's
        // default 1 MiB. Counted from the offset index a reader selects pages by.
        use crate::contract::schema::{CONTEXT_PX, CROP_PX, DEM_PX};
        use parquet::file::reader::{FileReader, SerializedFileReader};
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(shard_name("train", 0, 1));
        let mut w = ShardWriter::create(&path).unwrap();
        w.write(&(0..256).map(synthetic_sample).collect::<Vec<_>>())
            .unwrap();
        w.finish().unwrap();
        let options = parquet::file::serialized_reader::ReadOptionsBuilder::new()
            .with_page_index()
            .build();
        let reader =
            SerializedFileReader::new_with_options(File::open(&path).unwrap(), options).unwrap();
        let metadata = reader.metadata();
        let group = metadata.row_group(0);
        let page_index = metadata.page_index_for_row_group(0);
        let row_bytes = [
            ("dem", DEM_PX * DEM_PX * 4),
            ("image", CROP_PX * CROP_PX * 4),
            ("sun_lit", CROP_PX * CROP_PX * 4),
            // Parquet has no 8-bit integer: a UInt8 column is stored as INT32, four bytes a value.
            ("valid", CROP_PX * CROP_PX * 4),
            ("context_dem", CONTEXT_PX * CONTEXT_PX * 4),
        ];
        for (column, bytes) in row_bytes {
            let k = (0..group.num_columns())
                .find(|&k| group.column(k).column_path().parts()[0] == column)
                .unwrap();
            let starts: Vec<i64> = page_index
                .page_locations(k)
                .expect("an offset index is written")
                .iter()
                .map(|p| p.first_row_index)
                .chain([256])
                .collect();
            let rows: Vec<i64> = starts.windows(2).map(|w| w[1] - w[0]).collect();
            let budget_rows = TENSOR_PAGE_BYTES.div_ceil(bytes) as i64;
            assert!(
                rows.iter().all(|&r| r <= budget_rows),
                "{column}: pages of {rows:?} rows, budget {budget_rows}"
            );
            // Full pages (all but the last) reach the budget: pages are not cut smaller than it asks.
            assert!(
                rows[..rows.len() - 1].iter().all(|&r| r == budget_rows),
                "{column}: pages of {rows:?} rows, budget {budget_rows}"
            );
        }
    }

    #[test]
    fn row_selection_metadata_projection_and_ipc_agree_with_full_reads() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(shard_name("train", 0, 1));
        let samples: Vec<Sample> = (0..300).map(synthetic_sample).collect();
        let mut w = ShardWriter::create(&path).unwrap();
        w.write(&samples).unwrap();
        w.finish().unwrap();
        let shard = ShardFile::open(&path).unwrap();
        // Rows straddling page boundaries inside the second group, and the group's last row.
        assert_eq!(shard.read_rows(1, 3..17).unwrap(), samples[259..273]);
        assert_eq!(shard.read_rows(1, 43..44).unwrap(), samples[299..300]);
        assert_eq!(shard.read_rows(0, 0..0).unwrap(), Vec::<Sample>::new());
        let metadata = shard.read_metadata().unwrap();
        assert_eq!(metadata.len(), 300);
        for (m, s) in metadata.iter().zip(&samples) {
            assert!(m.dem_m.is_empty() && m.image.is_empty() && m.valid.is_empty());
            let stripped = Sample {
                dem_m: vec![],
                image: vec![],
                valid: vec![],
                sun_lit: vec![],
                context: None,
                ..s.clone()
            };
            assert_eq!(m, &stripped);
        }
        let ipc = ipc_stream_bytes(&shard.read_batches(1, None, true).unwrap()).unwrap();
        assert_eq!(samples_from_ipc_stream(&ipc).unwrap(), samples[256..]);
        let missing = shard.read_row_group(2).unwrap_err().to_string();
        assert!(
            missing.contains("no row group 2 (the shard has 2)"),
            "{missing}"
        );
        // Metadata plus the tensor columns of scattered rows (page edges, the first and last rows, neighbours)
        // give the whole samples, as a full read does.
        for (group, rows) in [
            (0, vec![0, 14, 15, 16, 100, 255]),
            (1, vec![3, 43]),
            (1, vec![]),
        ] {
            let first = group * ROW_GROUP_ROWS;
            let mut filled: Vec<Sample> =
                rows.iter().map(|&r| metadata[first + r].clone()).collect();
            shard.fill_tensors(group, &rows, &mut filled).unwrap();
            let expected: Vec<Sample> = rows.iter().map(|&r| samples[first + r].clone()).collect();
            assert_eq!(filled, expected, "row group {group}, rows {rows:?}");
        }
        let missing = shard
            .fill_tensors(2, &[0], &mut metadata[..1].to_vec())
            .unwrap_err();
        assert!(missing.to_string().contains("no row group 2"), "{missing}");
    }

    #[test]
    fn wrong_tensor_length_is_rejected() {
        let dir = tempfile::tempdir().unwrap();
        let mut s = synthetic_sample(0);
        s.image.pop();
        let mut w = ShardWriter::create(&dir.path().join("x.parquet")).unwrap();
        assert!(w.write(&[s]).unwrap_err().to_string().contains("image"));
    }

    #[test]
    fn float_tensors_use_byte_stream_split() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.parquet");
        let mut w = ShardWriter::create(&path).unwrap();
        w.write(&[synthetic_sample(1)]).unwrap();
        w.finish().unwrap();
        let reader =
            parquet::file::reader::SerializedFileReader::new(File::open(&path).unwrap()).unwrap();
        use parquet::file::reader::FileReader;
        let rg = reader.metadata().row_group(0);
        for col in rg.columns() {
            let name = col.column_path().parts()[0].clone();
            let encodings: Vec<Encoding> = col.encodings().collect();
            if FLOAT_TENSOR_COLUMNS.contains(&name.as_str()) {
                assert!(
                    encodings.contains(&Encoding::BYTE_STREAM_SPLIT),
                    "{name}: {encodings:?}"
                );
            }
            assert!(
                matches!(col.compression(), Compression::ZSTD(_)),
                "{name}: {:?}",
                col.compression()
            );
        }
    }
}

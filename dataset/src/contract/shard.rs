//! Parquet shard IO: float tensors with BYTE_STREAM_SPLIT + zstd, ~256-row row groups (one range read per random
//! access), written under a temporary name and renamed when complete.

use std::fs::File;
use std::path::{Path, PathBuf};

use arrow::record_batch::RecordBatch;
use parquet::arrow::arrow_reader::{
    ArrowReaderMetadata, ArrowReaderOptions, ParquetRecordBatchReaderBuilder, RowSelection,
    RowSelector,
};
use parquet::arrow::arrow_writer::{compute_leaves, ArrowRowGroupWriterFactory};
use parquet::arrow::{ArrowSchemaConverter, ArrowWriter, ProjectionMask};
use parquet::basic::{Compression, Encoding, Type as PhysicalType, ZstdLevel};
use parquet::file::metadata::ParquetMetaData;
use parquet::file::properties::{EnabledStatistics, WriterProperties};
use parquet::file::writer::SerializedFileWriter;
use rayon::prelude::*;

use crate::contract::manifest::{hash_file, ShardEntry};
use crate::contract::schema::{
    batch_to_sample_metadata, batch_to_samples, sample_schema, samples_to_batch, Sample,
    SchemaError, FLOAT_TENSOR_COLUMNS, SCHEMA_VERSION, TENSOR_COLUMNS,
};
use crate::science::raster::tmp_path;
use crate::storage::ShardBytes;

/// Rows per row group: ~256 samples ≈ 40 MB uncompressed, one HTTP range read for random access.
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

/// Writer properties: zstd everywhere; on the tensor leaves no dictionary (interning the 16k values per row of the
/// `valid` mask was ~9 % of the writer thread's time in the tycho-full project stage) and no page statistics
/// (min/max of a tensor column helps no query), and BYTE_STREAM_SPLIT on the float ones.
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
            .set_column_statistics_enabled(path.clone(), EnabledStatistics::None);
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

/// The shard file, hashed as it is written (when asked): a finished shard's checksum costs no second read.
struct HashingFile {
    file: File,
    hasher: Option<blake3::Hasher>,
}

impl std::io::Write for HashingFile {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let written = self.file.write(buf)?;
        if let Some(hasher) = self.hasher.as_mut() {
            hasher.update(&buf[..written]);
        }
        Ok(written)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.file.flush()
    }
}

/// Streams samples into one shard file; nothing at `path` until [`ShardWriter::finish`] succeeds.
///
/// Rows are buffered as Arrow batches until a row group is full; its column chunks are then encoded in parallel
/// (rayon) and appended in schema order, so the bytes do not depend on thread timing. One `ArrowWriter` encodes
/// column after column on the calling thread, which made the writer the serial bottleneck of the project stage.
pub struct ShardWriter {
    path: PathBuf,
    tmp: PathBuf,
    schema: arrow::datatypes::SchemaRef,
    file_writer: SerializedFileWriter<HashingFile>,
    columns: ArrowRowGroupWriterFactory,
    pending: Vec<RecordBatch>,
    pending_rows: usize,
    /// Rows per row group ([`ROW_GROUP_ROWS`] unless a small shard size asks for fewer).
    group_rows: usize,
    row_groups: usize,
    rows: usize,
}

impl ShardWriter {
    /// A shard hashed while it is written; [`ShardWriter::finish`] reports its blake3.
    pub fn create(path: &Path) -> Result<Self, ShardError> {
        Self::open(path, true)
    }

    /// An intermediate file closed with [`ShardWriter::close`]: no blake3 while writing, because its reader hashes
    /// it anyway (the pipeline runner hashes every stage output; doing it here too cost a pass over gigabytes).
    pub fn create_unhashed(path: &Path) -> Result<Self, ShardError> {
        Self::open(path, false)
    }

    fn open(path: &Path, hashed: bool) -> Result<Self, ShardError> {
        let tmp = tmp_path(path);
        let file = File::create(&tmp).map_err(|source| ShardError::Io {
            path: tmp.clone(),
            source,
        })?;
        let file = HashingFile {
            file,
            hasher: hashed.then(blake3::Hasher::new),
        };
        let schema = sample_schema();
        // ArrowWriter embeds the Arrow schema in the footer metadata; its low-level halves do the writing.
        let (file_writer, columns) =
            ArrowWriter::try_new(file, schema.clone(), Some(writer_properties()))
                .and_then(ArrowWriter::into_serialized_writer)
                .map_err(|source| ShardError::Parquet {
                    path: path.to_path_buf(),
                    source,
                })?;
        Ok(Self {
            path: path.to_path_buf(),
            tmp,
            schema,
            file_writer,
            columns,
            pending: Vec::new(),
            pending_rows: 0,
            group_rows: ROW_GROUP_ROWS,
            row_groups: 0,
            rows: 0,
        })
    }

    /// Cut row groups of `rows` rows instead of [`ROW_GROUP_ROWS`] (shards smaller than one default row group are
    /// cut from files written this way).
    pub fn with_row_group_rows(mut self, rows: usize) -> Self {
        self.group_rows = rows.max(1);
        self
    }

    /// Rows written but not yet encoded into a row group: [`Self::append_encoded_row_group`] needs none.
    pub fn buffered_rows(&self) -> usize {
        self.pending_rows
    }

    fn parquet_err(&self, source: parquet::errors::ParquetError) -> ShardError {
        ShardError::Parquet {
            path: self.path.clone(),
            source,
        }
    }

    pub fn write(&mut self, samples: &[Sample]) -> Result<(), ShardError> {
        let batch = samples_to_batch(samples).map_err(|source| ShardError::Schema {
            path: self.path.clone(),
            source,
        })?;
        self.write_batch(&batch)
    }

    /// Append rows already in Arrow form (e.g. read from another shard): no per-sample conversion. The batch
    /// must have the sample schema's columns and types; its schema-level metadata is replaced by this build's.
    pub fn write_batch(&mut self, batch: &RecordBatch) -> Result<(), ShardError> {
        let batch = RecordBatch::try_new(self.schema.clone(), batch.columns().to_vec())
            .map_err(|e| self.parquet_err(e.into()))?;
        self.pending_rows += batch.num_rows();
        self.rows += batch.num_rows();
        self.pending.push(batch);
        while self.pending_rows >= self.group_rows {
            self.flush_row_group(self.group_rows)?;
        }
        Ok(())
    }

    /// Encode the first `rows` pending rows as one row group.
    fn flush_row_group(&mut self, rows: usize) -> Result<(), ShardError> {
        let schema = self.schema.clone();
        // Take the first `rows` rows off the pending batches; only a group spanning batches is copied.
        let (mut parts, mut taken) = (Vec::new(), 0);
        let mut pending = std::mem::take(&mut self.pending).into_iter();
        for batch in pending.by_ref() {
            let take = (rows - taken).min(batch.num_rows());
            parts.push(batch.slice(0, take));
            taken += take;
            if take < batch.num_rows() {
                self.pending
                    .push(batch.slice(take, batch.num_rows() - take));
            }
            if taken == rows {
                break;
            }
        }
        self.pending.extend(pending);
        self.pending_rows -= rows;
        let group = match parts.len() {
            1 => parts.pop().expect("one part"),
            _ => arrow::compute::concat_batches(&schema, &parts)
                .map_err(|e| self.parquet_err(e.into()))?,
        };
        drop(parts);
        let writers = self
            .columns
            .create_column_writers(self.row_groups)
            .map_err(|e| self.parquet_err(e))?;
        // Every field of the sample schema is one Parquet leaf (no structs), so writer k encodes column k;
        // computing its levels inside the parallel closure keeps that off the calling thread too.
        assert_eq!(writers.len(), group.num_columns(), "one leaf per field");
        let fields = schema.fields().clone();
        let chunks = writers
            .into_par_iter()
            .zip(fields.par_iter())
            .zip(group.columns().par_iter())
            .map(|((mut writer, field), column)| {
                for leaf in compute_leaves(field, column)? {
                    writer.write(&leaf)?;
                }
                writer.close()
            })
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| self.parquet_err(e))?;
        let path = &self.path;
        let err = |source| ShardError::Parquet {
            path: path.clone(),
            source,
        };
        let mut row_group = self.file_writer.next_row_group().map_err(err)?;
        for chunk in chunks {
            chunk.append_to_row_group(&mut row_group).map_err(err)?;
        }
        row_group.close().map_err(err)?;
        self.row_groups += 1;
        Ok(())
    }

    /// Append row group `group` of `source` as it is encoded: its column chunks' bytes are copied, not decoded
    /// and re-encoded (publishing a split file as shards costs a file copy). Rows written with [`Self::write`] and
    /// not yet flushed would land after it, so they must not exist: call this only on a writer fed by row groups.
    pub fn append_encoded_row_group(
        &mut self,
        source: &EncodedRowGroups,
        group: usize,
    ) -> Result<(), ShardError> {
        if self.pending_rows > 0 {
            return Err(self.parquet_err(parquet::errors::ParquetError::General(
                "encoded row groups cannot follow partly buffered rows".into(),
            )));
        }
        let metadata = &source.metadata;
        let Some(row_group) = metadata.row_groups().get(group) else {
            return Err(ShardError::RowGroup {
                path: source.path.clone(),
                row_group: group,
                count: metadata.num_row_groups(),
            });
        };
        let page_index = metadata.page_index_for_row_group(group);
        let path = &self.path;
        let err = |source| ShardError::Parquet {
            path: path.clone(),
            source,
        };
        let mut writer = self.file_writer.next_row_group().map_err(err)?;
        for (k, column) in row_group.columns().iter().enumerate() {
            let close = parquet::column::writer::ColumnCloseResult {
                bytes_written: column.compressed_size() as u64,
                rows_written: row_group.num_rows() as u64,
                metadata: column.clone(),
                bloom_filter: None,
                column_index: page_index.column_index(k).cloned(),
                offset_index: page_index.offset_index(k).cloned(),
            };
            writer.append_column(&source.file, close).map_err(err)?;
        }
        writer.close().map_err(err)?;
        self.row_groups += 1;
        self.rows += row_group.num_rows() as usize;
        Ok(())
    }

    /// Write the last, partial row group and the footer; returns the footer's metadata and the file's blake3.
    fn close_file(
        mut self,
    ) -> Result<(ParquetMetaData, Option<String>, PathBuf, usize), ShardError> {
        if self.pending_rows > 0 {
            self.flush_row_group(self.pending_rows)?;
        }
        let metadata = self
            .file_writer
            .finish()
            .map_err(|source| ShardError::Parquet {
                path: self.path.clone(),
                source,
            })?;
        let blake3 = self
            .file_writer
            .inner()
            .hasher
            .as_ref()
            .map(|hasher| hasher.finalize().to_hex().to_string());
        drop(self.file_writer);
        std::fs::rename(&self.tmp, &self.path).map_err(|source| ShardError::Io {
            path: self.path.clone(),
            source,
        })?;
        Ok((metadata, blake3, self.path, self.rows))
    }

    /// Close and rename into place; returns the row count (for [`ShardWriter::create_unhashed`] files).
    pub fn close(self) -> Result<usize, ShardError> {
        Ok(self.close_file()?.3)
    }

    /// Close, rename into place, and describe the finished shard (size, rows, row groups, blake3).
    pub fn finish(self) -> Result<ShardEntry, ShardError> {
        let (metadata, blake3, path, rows) = self.close_file()?;
        let blake3 = match blake3 {
            Some(hash) => hash,
            None => hash_file(&path).map_err(|source| ShardError::Io {
                path: path.clone(),
                source,
            })?,
        };
        let bytes = std::fs::metadata(&path)
            .map_err(|source| ShardError::Io {
                path: path.clone(),
                source,
            })?
            .len();
        Ok(ShardEntry {
            path: path
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
            bytes,
            rows: rows as u64,
            row_groups: metadata.num_row_groups() as u64,
            blake3,
        })
    }
}

/// A sample file opened for copying its row groups verbatim ([`ShardWriter::append_encoded_row_group`]): footer
/// and page index parsed, schema checked to be this build's sample schema leaf for leaf.
pub struct EncodedRowGroups {
    path: PathBuf,
    file: File,
    metadata: ParquetMetaData,
}

impl EncodedRowGroups {
    pub fn open(path: &Path) -> Result<Self, ShardError> {
        let parquet_err = |source| ShardError::Parquet {
            path: path.to_path_buf(),
            source,
        };
        let file = File::open(path).map_err(|source| ShardError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let metadata = parquet::file::metadata::ParquetMetaDataReader::new()
            .with_page_index_policy(parquet::file::metadata::PageIndexPolicy::Optional)
            // Full page encoding stats (not the default summary mask), so the copied footer matches the source's.
            .with_metadata_options(Some(
                parquet::file::metadata::ParquetMetaDataOptions::new()
                    .with_encoding_stats_as_mask(false),
            ))
            .parse_and_finish(&file)
            .map_err(parquet_err)?;
        let expected = ArrowSchemaConverter::new()
            .convert(&sample_schema())
            .map_err(parquet_err)?;
        if metadata.file_metadata().schema() != expected.root_schema() {
            return Err(parquet_err(parquet::errors::ParquetError::General(
                "its Parquet schema is not this build's sample schema; re-run the stage that wrote it"
                    .into(),
            )));
        }
        Ok(Self {
            path: path.to_path_buf(),
            file,
            metadata,
        })
    }

    /// Row count per row group, from the footer.
    pub fn row_group_sizes(&self) -> Vec<usize> {
        self.metadata
            .row_groups()
            .iter()
            .map(|rg| rg.num_rows() as usize)
            .collect()
    }
}

/// An open shard with its footer parsed once: random reads of row groups or single rows touch only the needed
/// column chunks, and a server can hold one per shard instead of re-reading footers per request. A local file, or
/// an object in object storage ([`crate::storage`]) read with one ranged GET per row group.
#[derive(Clone)]
pub struct ShardFile {
    /// The file's path, or the object's URL (for messages).
    path: PathBuf,
    metadata: ArrowReaderMetadata,
    remote: Option<crate::storage::RemoteObject>,
}

impl ShardFile {
    /// The file's own Arrow schema: a schema 1.1 shard has no context columns, unlike this build's
    /// [`crate::contract::schema::sample_schema`].
    pub fn schema(&self) -> arrow::datatypes::SchemaRef {
        self.metadata.schema().clone()
    }

    /// Open and parse the footer; refuses a shard written with another major schema version.
    pub fn open(path: &Path) -> Result<Self, ShardError> {
        let file = File::open(path).map_err(|source| ShardError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let metadata =
            ArrowReaderMetadata::load(&file, ArrowReaderOptions::default()).map_err(|source| {
                ShardError::Parquet {
                    path: path.to_path_buf(),
                    source,
                }
            })?;
        Self::checked(path.to_path_buf(), metadata, None)
    }

    /// Open a shard in object storage: its footer is read with two ranged GETs (the length, then the metadata).
    pub fn open_remote(object: crate::storage::RemoteObject) -> Result<Self, ShardError> {
        let path = PathBuf::from(object.url());
        let metadata = ArrowReaderMetadata::load(&object, ArrowReaderOptions::default()).map_err(
            |source| ShardError::Parquet {
                path: path.clone(),
                source,
            },
        )?;
        Self::checked(path, metadata, Some(object))
    }

    fn checked(
        path: PathBuf,
        metadata: ArrowReaderMetadata,
        remote: Option<crate::storage::RemoteObject>,
    ) -> Result<Self, ShardError> {
        let found = metadata
            .schema()
            .metadata()
            .get("g2r.schema_version")
            .cloned()
            .unwrap_or_else(|| "none".into());
        if found.split('.').next() != SCHEMA_VERSION.split('.').next() {
            return Err(ShardError::SchemaVersion { path, found });
        }
        Ok(Self {
            path,
            metadata,
            remote,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Row count per row group, from the footer.
    pub fn row_group_sizes(&self) -> Vec<usize> {
        self.metadata
            .metadata()
            .row_groups()
            .iter()
            .map(|rg| rg.num_rows() as usize)
            .collect()
    }

    fn parquet_err(&self, source: parquet::errors::ParquetError) -> ShardError {
        ShardError::Parquet {
            path: self.path.clone(),
            source,
        }
    }

    /// A reader of the whole file (local) or of `row_group` (remote: its column chunks fetched in one GET).
    fn builder(
        &self,
        row_group: Option<usize>,
    ) -> Result<ParquetRecordBatchReaderBuilder<ShardBytes>, ShardError> {
        let bytes = match (&self.remote, row_group) {
            (None, _) => {
                ShardBytes::File(File::open(&self.path).map_err(|source| ShardError::Io {
                    path: self.path.clone(),
                    source,
                })?)
            }
            (Some(object), Some(group)) => {
                let columns = self.metadata.metadata().row_group(group).columns();
                let start = columns.iter().map(|c| c.byte_range().0).min().unwrap_or(0);
                let end = columns
                    .iter()
                    .map(|c| c.byte_range().0 + c.byte_range().1)
                    .max()
                    .unwrap_or(0);
                ShardBytes::Fetched {
                    offset: start,
                    bytes: object.fetch(start..end).map_err(|e| self.parquet_err(e))?,
                    len: parquet::file::reader::Length::len(object),
                }
            }
            (Some(_), None) => {
                return Err(self.parquet_err(parquet::errors::ParquetError::General(
                    "a remote shard is read one row group at a time".into(),
                )))
            }
        };
        Ok(ParquetRecordBatchReaderBuilder::new_with_metadata(
            bytes,
            self.metadata.clone(),
        ))
    }

    /// Raw Arrow batches of `rows` (within `row_group`), all columns or the metadata columns only.
    pub fn read_batches(
        &self,
        row_group: usize,
        rows: Option<std::ops::Range<usize>>,
        tensors: bool,
    ) -> Result<Vec<RecordBatch>, ShardError> {
        let sizes = self.row_group_sizes();
        let Some(&group_rows) = sizes.get(row_group) else {
            return Err(ShardError::RowGroup {
                path: self.path.clone(),
                row_group,
                count: sizes.len(),
            });
        };
        let mut builder = self
            .builder(Some(row_group))?
            .with_row_groups(vec![row_group])
            .with_batch_size(ROW_GROUP_ROWS);
        if let Some(rows) = rows {
            let rows = rows.start.min(group_rows)..rows.end.min(group_rows);
            builder = builder.with_row_selection(RowSelection::from(vec![
                RowSelector::skip(rows.start),
                RowSelector::select(rows.len()),
                RowSelector::skip(group_rows - rows.end),
            ]));
        }
        if !tensors {
            let schema = sample_schema();
            let keep: Vec<&str> = schema
                .fields()
                .iter()
                .map(|f| f.name().as_str())
                .filter(|n| !TENSOR_COLUMNS.contains(n))
                .collect();
            let mask = ProjectionMask::columns(builder.parquet_schema(), keep);
            builder = builder.with_projection(mask);
        }
        let reader = builder.build().map_err(|e| self.parquet_err(e))?;
        reader
            .map(|b| b.map_err(|e| self.parquet_err(e.into())))
            .collect()
    }

    fn decode(&self, batches: &[RecordBatch], tensors: bool) -> Result<Vec<Sample>, ShardError> {
        let mut out = Vec::new();
        for batch in batches {
            let decoded = if tensors {
                batch_to_samples(batch)
            } else {
                batch_to_sample_metadata(batch)
            };
            out.extend(decoded.map_err(|source| ShardError::Schema {
                path: self.path.clone(),
                source,
            })?);
        }
        Ok(out)
    }

    /// Every sample of one row group.
    pub fn read_row_group(&self, row_group: usize) -> Result<Vec<Sample>, ShardError> {
        self.decode(&self.read_batches(row_group, None, true)?, true)
    }

    /// Rows `rows` of one row group, decoding only the pages those rows need.
    pub fn read_rows(
        &self,
        row_group: usize,
        rows: std::ops::Range<usize>,
    ) -> Result<Vec<Sample>, ShardError> {
        self.decode(&self.read_batches(row_group, Some(rows), true)?, true)
    }

    /// Metadata of every row (raster fields empty), reading only the small columns.
    pub fn read_metadata(&self) -> Result<Vec<Sample>, ShardError> {
        let mut out = Vec::new();
        for group in 0..self.row_group_sizes().len() {
            out.extend(self.decode(&self.read_batches(group, None, false)?, false)?);
        }
        Ok(out)
    }

    /// Every sample of the shard.
    pub fn read_all(&self) -> Result<Vec<Sample>, ShardError> {
        let mut out = Vec::new();
        for group in 0..self.row_group_sizes().len() {
            out.extend(self.read_row_group(group)?);
        }
        Ok(out)
    }
}

/// Read every sample of a shard.
pub fn read_shard(path: &Path) -> Result<Vec<Sample>, ShardError> {
    ShardFile::open(path)?.read_all()
}

/// Read one row group (random access reads only that group's column chunks).
pub fn read_row_group(path: &Path, row_group: usize) -> Result<Vec<Sample>, ShardError> {
    ShardFile::open(path)?.read_row_group(row_group)
}

/// Ids and crop centres (map metres) of every row of a shard.
#[derive(Debug, Default)]
pub struct SamplePositions {
    pub sample_ids: Vec<String>,
    pub center_x_m: Vec<f64>,
    pub center_y_m: Vec<f64>,
}

/// (sample_id, center_x, center_y) of every row, reading only those three columns.
pub fn read_sample_positions(path: &Path) -> Result<SamplePositions, ShardError> {
    use arrow::array::{Array, Float64Array, StringArray};
    let builder = ShardFile::open(path)?.builder(None)?;
    let mask = parquet::arrow::ProjectionMask::columns(
        builder.parquet_schema(),
        ["sample_id", "center_x", "center_y"],
    );
    let reader = builder
        .with_projection(mask)
        .build()
        .map_err(|source| ShardError::Parquet {
            path: path.to_path_buf(),
            source,
        })?;
    let (mut ids, mut xs, mut ys) = (Vec::new(), Vec::new(), Vec::new());
    for batch in reader {
        let batch = batch.map_err(|e| ShardError::Parquet {
            path: path.to_path_buf(),
            source: e.into(),
        })?;
        let bad = || ShardError::Schema {
            path: path.to_path_buf(),
            source: crate::contract::schema::SchemaError::Column("sample_id/center_x/center_y"),
        };
        let id = batch
            .column_by_name("sample_id")
            .and_then(|c| c.as_any().downcast_ref::<StringArray>())
            .ok_or_else(bad)?;
        let x = batch
            .column_by_name("center_x")
            .and_then(|c| c.as_any().downcast_ref::<Float64Array>())
            .ok_or_else(bad)?;
        let y = batch
            .column_by_name("center_y")
            .and_then(|c| c.as_any().downcast_ref::<Float64Array>())
            .ok_or_else(bad)?;
        ids.extend((0..id.len()).map(|i| id.value(i).to_string()));
        xs.extend_from_slice(x.values());
        ys.extend_from_slice(y.values());
    }
    Ok(SamplePositions {
        sample_ids: ids,
        center_x_m: xs,
        center_y_m: ys,
    })
}

/// Row count per row group, from the footer only.
pub fn row_group_sizes(path: &Path) -> Result<Vec<usize>, ShardError> {
    Ok(ShardFile::open(path)?.row_group_sizes())
}

/// Shard file name for index `i` of `n` in a split: `{split}-{i:05}-of-{n:05}.parquet`.
pub fn shard_name(split: &str, index: usize, count: usize) -> String {
    format!("{split}-{index:05}-of-{count:05}.parquet")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::contract::wire::{ipc_stream_bytes, samples_from_ipc_stream};
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
        // Publish writes one row at a time, project in rejection-thinned chunks: row groups are cut at 256 rows
        // and their columns encoded in parallel, so both must give the bytes of a single write.
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

//! Writing shards: row groups encoded in parallel into a file hashed as it is written, or copied verbatim.

use std::fs::File;
use std::path::{Path, PathBuf};

use arrow::record_batch::RecordBatch;
use parquet::arrow::arrow_writer::{compute_leaves, ArrowRowGroupWriterFactory};
use parquet::arrow::{ArrowSchemaConverter, ArrowWriter};
use parquet::file::metadata::ParquetMetaData;
use parquet::file::writer::SerializedFileWriter;
use rayon::prelude::*;

use crate::contract::manifest::ShardEntry;
use crate::contract::schema::{sample_schema, samples_to_batch, Sample};
use crate::files::hash_file;
use crate::files::tmp_path;

use super::{writer_properties, ShardError, ROW_GROUP_ROWS};

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

//! Reading shards: a footer parsed once, then row groups, rows or a few columns read on demand.

use std::fs::File;
use std::path::{Path, PathBuf};

use arrow::record_batch::RecordBatch;
use parquet::arrow::arrow_reader::{
    ArrowReaderMetadata, ArrowReaderOptions, ParquetRecordBatchReaderBuilder, RowSelection,
    RowSelector,
};
use parquet::arrow::ProjectionMask;
use parquet::file::metadata::PageIndexPolicy;

use crate::contract::schema::{
    batch_to_sample_metadata, batch_to_samples, fill_tensors, sample_schema, Sample,
    SCHEMA_VERSION, TENSOR_COLUMNS, TENSOR_FILL_COLUMNS,
};
use crate::storage::{DatasetLocation, RemoteObject, ShardBytes};

use super::{ShardError, ROW_GROUP_ROWS};

/// An open shard with its footer parsed once: random reads of row groups or single rows touch only the needed
/// column chunks, and a server can hold one per shard instead of re-reading footers per request. A local file, or
/// an object in object storage ([`crate::storage`]) whose row groups are read by ranged GETs of the column chunks
/// a read needs (adjacent chunks merged into one GET).
#[derive(Clone)]
pub struct ShardFile {
    /// The file's path, or the object's URL (for messages).
    path: PathBuf,
    metadata: ArrowReaderMetadata,
    remote: Option<RemoteObject>,
}

impl ShardFile {
    /// The file's own Arrow schema: a schema 1.1 shard has no context columns, unlike this build's
    /// [`crate::contract::schema::sample_schema`].
    pub fn schema(&self) -> arrow::datatypes::SchemaRef {
        self.metadata.schema().clone()
    }

    /// Open and parse the footer with its offset index; refuses a shard written with another major schema version.
    /// The offset index (where each page starts, and its first row) lets a read of a few rows skip the pages before
    /// them unread: without it every page before a selected row is decompressed to count its rows, and that was
    /// most of a dataset server's tensor and preview requests (profiled, docs/usage.md).
    pub fn open(path: &Path) -> Result<Self, ShardError> {
        let file = File::open(path).map_err(|source| ShardError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let options = ArrowReaderOptions::new().with_offset_index_policy(PageIndexPolicy::Optional);
        let metadata = ArrowReaderMetadata::load(&file, options)
            .map_err(|source| ShardError::reading(path, source, false))?;
        Self::checked(path.to_path_buf(), metadata, None)
    }

    /// Shard `name` of a published dataset, in a directory or under a bucket prefix, its footer parsed.
    pub fn open_in(location: &DatasetLocation, name: &str) -> anyhow::Result<Self> {
        Ok(match location {
            DatasetLocation::Local(dir) => Self::open(&dir.join(name))?,
            DatasetLocation::Remote(remote) => {
                Self::open_remote(RemoteObject::open(remote.clone(), name)?)?
            }
        })
    }

    /// Open a shard in object storage: its footer is read with two ranged GETs (the length, then the metadata).
    pub fn open_remote(object: RemoteObject) -> Result<Self, ShardError> {
        let path = PathBuf::from(object.url());
        let metadata = ArrowReaderMetadata::load(&object, ArrowReaderOptions::default())
            .map_err(|source| ShardError::reading(&path, source, true))?;
        Self::checked(path, metadata, Some(object))
    }

    fn checked(
        path: PathBuf,
        metadata: ArrowReaderMetadata,
        remote: Option<RemoteObject>,
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
        ShardError::reading(&self.path, source, self.remote.is_some())
    }

    /// A reader of the whole file (local), or of `row_group` (remote: the column chunks of `columns`, or of every
    /// column, fetched ahead; chunks that lie together come in one GET).
    fn builder(
        &self,
        row_group: Option<usize>,
        columns: Option<&[&str]>,
    ) -> Result<ParquetRecordBatchReaderBuilder<ShardBytes>, ShardError> {
        let bytes = match (&self.remote, row_group) {
            (None, _) => {
                ShardBytes::File(File::open(&self.path).map_err(|source| ShardError::Io {
                    path: self.path.clone(),
                    source,
                })?)
            }
            (Some(object), Some(group)) => {
                let ranges: Vec<std::ops::Range<u64>> = self
                    .metadata
                    .metadata()
                    .row_group(group)
                    .columns()
                    .iter()
                    .filter(|chunk| {
                        columns.is_none_or(|wanted| {
                            chunk
                                .column_path()
                                .parts()
                                .first()
                                .is_some_and(|name| wanted.contains(&name.as_str()))
                        })
                    })
                    .map(|chunk| {
                        let (start, length) = chunk.byte_range();
                        start..start + length
                    })
                    .collect();
                object
                    .fetch_ranges(&ranges)
                    .map_err(|e| self.parquet_err(e))?
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

    /// Raw Arrow batches of `rows` (within `row_group`), all columns or the metadata columns only (a remote shard
    /// then fetches only those columns' bytes).
    pub fn read_batches(
        &self,
        row_group: usize,
        rows: Option<std::ops::Range<usize>>,
        tensors: bool,
    ) -> Result<Vec<RecordBatch>, ShardError> {
        let group_rows = self.group_rows(row_group)?;
        // The metadata columns' names only when they are asked for: a tensor read (the trainer's per-row-group
        // path) builds no schema.
        let schema = (!tensors).then(sample_schema);
        let metadata_columns: Option<Vec<&str>> = schema.as_ref().map(|schema| {
            schema
                .fields()
                .iter()
                .map(|f| f.name().as_str())
                .filter(|n| !TENSOR_COLUMNS.contains(n))
                .collect()
        });
        let selection = rows.map(|rows| {
            let rows = rows.start.min(group_rows)..rows.end.min(group_rows);
            RowSelection::from(vec![
                RowSelector::skip(rows.start),
                RowSelector::select(rows.len()),
                RowSelector::skip(group_rows - rows.end),
            ])
        });
        self.read_selected(row_group, selection, metadata_columns.as_deref())?
            .collect()
    }

    /// The row count of `row_group`, or an error naming the shard's count.
    fn group_rows(&self, row_group: usize) -> Result<usize, ShardError> {
        let sizes = self.row_group_sizes();
        sizes
            .get(row_group)
            .copied()
            .ok_or_else(|| ShardError::RowGroup {
                path: self.path.clone(),
                row_group,
                count: sizes.len(),
            })
    }

    /// The batches of `row_group`'s rows in `selection` (all when `None`), of `columns` (all when `None`; a remote
    /// shard fetches only those columns' chunks).
    fn read_selected(
        &self,
        row_group: usize,
        selection: Option<RowSelection>,
        columns: Option<&[&str]>,
    ) -> Result<impl Iterator<Item = Result<RecordBatch, ShardError>> + '_, ShardError> {
        let mut builder = self
            .builder(Some(row_group), columns)?
            .with_row_groups(vec![row_group])
            .with_batch_size(ROW_GROUP_ROWS);
        if let Some(selection) = selection {
            builder = builder.with_row_selection(selection);
        }
        if let Some(columns) = columns {
            let mask = ProjectionMask::columns(builder.parquet_schema(), columns.iter().copied());
            builder = builder.with_projection(mask);
        }
        let reader = builder.build().map_err(|e| self.parquet_err(e))?;
        Ok(reader.map(|b| b.map_err(|e| self.parquet_err(e.into()))))
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

    /// Fill the rasters of `samples` (metadata from elsewhere: a server's index) with rows `rows` of `row_group`
    /// (ascending, distinct; `samples[k]` is row `rows[k]`), reading only [`TENSOR_FILL_COLUMNS`] and only the pages
    /// those rows lie on: a few column chunks instead of every column's (each chunk read sets up a codec, and the
    /// metadata columns' dozens of chunks cost more than the rasters' pages of one row).
    pub fn fill_tensors(
        &self,
        row_group: usize,
        rows: &[usize],
        samples: &mut [Sample],
    ) -> Result<(), ShardError> {
        assert_eq!(rows.len(), samples.len(), "one sample per row");
        assert!(
            rows.windows(2).all(|w| w[0] < w[1]),
            "rows ascending and distinct"
        );
        let group_rows = self.group_rows(row_group)?;
        assert!(
            rows.last().is_none_or(|&last| last < group_rows),
            "rows within the row group's {group_rows}"
        );
        let mut selectors = Vec::new();
        let mut next = 0;
        for &row in rows {
            selectors.push(RowSelector::skip(row - next));
            selectors.push(RowSelector::select(1));
            next = row + 1;
        }
        selectors.push(RowSelector::skip(group_rows - next));
        let batches = self.read_selected(
            row_group,
            Some(RowSelection::from(selectors)),
            Some(&TENSOR_FILL_COLUMNS),
        )?;
        let mut filled = 0;
        for batch in batches {
            let batch = batch?;
            let end = filled + batch.num_rows();
            let into = samples
                .get_mut(filled..end)
                .expect("a row selection yields the rows it selects");
            fill_tensors(&batch, into).map_err(|source| ShardError::Schema {
                path: self.path.clone(),
                source,
            })?;
            filled = end;
        }
        assert_eq!(
            filled,
            rows.len(),
            "a row selection yields the rows it selects"
        );
        Ok(())
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

/// Row count per row group, from the footer only.
pub fn row_group_sizes(path: &Path) -> Result<Vec<usize>, ShardError> {
    Ok(ShardFile::open(path)?.row_group_sizes())
}

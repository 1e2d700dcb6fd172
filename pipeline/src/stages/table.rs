//! Small Parquet tables for stage outputs (zstd, one file each), readable by pyarrow/polars unaided.

use std::fs::File;
use std::path::{Path, PathBuf};

use anyhow::Context;
use std::sync::Arc;

use arrow::array::{ArrayRef, Float64Array, RecordBatch, StringArray, UInt32Array, UInt64Array};
use arrow::datatypes::{DataType, Field, Schema};
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use parquet::arrow::ArrowWriter;
use parquet::basic::{Compression, ZstdLevel};
use parquet::file::properties::WriterProperties;

/// A column of a stage table.
pub enum Col {
    Str(Vec<String>),
    U32(Vec<u32>),
    U64(Vec<u64>),
    F64(Vec<f64>),
}

/// Write named columns as one Parquet table.
pub fn write_table(path: &Path, columns: Vec<(&str, Col)>) -> anyhow::Result<()> {
    let (fields, arrays): (Vec<Field>, Vec<ArrayRef>) = columns
        .into_iter()
        .map(|(name, col)| match col {
            Col::Str(v) => (
                Field::new(name, DataType::Utf8, false),
                Arc::new(StringArray::from(v)) as ArrayRef,
            ),
            Col::U32(v) => (
                Field::new(name, DataType::UInt32, false),
                Arc::new(UInt32Array::from(v)) as ArrayRef,
            ),
            Col::U64(v) => (
                Field::new(name, DataType::UInt64, false),
                Arc::new(UInt64Array::from(v)) as ArrayRef,
            ),
            Col::F64(v) => (
                Field::new(name, DataType::Float64, false),
                Arc::new(Float64Array::from(v)) as ArrayRef,
            ),
        })
        .unzip();
    write_batch(
        path,
        &RecordBatch::try_new(Arc::new(Schema::new(fields)), arrays)?,
    )
}

/// Write one record batch as a stage table: the same bytes [`write_table`] gives for the same columns.
pub fn write_batch(path: &Path, batch: &RecordBatch) -> anyhow::Result<()> {
    let props = WriterProperties::builder()
        .set_compression(Compression::ZSTD(ZstdLevel::try_new(3)?))
        .build();
    let mut writer = ArrowWriter::try_new(File::create(path)?, batch.schema(), Some(props))?;
    writer.write(batch)?;
    writer.close()?;
    Ok(())
}

/// Several stage tables with one schema (consecutive parts of one table) written as that one table.
pub fn concat_tables(parts: &[PathBuf], out: &Path) -> anyhow::Result<()> {
    let first = parts
        .first()
        .ok_or_else(|| anyhow::anyhow!("no stage tables to concatenate into {}", out.display()))?;
    let schema = ParquetRecordBatchReaderBuilder::try_new(File::open(first)?)?
        .schema()
        .clone();
    let mut batches = Vec::new();
    for part in parts {
        batches.extend(
            read_table(part)
                .with_context(|| format!("{}: unreadable stage table", part.display()))?,
        );
    }
    write_batch(out, &arrow::compute::concat_batches(&schema, &batches)?)
}

/// Read a whole stage table.
pub fn read_table(path: &Path) -> anyhow::Result<Vec<RecordBatch>> {
    let reader = ParquetRecordBatchReaderBuilder::try_new(File::open(path)?)?.build()?;
    Ok(reader.collect::<Result<Vec<_>, _>>()?)
}

fn column<'a, T: 'static>(batch: &'a RecordBatch, name: &str) -> anyhow::Result<&'a T> {
    batch
        .column_by_name(name)
        .and_then(|c| c.as_any().downcast_ref::<T>())
        .ok_or_else(|| {
            anyhow::anyhow!("stage table lacks column '{name}' (re-run the stage that writes it)")
        })
}

pub fn strings(batches: &[RecordBatch], name: &str) -> anyhow::Result<Vec<String>> {
    let mut out = Vec::new();
    for b in batches {
        out.extend(
            column::<StringArray>(b, name)?
                .iter()
                .map(|v| v.unwrap_or_default().to_string()),
        );
    }
    Ok(out)
}

pub fn u32s(batches: &[RecordBatch], name: &str) -> anyhow::Result<Vec<u32>> {
    let mut out = Vec::new();
    for b in batches {
        out.extend_from_slice(column::<UInt32Array>(b, name)?.values());
    }
    Ok(out)
}

pub fn f64s(batches: &[RecordBatch], name: &str) -> anyhow::Result<Vec<f64>> {
    let mut out = Vec::new();
    for b in batches {
        out.extend_from_slice(column::<Float64Array>(b, name)?.values());
    }
    Ok(out)
}

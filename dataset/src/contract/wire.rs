//! The dataset server's wire format: sample rows as an Arrow IPC stream (its tensor endpoints send it; the
//! trainer's HTTP source and the tests read it back). Shard files on disk are [`super::shard`]'s business.

use arrow::record_batch::RecordBatch;

use crate::contract::schema::{batch_to_samples, sample_schema, Sample, SchemaError};

/// Arrow IPC stream bytes (the wire format of the dataset server's tensor endpoints) of `batches`.
pub fn ipc_stream_bytes(batches: &[RecordBatch]) -> Result<Vec<u8>, arrow::error::ArrowError> {
    let schema = batches
        .first()
        .map_or_else(sample_schema, RecordBatch::schema);
    let mut writer = arrow::ipc::writer::StreamWriter::try_new(Vec::new(), &schema)?;
    for batch in batches {
        writer.write(batch)?;
    }
    writer.into_inner()
}

/// Decode an Arrow IPC stream of sample rows (what [`ipc_stream_bytes`] wrote).
pub fn samples_from_ipc_stream(bytes: &[u8]) -> Result<Vec<Sample>, SchemaError> {
    let reader = arrow::ipc::reader::StreamReader::try_new(std::io::Cursor::new(bytes), None)?;
    let mut out = Vec::new();
    for batch in reader {
        out.extend(batch_to_samples(&batch?)?);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::contract::schema::samples_to_batch;

    /// What the stream carries decodes to the same samples, in order, across several batches; an empty stream
    /// still carries the schema.
    #[test]
    fn samples_survive_the_stream_across_batches() {
        let samples: Vec<Sample> = (0..5).map(crate::testing::synthetic_sample).collect();
        let batches = [
            samples_to_batch(&samples[..2]).unwrap(),
            samples_to_batch(&samples[2..]).unwrap(),
        ];
        let bytes = ipc_stream_bytes(&batches).unwrap();
        assert_eq!(samples_from_ipc_stream(&bytes).unwrap(), samples);
        let empty = ipc_stream_bytes(&[]).unwrap();
        assert!(samples_from_ipc_stream(&empty).unwrap().is_empty());
        let reader =
            arrow::ipc::reader::StreamReader::try_new(std::io::Cursor::new(&empty), None).unwrap();
        assert_eq!(*reader.schema(), *sample_schema());
    }
}

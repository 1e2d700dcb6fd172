//! A sample's rasters as JSON (`/v1/rows?tensors=base64`): each raster's little-endian bytes as base64 (row-major,
//! north row first), with its dtype and shape.
//!
//! The base64 text goes into the JSON as it is. Base64 holds no character JSON escapes, but serde_json checks every
//! character of a string it writes, and on a load test's tensor pages (~0.6 MB of base64 each) that check took
//! 6.6 % of the machine's cycles, client included (perf, docs/experiments.md). A [`RawValue`] is written unchecked.

use base64::Engine;
use serde_json::value::RawValue;

use dataset::contract::schema::{Sample, CONTEXT_PX, CROP_PX, DEM_PX};

/// One raster. Fields in alphabetical order, as the JSON of a map has them.
#[derive(serde::Serialize)]
pub struct TensorJson {
    base64: Box<RawValue>,
    dtype: &'static str,
    /// The context window's cell size; no other raster has one.
    #[serde(skip_serializing_if = "Option::is_none")]
    gsd_m: Option<f64>,
    shape: [usize; 2],
}

/// A sample's rasters; `context_dem` is null for a schema 1.1 dataset, which has no context window, and
/// `context_highland` for a dataset built without a unit map.
#[derive(serde::Serialize)]
pub struct TensorsJson {
    context_dem: Option<TensorJson>,
    context_highland: Option<TensorJson>,
    dem: TensorJson,
    image: TensorJson,
    sun_lit: TensorJson,
    valid: TensorJson,
}

impl TensorsJson {
    pub fn of(s: &Sample) -> Self {
        let float32 = |v: &[f32], px: usize| TensorJson {
            base64: base64_string(&le_bytes(v)),
            dtype: "float32",
            gsd_m: None,
            shape: [px, px],
        };
        Self {
            context_dem: s.context.as_ref().map(|c| TensorJson {
                gsd_m: Some(c.gsd_m),
                ..float32(&c.heights_m, CONTEXT_PX)
            }),
            context_highland: s.context.as_ref().and_then(|c| {
                c.highland.as_ref().map(|h| TensorJson {
                    gsd_m: Some(c.gsd_m),
                    ..float32(h, CONTEXT_PX)
                })
            }),
            dem: float32(&s.dem_m, DEM_PX),
            image: float32(&s.image, CROP_PX),
            sun_lit: float32(&s.sun_lit, CROP_PX),
            valid: TensorJson {
                base64: base64_string(&s.valid),
                dtype: "uint8",
                gsd_m: None,
                shape: [CROP_PX, CROP_PX],
            },
        }
    }
}

fn le_bytes(values: &[f32]) -> Vec<u8> {
    let mut bytes = Vec::with_capacity(values.len() * 4);
    for v in values {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    bytes
}

/// `bytes` as a JSON string of their base64.
fn base64_string(bytes: &[u8]) -> Box<RawValue> {
    let mut text = String::with_capacity(bytes.len().div_ceil(3) * 4 + 2);
    text.push('"');
    base64::engine::general_purpose::STANDARD.encode_string(bytes, &mut text);
    text.push('"');
    RawValue::from_string(text).expect("base64 in quotes is a JSON string")
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The JSON the server wrote before the rasters' base64 went in unchecked: a map built value by value.
    fn as_a_map(s: &Sample) -> serde_json::Value {
        let b64 = |bytes: &[u8]| base64::engine::general_purpose::STANDARD.encode(bytes);
        let f32s = |v: &[f32]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
        serde_json::json!({
            "dem": { "dtype": "float32", "shape": [DEM_PX, DEM_PX], "base64": b64(&f32s(&s.dem_m)) },
            "image": { "dtype": "float32", "shape": [CROP_PX, CROP_PX], "base64": b64(&f32s(&s.image)) },
            "valid": { "dtype": "uint8", "shape": [CROP_PX, CROP_PX], "base64": b64(&s.valid) },
            "sun_lit": { "dtype": "float32", "shape": [CROP_PX, CROP_PX], "base64": b64(&f32s(&s.sun_lit)) },
            "context_dem": s.context.as_ref().map(|c| serde_json::json!({
                "dtype": "float32", "shape": [CONTEXT_PX, CONTEXT_PX], "base64": b64(&f32s(&c.heights_m)), "gsd_m": c.gsd_m,
            })),
            "context_highland": s.context.as_ref().and_then(|c| c.highland.as_ref()).map(|h| serde_json::json!({
                "dtype": "float32", "shape": [CONTEXT_PX, CONTEXT_PX], "base64": b64(&f32s(h)), "gsd_m": s.context.as_ref().map(|c| c.gsd_m),
            })),
        })
    }

    fn sample(context: bool) -> Sample {
        let mut s = dataset::testing::synthetic_sample(3);
        if !context {
            s.context = None;
        }
        s
    }

    #[test]
    fn the_json_is_byte_for_byte_the_map_of_each_raster() {
        for context in [true, false] {
            let s = sample(context);
            let written = serde_json::to_vec(&TensorsJson::of(&s)).unwrap();
            assert_eq!(
                String::from_utf8(written).unwrap(),
                serde_json::to_string(&as_a_map(&s)).unwrap(),
                "context window: {context}"
            );
        }
    }

    #[test]
    fn the_base64_decodes_to_the_rasters_bytes() {
        let s = sample(true);
        let json: serde_json::Value = serde_json::to_value(TensorsJson::of(&s)).unwrap();
        let decoded = base64::engine::general_purpose::STANDARD
            .decode(json["dem"]["base64"].as_str().unwrap())
            .unwrap();
        let dem: Vec<f32> = decoded
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .collect();
        assert_eq!(dem, s.dem_m);
    }
}

//! A shard written by `dataset` reads back with pyarrow and no custom code (pip install pyarrow).

use std::process::Command;

use dataset::contract::crater_frame::CraterPosition;
use dataset::contract::schema::{ContextWindow, Sample, Split, CONTEXT_PX, CROP_PX, DEM_PX};
use dataset::contract::shard::ShardWriter;

fn sample(i: usize) -> Sample {
    let n = CROP_PX * CROP_PX;
    Sample {
        sample_id: format!("M0000001:{i}:7"),
        split: if i.is_multiple_of(2) {
            Split::Train
        } else {
            Split::Val
        },
        tile_id: "t_0_0".into(),
        ortho_id: "M0000001".into(),
        center_x_m: i as f64 * 5.0,
        center_y_m: -1_300_000.0,
        center_lon_deg: -11.3,
        center_lat_deg: -43.3,
        footprint_lonlat_deg: [0.0; 8],
        dem_m: (0..DEM_PX * DEM_PX)
            .map(|k| k as f32 * 0.5 - 1200.0)
            .collect(),
        image: (0..n).map(|k| (k + i) as f32 / n as f32).collect(),
        valid: (0..n).map(|k| (k % 5 != 0) as u8).collect(),
        sun_lit: vec![1.0; n],
        sun_dir_enu: [0.6, 0.0, 0.8],
        camera_pos_enu_m: [0.0, 10.0, 50_000.0],
        enu_origin_height_m: 0.0,
        map_to_en: [1.0, 0.0, 0.0, 1.0],
        camera_att: [1.0, 0.0, 0.0, 0.0],
        fov_deg: 2.85,
        gsd_m: 5.0,
        incidence_deg: 36.87,
        emission_deg: 0.01,
        phase_deg: 36.86,
        acq_time: "2010-01-01T00:00:00.000Z".into(),
        provenance: "interop-test".into(),
        // Cell 0 is off the DEM (NaN): NaN must survive as NaN, not become a null or a number.
        context: Some(ContextWindow {
            gsd_m: 512.0,
            heights_m: (0..CONTEXT_PX * CONTEXT_PX)
                .map(|k| if k == 0 { f32::NAN } else { k as f32 - 1500.0 })
                .collect(),
            // Unmapped (NaN) in row 0, then mare west of column 16 and highland east of it.
            highland: Some(
                (0..CONTEXT_PX * CONTEXT_PX)
                    .map(|k| match (k / CONTEXT_PX, k % CONTEXT_PX) {
                        (0, _) => f32::NAN,
                        (_, col) => f32::from(u8::from(col >= 16)),
                    })
                    .collect(),
            ),
        }),
        crater: Some(CraterPosition {
            rho: 0.8125,
            relative_height_m: -137.5,
            relief_to_diameter: Some(0.0625),
        }),
    }
}

#[test]
fn shard_reads_back_with_pyarrow_without_custom_code() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir
        .path()
        .join(dataset::contract::shard::shard_name("train", 0, 1));
    let mut writer = ShardWriter::create(&path).unwrap();
    writer
        .write(&(0..300).map(sample).collect::<Vec<_>>())
        .unwrap();
    writer.finish().unwrap();
    let script = r#"
import sys, pyarrow.parquet as pq
f = pq.ParquetFile(sys.argv[1])
t = pq.read_table(sys.argv[1])
assert t.num_rows == 300, t.num_rows
assert f.metadata.num_row_groups == 2, f.metadata.num_row_groups
assert f.schema_arrow.metadata[b"g2r.schema_version"] == b"1.6.0", f.schema_arrow.metadata
assert t.column("map_to_en")[0].values.to_pylist() == [1.0, 0.0, 0.0, 1.0]
assert t.column("enu_origin_height_m").to_pylist()[0] == 0.0
dem = t.column("dem")[3].values.to_numpy()
assert dem.shape == (130 * 130,), dem.shape
assert abs(float(dem[10]) - (10 * 0.5 - 1200.0)) < 1e-6
img = t.column("image")[7].values.to_numpy().reshape(128, 128)
assert abs(float(img[0, 5]) - (5 + 7) / 16384) < 1e-7
assert t.column("valid")[0].values.to_numpy().sum() == 16384 - 16384 // 5 - 1
assert t.column("split").to_pylist()[:2] == ["train", "val"]
assert t.schema.field("dem").metadata[b"unit"] == b"m"
ctx = t.column("context_dem")[2].values.to_numpy().reshape(32, 32)
assert ctx[0, 0] != ctx[0, 0] and ctx[1, 3] == 35 - 1500.0, ctx[:2, :4]
assert t.column("context_gsd_m").to_pylist()[0] == 512.0
assert t.column("crater_rho").to_pylist()[0] == 0.8125 and t.column("crater_relative_height_m").to_pylist()[0] == -137.5
assert t.schema.field("crater_relative_height_m").metadata[b"unit"] == b"m"
assert t.column("crater_relief_to_diameter").to_pylist()[0] == 0.0625
units = t.column("context_highland")[4].values.to_numpy().reshape(32, 32)
assert units[0, 7] != units[0, 7] and units[1, 15] == 0.0 and units[1, 16] == 1.0, units[:2, 14:18]
assert t.schema.field("context_highland").metadata[b"unit"] == b"1"
encodings = f.metadata.row_group(0).column(t.schema.get_field_index("dem")).encodings
print("ok", encodings)
"#;
    let output = Command::new(g2r_tests::python())
        .arg("-c")
        .arg(script)
        .arg(&path)
        .output()
        .expect("python3 must be installed: run `bash .ci/setup`");
    assert!(
        output.status.success(),
        "pyarrow could not read the shard (run `bash .ci/setup`, which puts pyarrow in .venv):\n{}{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    assert!(
        String::from_utf8_lossy(&output.stdout).contains("BYTE_STREAM_SPLIT"),
        "{}",
        String::from_utf8_lossy(&output.stdout)
    );
}

//! Same world config + seed ⇒ byte-identical files; a different seed changes them; bad requests are refused.

use std::path::Path;

use pipeline::synth::WorldConfig;

fn tiny() -> WorldConfig {
    g2r_tests::tiny_world_config()
}

fn file_hashes(dir: &Path) -> Vec<(String, String)> {
    let world: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("world.json")).unwrap()).unwrap();
    world["files"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| {
            (
                f["path"].as_str().unwrap().to_string(),
                f["blake3"].as_str().unwrap().to_string(),
            )
        })
        .collect()
}

#[test]
fn same_seed_gives_byte_identical_world_and_other_seed_differs() {
    let tmp = tempfile::tempdir().unwrap();
    let cfg = tiny();
    let a = pipeline::synth::generate(&cfg, 7, &tmp.path().join("a"), false).unwrap();
    let b = pipeline::synth::generate(&cfg, 7, &tmp.path().join("b"), false).unwrap();
    let c = pipeline::synth::generate(&cfg, 8, &tmp.path().join("c"), false).unwrap();
    let (ha, hb, hc) = (file_hashes(&a), file_hashes(&b), file_hashes(&c));
    assert_eq!(
        ha.len(),
        6 + 2 + 3 * 3,
        "dem, 5 truth files, index table + label, 3 × (ortho + metadata + ISD)"
    );
    assert_eq!(ha, hb);
    assert_eq!(
        std::fs::read(a.join("world.json")).unwrap(),
        std::fs::read(b.join("world.json")).unwrap()
    );
    // And the listed hashes are those of the files on disk.
    for (path, hash) in &ha {
        assert_eq!(
            &dataset::files::hash_file(&a.join(path)).unwrap(),
            hash,
            "{path}"
        );
    }
    let dem = |h: &[(String, String)]| {
        h.iter()
            .find(|(p, _)| p == "dem/dem.tif")
            .unwrap()
            .1
            .clone()
    };
    assert_ne!(dem(&ha), dem(&hc), "another seed must give another world");
}

#[test]
fn existing_output_is_refused_without_force_and_no_partial_is_left() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("w");
    std::fs::create_dir_all(&out).unwrap();
    let err = pipeline::synth::generate(&tiny(), 1, &out, false)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("already exists") && err.contains("--force"),
        "{err}"
    );
    assert!(!tmp.path().join("w.partial").exists());
}

/// The error message of generating `cfg` into a fresh directory.
fn generation_error(cfg: &WorldConfig) -> String {
    let out = tempfile::tempdir().unwrap().path().join("w");
    pipeline::synth::generate(cfg, 1, &out, false)
        .unwrap_err()
        .to_string()
}

#[test]
fn impossible_configs_name_the_field_to_fix() {
    let mut cfg = tiny();
    cfg.world.dem_gsd_m = 4.0; // not a multiple of the 2.5 m fine grid
    let err = generation_error(&cfg);
    assert!(err.contains("dem_gsd_m"), "{err}");
    let mut cfg = tiny();
    cfg.acquisitions.incidence_max_deg = 95.0; // sun below the horizon
    let err = generation_error(&cfg);
    assert!(err.contains("incidence"), "{err}");
    let err = WorldConfig::from_toml("[world]\nname = 1")
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("name") || err.contains("invalid type"),
        "{err}"
    );
}

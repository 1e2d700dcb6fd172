//! A population of complex craters on a small world: the drawn craters are stamped where, and as worn as, the
//! catalogue the world writes says (the terrain classes and the true DEM agree with it), and the pipeline's crater
//! frames read that catalogue.

use dataset::contract::crater_frame::{read_catalogue, CraterFrames};
use dataset::contract::world::{self as layout, TerrainClass};
use dataset::science::raster::{read_bands, read_raster};
use pipeline::synth::config::{tiny, ComplexCraterPopulation};

#[test]
fn a_world_with_several_complex_craters_writes_the_catalogue_it_stamped() {
    let mut config = tiny();
    config.complex_craters = Some(ComplexCraterPopulation {
        count_min: 2,
        count_max: 3,
        diameter_min_m: 900.0,
        diameter_max_m: 1300.0,
        depth_to_diameter: 0.1,
        terraces_min: 2,
        terraces_max: 4,
        degradation_max: 0.8,
        min_separation_radii: 1.1,
    });
    let dir = tempfile::tempdir().unwrap();
    let world = pipeline::synth::generate(&config, 5, &dir.path().join("w"), false).unwrap();
    let catalogue_path = world.join(layout::TRUE_COMPLEX_CRATERS);
    let catalogue = read_catalogue(&catalogue_path).unwrap();
    assert!((2..=3).contains(&catalogue.len()), "{catalogue:?}");
    let dem = read_raster(&world.join(layout::TRUE_DEM)).unwrap();
    let plain_world =
        pipeline::synth::generate(&tiny(), 5, &dir.path().join("plain"), false).unwrap();
    let plain = read_raster(&plain_world.join(layout::TRUE_DEM)).unwrap();
    // Each crater's degradation, by its diameter, from the catalogue's own column.
    let worn: std::collections::HashMap<u64, f64> = std::fs::read_to_string(&catalogue_path)
        .unwrap()
        .lines()
        .skip(1)
        .map(|line| {
            let cols: Vec<f64> = line.split(',').map(|v| v.parse().unwrap()).collect();
            ((cols[2] * 1000.0).round().to_bits(), cols[3])
        })
        .collect();
    let classes = &read_bands(&world.join(layout::TRUE_TERRAIN_CLASS)).unwrap()[0];
    let delivered = read_raster(&world.join(layout::DEM)).unwrap();
    for crater in &catalogue {
        assert!((900.0..=1300.0).contains(&crater.diameter_m));
        let (x, y) = dem
            .crs
            .from_lonlat_deg(crater.lon_deg, crater.lat_deg)
            .unwrap();
        let radius = crater.diameter_m / 2.0;
        // Class at the centre, on the wall and beyond the ejecta, on the delivered DEM's grid.
        let class_at = |dx: f64, dy: f64| {
            let (c, r) = delivered.transform.map_to_pixel(x + dx, y + dy);
            TerrainClass::from_code(classes.get(c.floor() as usize, r.floor() as usize) as f64)
        };
        assert_eq!(class_at(0.0, 0.0), Some(TerrainClass::MeltFloor));
        assert_eq!(
            class_at(0.75 * radius, 0.0),
            Some(TerrainClass::TerracedWall)
        );
        // The true DEM less the same world's without the craters (same seed: the same background and simple
        // craters) is the stamp alone: its floor at 0.3 radii lies the worn depth down, 0.1 D × (1 − 0.6 ×
        // degradation), within the hummocks (a few % of it) and the other craters' ejecta there (at ≥ 1.8 of
        // their radii: under a fifth of a rim of 0.02 × 1300 m).
        let stamp = |dx: f64, dy: f64| {
            let (c, r) = dem.transform.map_to_pixel(x + dx, y + dy);
            (dem.bilinear(c, r) - plain.bilinear(c, r)) as f64
        };
        let degradation = worn[&(crater.diameter_m * 1000.0).round().to_bits()];
        let depth = 0.1 * crater.diameter_m * (1.0 - 0.6 * degradation);
        for k in 0..8 {
            let a = k as f64 * std::f64::consts::TAU / 8.0;
            let floor = stamp(0.3 * radius * a.cos(), 0.3 * radius * a.sin());
            assert!(
                (floor + depth).abs() < 0.05 * depth + 0.2 * 0.02 * 1300.0,
                "floor {floor:.1} m, worn depth {depth:.1} m (D {:.0} m, degradation {degradation})",
                crater.diameter_m
            );
        }
    }
    // The pipeline frames every one of them from the catalogue, on the delivered DEM.
    let (frames, report) = CraterFrames::new(&delivered, &catalogue, 500.0).unwrap();
    assert_eq!(report.framed, catalogue.len(), "{report:?}");
    assert!(!frames.is_empty());
    // The catalogue is listed with its hash in world.json.
    let manifest: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(world.join(layout::MANIFEST)).unwrap())
            .unwrap();
    let listed = manifest["files"]
        .as_array()
        .unwrap()
        .iter()
        .any(|f| f.to_string().contains(layout::TRUE_COMPLEX_CRATERS));
    assert!(listed, "world.json lists {}", layout::TRUE_COMPLEX_CRATERS);
}

//! The demo world must be credible enough that learned-vs-Hapke numbers mean something (docs/design.md, Synthetic world).
//! The world is generated once per run (about a minute) and shared by the tests in this file.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use dataset::contract::acquisition::AcquisitionMetadata;
use dataset::science::crs::{LocalFrame, LunarCrs, MOON_RADIUS_M};
use dataset::science::raster::read_raster;
use gdal::Dataset;
use glam::DVec3;
use serde_json::Value;

fn demo_world() -> &'static Path {
    static WORLD: OnceLock<PathBuf> = OnceLock::new();
    WORLD.get_or_init(|| {
        let out = Path::new(env!("CARGO_TARGET_TMPDIR")).join("demo-world-seed42");
        let config = pipeline::synth::WorldConfig::from_toml(
            pipeline::synth::config::preset("demo").unwrap(),
        )
        .unwrap();
        pipeline::synth::generate(&config, 42, &out, true).expect("demo world generates")
    })
}

fn world_json() -> Value {
    serde_json::from_str(&std::fs::read_to_string(demo_world().join("world.json")).unwrap())
        .unwrap()
}

fn crs() -> LunarCrs {
    LunarCrs::new(world_json()["crs"].as_str().unwrap())
}

#[test]
fn crater_size_frequency_slope_matches_configuration() {
    let world = world_json();
    let configured = world["config"]["terrain"]["sfd_cumulative_slope"]
        .as_f64()
        .unwrap();
    let (d_min, d_max) = (
        world["config"]["terrain"]["crater_min_diameter_m"]
            .as_f64()
            .unwrap(),
        world["config"]["terrain"]["crater_max_diameter_m"]
            .as_f64()
            .unwrap(),
    );
    let craters: Vec<Value> = serde_json::from_str(
        &std::fs::read_to_string(demo_world().join("truth/craters.json")).unwrap(),
    )
    .unwrap();
    let mut diameters: Vec<f64> = craters
        .iter()
        .map(|c| c["diameter_m"].as_f64().unwrap())
        .collect();
    diameters.sort_by(|a, b| b.total_cmp(a));
    // Least squares of ln N(>D) on ln D, away from the truncation at both ends.
    let points: Vec<(f64, f64)> = diameters
        .iter()
        .enumerate()
        .filter(|(_, &d)| d > 2.0 * d_min && d < d_max / 4.0)
        .map(|(k, &d)| (d.ln(), ((k + 1) as f64).ln()))
        .collect();
    let n = points.len() as f64;
    let (mx, my) = (
        points.iter().map(|p| p.0).sum::<f64>() / n,
        points.iter().map(|p| p.1).sum::<f64>() / n,
    );
    let slope = points.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum::<f64>()
        / points.iter().map(|p| (p.0 - mx).powi(2)).sum::<f64>();
    println!(
        "fitted cumulative SFD slope {slope:.3} (configured {configured}) over {} craters",
        points.len()
    );
    assert!(
        (slope - configured).abs() <= 0.15,
        "fitted slope {slope} vs configured {configured}"
    );
}

#[test]
fn fresh_craters_have_lunar_depth_to_diameter() {
    let world = world_json();
    let dem = read_raster(&demo_world().join("truth/dem_true.tif")).unwrap();
    let craters: Vec<Value> = serde_json::from_str(
        &std::fs::read_to_string(demo_world().join("truth/craters.json")).unwrap(),
    )
    .unwrap();
    let cc = &world["config"]["complex_crater"];
    let crs = crs();
    let (cx, cy) = crs
        .from_lonlat_deg(
            world["config"]["world"]["center_lon_deg"].as_f64().unwrap(),
            world["config"]["world"]["center_lat_deg"].as_f64().unwrap(),
        )
        .unwrap();
    let (ccx, ccy, cc_r) = (
        cx + cc["offset_east_m"].as_f64().unwrap(),
        cy + cc["offset_north_m"].as_f64().unwrap(),
        cc["diameter_m"].as_f64().unwrap() / 2.0,
    );
    let gt = dem.transform;
    let mut ratios = Vec::new();
    for c in &craters {
        let (x, y, d) = (
            c["x_m"].as_f64().unwrap(),
            c["y_m"].as_f64().unwrap(),
            c["diameter_m"].as_f64().unwrap(),
        );
        let r = d / 2.0;
        let (col, row) = gt.map_to_pixel(x, y);
        let r_px = r / gt.gsd_m();
        let inside = col - 1.5 * r_px > 0.0
            && row - 1.5 * r_px > 0.0
            && col + 1.5 * r_px < dem.width as f64
            && row + 1.5 * r_px < dem.height as f64;
        let away_from_complex = ((x - ccx).powi(2) + (y - ccy).powi(2)).sqrt() > 3.2 * cc_r;
        if c["freshness"].as_f64().unwrap() < 0.5 || d < 100.0 || !inside || !away_from_complex {
            continue;
        }
        let sample = |rho: f64, az: f64| {
            dem.bilinear(col + rho * r_px * az.cos(), row + rho * r_px * az.sin()) as f64
        };
        let floor = (0..40)
            .flat_map(|i| (0..5).map(move |j| (i, j)))
            .map(|(i, j)| sample(0.05 * j as f64, i as f64 * 0.157))
            .fold(f64::MAX, f64::min);
        let mut rims: Vec<f64> = (0..24)
            .map(|i| {
                (0..13)
                    .map(|j| {
                        sample(
                            0.85 + 0.025 * j as f64,
                            i as f64 * std::f64::consts::TAU / 24.0,
                        )
                    })
                    .fold(f64::MIN, f64::max)
            })
            .collect();
        rims.sort_by(f64::total_cmp);
        ratios.push((rims[12] - floor) / d);
    }
    ratios.sort_by(f64::total_cmp);
    assert!(
        ratios.len() >= 5,
        "only {} fresh craters ≥ 100 m to measure",
        ratios.len()
    );
    let median = ratios[ratios.len() / 2];
    println!(
        "fresh-crater depth/diameter: median {median:.3} over {} craters (range {:.3}..{:.3})",
        ratios.len(),
        ratios[0],
        ratios[ratios.len() - 1]
    );
    assert!((0.15..=0.22).contains(&median), "median fresh d/D {median}");
}

/// Valid pixel values of an ortho.
fn ortho_values(id: &str) -> Vec<f32> {
    read_raster(&demo_world().join(format!("ortho/{id}.tif")))
        .unwrap()
        .data
        .into_iter()
        .filter(|v| v.is_finite())
        .collect()
}

#[test]
fn cast_shadows_appear_at_high_incidence_only() {
    let world = world_json();
    let mut high = 0;
    for ortho in world["orthos"].as_array().unwrap() {
        let (id, incidence) = (
            ortho["ortho_id"].as_str().unwrap(),
            ortho["incidence_deg"].as_f64().unwrap(),
        );
        if incidence > 40.0 && incidence < 70.0 {
            continue;
        }
        let mut values = ortho_values(id);
        values.sort_by(f32::total_cmp);
        let median = values[values.len() / 2];
        // Cast shadows are near-black (noise only): far below the median brightness.
        let dark =
            values.iter().filter(|&&v| v < 0.1 * median).count() as f64 / values.len() as f64;
        println!(
            "{id}: incidence {incidence:.1}°, dark (shadowed) share {:.2} %",
            100.0 * dark
        );
        if incidence > 70.0 {
            high += 1;
            assert!(
                dark > 0.01,
                "{id} at i = {incidence:.1}° has only {dark:.4} of its pixels in shadow"
            );
        } else {
            assert!(dark < 0.002, "{id} at i = {incidence:.1}° has {dark:.4} dark pixels: shadows where the sun is high");
        }
    }
    assert!(
        high >= 1,
        "the demo world has no acquisition above 70° incidence"
    );
}

#[test]
fn brightness_correlates_with_but_is_not_determined_by_dem_features() {
    let world = world_json();
    let crs = crs();
    let dem = read_raster(&demo_world().join("dem/dem.tif")).unwrap();
    let mut r2s = Vec::new();
    for ortho in world["orthos"].as_array().unwrap() {
        let id = ortho["ortho_id"].as_str().unwrap();
        let image = read_raster(&demo_world().join(format!("ortho/{id}.tif"))).unwrap();
        let meta =
            AcquisitionMetadata::load(&demo_world().join(format!("ortho/{id}.json"))).unwrap();
        // Average the ortho pixels into DEM cells (area downsampling 2 m → 5 m).
        let (mut sum, mut count) = (
            vec![0f64; dem.width * dem.height],
            vec![0u32; dem.width * dem.height],
        );
        for row in 0..image.height {
            for col in 0..image.width {
                let v = image.get(col, row);
                let (x, y) = image.transform.pixel_center(col as f64, row as f64);
                let (dc, dr) = dem.transform.map_to_pixel(x, y);
                let (dc, dr) = (dc.round(), dr.round());
                if dc < 0.0 || dr < 0.0 || dc >= dem.width as f64 || dr >= dem.height as f64 {
                    continue;
                }
                let i = dr as usize * dem.width + dc as usize;
                if v.is_finite() {
                    sum[i] += v as f64;
                    count[i] += 1;
                } else {
                    count[i] = u32::MAX / 2; // any nodata in the cell disqualifies it
                }
            }
        }
        let (cx, cy) = image
            .transform
            .pixel_center(image.width as f64 / 2.0, image.height as f64 / 2.0);
        let frame = LocalFrame::new(&crs, cx, cy, 0.0).unwrap();
        let sun = frame.sun_dir_enu(meta.sun_body());
        let camera = frame.body_point_to_enu(dataset::science::geometry::spacecraft_position_at(
            meta.spacecraft_start_body_m.into(),
            meta.spacecraft_stop_body_m.into(),
            0.5,
        ));
        // Features from the delivered DEM: Lommel–Seeliger term and cos i; target: mean I/F in the cell.
        let mut rows: Vec<([f64; 3], f64)> = Vec::new();
        let gsd = dem.transform.gsd_m();
        for r in (1..dem.height - 1).step_by(2) {
            for c in (1..dem.width - 1).step_by(2) {
                let i = r * dem.width + c;
                if count[i] < 4 || count[i] > 100 {
                    continue;
                }
                let dzdx = (dem.get(c + 1, r) - dem.get(c - 1, r)) as f64 / (2.0 * gsd);
                let dzdy = -(dem.get(c, r + 1) - dem.get(c, r - 1)) as f64 / (2.0 * gsd);
                if !dzdx.is_finite() || !dzdy.is_finite() {
                    continue;
                }
                let (x, y) = dem.transform.pixel_center(c as f64, r as f64);
                let p = frame.map_to_enu(x, y, dem.get(c, r) as f64);
                let n = DVec3::new(
                    -dzdx - p.x / MOON_RADIUS_M,
                    -dzdy - p.y / MOON_RADIUS_M,
                    1.0,
                )
                .normalize();
                let v = (camera - p).normalize();
                let (mu0, mu) = (n.dot(sun).max(0.0), n.dot(v).max(1e-6));
                rows.push(([1.0, mu0 / (mu0 + mu), mu0], sum[i] / count[i] as f64));
            }
        }
        let r2 = r_squared(&rows);
        println!("{id}: incidence {:.1}°, R² of I/F ~ 1 + LS + cos i on the delivered DEM = {r2:.3} ({} cells)", ortho["incidence_deg"].as_f64().unwrap(), rows.len());
        r2s.push((ortho["incidence_deg"].as_f64().unwrap(), r2));
    }
    let mean = r2s.iter().map(|r| r.1).sum::<f64>() / r2s.len() as f64;
    println!("mean R² over {} orthos: {mean:.3}", r2s.len());
    // Not determined: albedo variation, cast shadows, DEM error and noise always leave a share unexplained.
    assert!(
        r2s.iter().all(|&(_, r)| r < 0.9),
        "R² (incidence, R²) {r2s:?}"
    );
    // Correlated where topography dominates: under a low sun (i > 50°) shading by slopes is strong. Under a high
    // sun shading is weak and albedo dominates, so R² there is low — as on the real Moon near full phase.
    assert!(
        r2s.iter().filter(|(i, _)| *i > 50.0).all(|&(_, r)| r > 0.3),
        "R² (incidence, R²) {r2s:?}"
    );
    assert!((0.25..0.85).contains(&mean), "mean R² {mean}");
}

/// Maria are told apart by the DEM, as on the Moon: flooded plains carry fewer craters (the old ones are buried)
/// and less relief than highlands, and they are darker. This is what makes the unit albedo — the largest
/// reflectance component — predictable from terrain (pipeline/src/synth/units.rs).
#[test]
fn maria_are_darker_smoother_and_less_cratered_than_highlands() {
    let config =
        pipeline::synth::WorldConfig::from_toml(pipeline::synth::config::preset("demo").unwrap())
            .unwrap();
    let units = pipeline::synth::geologic_units::Units::new(&config.reflectance, 42);
    let dem = read_raster(&demo_world().join("dem/dem.tif")).unwrap();
    let w_map = read_raster(&demo_world().join("truth/hapke_params.tif")).unwrap();
    // Per unit (0 = mare, 1 = highland; the soft boundary is left out): cells, summed slope², summed w.
    let mut stats = [(0usize, 0f64, 0f64); 2];
    let gsd = dem.transform.gsd_m();
    for r in (1..dem.height - 1).step_by(3) {
        for c in (1..dem.width - 1).step_by(3) {
            let (x, y) = dem.transform.pixel_center(c as f64, r as f64);
            let highland = units.highland(x, y);
            let unit = match highland {
                h if h < 0.05 => 0,
                h if h > 0.95 => 1,
                _ => continue,
            };
            let dzdx = (dem.get(c + 1, r) - dem.get(c - 1, r)) as f64 / (2.0 * gsd);
            let dzdy = (dem.get(c, r + 1) - dem.get(c, r - 1)) as f64 / (2.0 * gsd);
            if !(dzdx.is_finite() && dzdy.is_finite()) {
                continue; // the delivered DEM's nodata artefacts
            }
            let (wc, wr) = w_map.transform.map_to_pixel(x, y);
            stats[unit].0 += 1;
            stats[unit].1 += dzdx * dzdx + dzdy * dzdy;
            stats[unit].2 += w_map.get(wc as usize, wr as usize) as f64;
        }
    }
    assert!(
        stats.iter().all(|s| s.0 > 1000),
        "both units present: {stats:?}"
    );
    let rms_slope = |u: usize| (stats[u].1 / stats[u].0 as f64).sqrt();
    let mean_w = |u: usize| stats[u].2 / stats[u].0 as f64;
    // Craters that predate the flood, per km² of each unit (the catalogue includes a margin: count inside only).
    let craters: Vec<Value> = serde_json::from_str(
        &std::fs::read_to_string(demo_world().join("truth/craters.json")).unwrap(),
    )
    .unwrap();
    let flood = config.terrain.mare_flood_age;
    let mut old = [0usize; 2];
    for c in &craters {
        let (x, y) = (c["x_m"].as_f64().unwrap(), c["y_m"].as_f64().unwrap());
        let (col, row) = dem.transform.map_to_pixel(x, y);
        let inside = col >= 0.0 && row >= 0.0 && col < dem.width as f64 && row < dem.height as f64;
        if !inside || c["age"].as_f64().unwrap() <= flood {
            continue;
        }
        match units.highland(x, y) {
            h if h < 0.05 => old[0] += 1,
            h if h > 0.95 => old[1] += 1,
            _ => {}
        }
    }
    let density = |u: usize| old[u] as f64 / stats[u].0 as f64;
    println!(
        "mare vs highland: RMS slope {:.3} vs {:.3}, mean w {:.3} vs {:.3}, pre-flood craters per sampled cell \
         {:.2e} vs {:.2e}",
        rms_slope(0),
        rms_slope(1),
        mean_w(0),
        mean_w(1),
        density(0),
        density(1)
    );
    assert!(mean_w(0) < 0.85 * mean_w(1));
    assert!(rms_slope(0) < 0.8 * rms_slope(1));
    assert!(density(0) < 0.1 * density(1));
}

/// R² of an ordinary least-squares fit with three regressors (normal equations, Cramer's rule).
/// `truth/w_morphology.tif` is the true albedo without its independent component and nothing else: where neither is
/// clamped, w / w_morphology = 1 + v·noise with |noise| ≤ 1 (v = the configured `independent_variation`), and the
/// component is really there (its RMS is not negligible against v).
#[test]
fn the_morphology_albedo_differs_from_the_true_one_by_the_independent_component_only() {
    let world = world_json();
    let v = world["config"]["reflectance"]["independent_variation"]
        .as_f64()
        .unwrap();
    let w = read_raster(&demo_world().join("truth/hapke_params.tif")).unwrap();
    let morphology = read_raster(&demo_world().join("truth/w_morphology.tif")).unwrap();
    assert_eq!(
        (w.width, w.height, w.transform),
        (morphology.width, morphology.height, morphology.transform)
    );
    let unclamped = |x: f32| x > 0.02 && x < 0.95;
    let (mut n, mut sum_sq, mut worst) = (0usize, 0f64, 0f64);
    for (&a, &m) in w.data.iter().zip(&morphology.data).step_by(7) {
        if !(unclamped(a) && unclamped(m)) {
            continue;
        }
        let deviation = a as f64 / m as f64 - 1.0;
        n += 1;
        sum_sq += deviation * deviation;
        worst = worst.max(deviation.abs());
    }
    let rms = (sum_sq / n.max(1) as f64).sqrt();
    eprintln!("w / w_morphology − 1 over {n} cells: RMS {rms:.4}, max {worst:.4} (v = {v})");
    assert!(n > 100_000, "{n} unclamped cells");
    // f32 storage rounds each map to ~6e-8 relative.
    assert!(worst <= v + 1e-6, "max {worst} > v {v}");
    assert!(rms >= v / 10.0, "RMS {rms} against v {v}");
}

fn r_squared(rows: &[([f64; 3], f64)]) -> f64 {
    let mut a = [[0.0; 3]; 3];
    let mut b = [0.0; 3];
    for (x, y) in rows {
        for i in 0..3 {
            b[i] += x[i] * y;
            for j in 0..3 {
                a[i][j] += x[i] * x[j];
            }
        }
    }
    let det = |m: &[[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det(&a);
    let beta: Vec<f64> = (0..3)
        .map(|k| {
            let mut m = a;
            for i in 0..3 {
                m[i][k] = b[i];
            }
            det(&m) / d
        })
        .collect();
    let mean = rows.iter().map(|r| r.1).sum::<f64>() / rows.len() as f64;
    let (mut ss_res, mut ss_tot) = (0.0, 0.0);
    for (x, y) in rows {
        let pred: f64 = (0..3).map(|i| beta[i] * x[i]).sum();
        ss_res += (y - pred).powi(2);
        ss_tot += (y - mean).powi(2);
    }
    1.0 - ss_res / ss_tot
}

#[test]
fn geotiffs_carry_lunar_crs_geotransform_and_nodata() {
    let world = world_json();
    let dem = Dataset::open(demo_world().join("dem/dem.tif")).unwrap();
    let g = &world["dem_grid"];
    let expected = [
        g["min_x"].as_f64().unwrap(),
        5.0,
        0.0,
        g["max_y"].as_f64().unwrap(),
        0.0,
        -5.0,
    ];
    assert_eq!(dem.geo_transform().unwrap(), expected);
    let srs = dem.spatial_ref().unwrap();
    assert_eq!(srs.semi_major().unwrap(), 1_737_400.0);
    assert_eq!(
        srs.semi_minor().unwrap(),
        1_737_400.0,
        "a sphere, not an ellipsoid"
    );
    assert!(srs.is_projected());
    let band = dem.rasterband(1).unwrap();
    assert_eq!(band.no_data_value(), Some(-32768.0));
    use gdal::Metadata;
    assert!(band.description().unwrap().contains("height_m"));
    // The delivered DEM has its nodata holes, written as the nodata value GDAL reports.
    let raster = read_raster(&demo_world().join("dem/dem.tif")).unwrap();
    assert!(
        raster.data.iter().any(|v| v.is_nan()),
        "DEM holes should read back as nodata"
    );

    for ortho in world["orthos"].as_array().unwrap().iter().take(3) {
        let id = ortho["ortho_id"].as_str().unwrap();
        let ds = Dataset::open(demo_world().join(format!("ortho/{id}.tif"))).unwrap();
        let gt = ds.geo_transform().unwrap();
        assert_eq!((gt[1], gt[5]), (2.0, -2.0));
        // Ortho pixel edges line up with the scene grid (pixel-centre convention shared by every raster).
        assert!(
            ((gt[0] - expected[0]) / 2.0).fract().abs() < 1e-9
                && ((gt[3] - expected[3]) / 2.0).fract().abs() < 1e-9
        );
        assert_eq!(ds.spatial_ref().unwrap().semi_major().unwrap(), 1_737_400.0);
        let band = ds.rasterband(1).unwrap();
        assert_eq!(band.no_data_value(), Some(-1.0));
        let values = read_raster(&demo_world().join(format!("ortho/{id}.tif"))).unwrap();
        let nodata = values.data.iter().filter(|v| v.is_nan()).count();
        assert!(
            nodata > 0 && nodata < values.data.len() / 2,
            "{id}: irregular strip border gives some, not most, nodata ({nodata})"
        );
        assert!(
            values.get(0, 0).is_nan(),
            "{id}: the bounding-box corner lies outside the strip"
        );
    }
    let truth = Dataset::open(demo_world().join("truth/hapke_params.tif")).unwrap();
    assert_eq!(truth.raster_count(), 6);
    let names: Vec<String> = (1..=6)
        .map(|i| truth.rasterband(i).unwrap().description().unwrap())
        .collect();
    assert!(
        names[0].starts_with("w ") && names[5].starts_with("theta_bar_deg"),
        "{names:?}"
    );
}

//! Projection of an orthoimage onto DEM crops: for a crop centre on the DEM grid, cut the 130 × 130 DEM (crop +
//! 1-px apron), area-average the ortho into the 128 × 128 crop cells, compute the crop's geometry from the
//! acquisition metadata in its local ENU frame, and take sun-lit fraction and camera visibility from the *full*
//! DEM. Crops that fail the manifest's thresholds are rejected with a counted reason, never silently dropped.
//!
//! Crop convention: centre (c, r) covers DEM columns c−64 … c+63 and rows r−64 … r+63; its centre point is the
//! corner shared by the four middle cells, i.e. the geotransform at (c, r) in pixel-edge coordinates.

use dataset::contract::acquisition::AcquisitionMetadata;
use dataset::contract::catalogue_error::FramedCatalogue;
use dataset::contract::context::ContextSampler;
use dataset::contract::schema::{crop_interior, ContextWindow, Sample, CROP_PX, DEM_PX};
use dataset::science::crs::{CrsError, LocalFrame};
use dataset::science::horizon::{
    visibility_window, HeightField, VisibilityWindow, SUN_ANGULAR_RADIUS_RAD,
};
use dataset::science::raster::Raster;
use dataset::science::resample::{resample_cells, ResampleKernel};

pub use crate::manifest::ProjectParams;

/// Why a crop was not published. Every rejection is counted by reason.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "snake_case")]
pub enum Rejection {
    /// Crop + apron reaches outside the DEM.
    OutsideDem,
    /// A DEM height in crop + apron is nodata.
    DemNodata,
    TooFewValid,
    TooShadowed,
    TooOccluded,
}

/// What all crops of one ortho share: the rasters, metadata, and visibility swept once on the full DEM.
pub struct OrthoProjector<'a> {
    pub dem: &'a Raster,
    pub ortho: Raster,
    pub meta: AcquisitionMetadata,
    sun_visibility: VisibilityWindow,
    camera_visibility: VisibilityWindow,
    provenance: String,
}

impl<'a> OrthoProjector<'a> {
    /// Sweep sun and camera visibility over the DEM around the ortho (one frame at the ortho centre: the sun is
    /// far, and the camera ~50 km away changes direction by only the strip's angular width). `field` is `dem`'s
    /// height field, built once per stage (its relief scan covers the whole DEM).
    pub fn new(
        (dem, field): (&'a Raster, &HeightField<'_>),
        ortho: Raster,
        meta: AcquisitionMetadata,
        params: &ProjectParams,
        provenance: String,
    ) -> Result<Self, CrsError> {
        let (x0, y0) = (ortho.transform.origin_x, ortho.transform.origin_y);
        let (x1, y1) = ortho
            .transform
            .pixel_center(ortho.width as f64 - 0.5, ortho.height as f64 - 0.5);
        let (c0, r0) = dem.transform.map_to_pixel(x0, y0);
        let (c1, r1) = dem.transform.map_to_pixel(x1, y1);
        let cols =
            (c0.floor().max(0.0) as usize)..((c1.ceil() + 1.0).max(0.0) as usize).min(dem.width);
        let rows =
            (r0.floor().max(0.0) as usize)..((r1.ceil() + 1.0).max(0.0) as usize).min(dem.height);
        let (cx, cy) = ((x0 + x1) / 2.0, (y0 + y1) / 2.0);
        let (cc, cr) = dem.transform.map_to_pixel(cx, cy);
        let h = dem.bilinear(cc, cr);
        let frame = LocalFrame::new(&dem.crs, cx, cy, if h.is_finite() { h as f64 } else { 0.0 })?;
        let sun = frame.sun_dir_enu(meta.sun_body());
        let mid = dataset::science::geometry::spacecraft_position_at(
            meta.spacecraft_start_body_m.into(),
            meta.spacecraft_stop_body_m.into(),
            0.5,
        );
        let camera = frame.body_point_to_enu(mid).normalize();
        let sun_visibility = visibility_window(
            field,
            cols.clone(),
            rows.clone(),
            &frame,
            sun,
            SUN_ANGULAR_RADIUS_RAD,
            params.sun_disk_samples,
        );
        let camera_visibility = visibility_window(field, cols, rows, &frame, camera, 0.0, 1);
        Ok(Self {
            dem,
            ortho,
            meta,
            sun_visibility,
            camera_visibility,
            provenance,
        })
    }

    /// Build the sample for the crop centred at DEM (col, row), or say why it is rejected.
    pub fn project(
        &self,
        col: usize,
        row: usize,
        params: &ProjectParams,
    ) -> Result<Sample, Rejection> {
        let (dem, half) = (self.dem, CROP_PX / 2);
        if col < half + 1
            || row < half + 1
            || col + half + 1 > dem.width
            || row + half + 1 > dem.height
        {
            return Err(Rejection::OutsideDem);
        }
        let (apron_c0, apron_r0) = (col - half - 1, row - half - 1);
        let mut dem_m = Vec::with_capacity(DEM_PX * DEM_PX);
        for r in apron_r0..apron_r0 + DEM_PX {
            dem_m.extend_from_slice(
                &dem.data[r * dem.width + apron_c0..r * dem.width + apron_c0 + DEM_PX],
            );
        }
        if dem_m.iter().any(|h| !h.is_finite()) {
            return Err(Rejection::DemNodata);
        }
        let (crop_c0, crop_r0) = (col - half, row - half);
        let (mut image, mut valid) = resample_cells(
            &self.ortho,
            &dem.transform,
            (crop_c0, crop_r0),
            CROP_PX,
            ResampleKernel::Area,
        );
        let mut sun_lit = vec![0f32; CROP_PX * CROP_PX];
        let (mut occluded, mut shadowed) = (0usize, 0usize);
        for j in 0..CROP_PX {
            for i in 0..CROP_PX {
                let k = j * CROP_PX + i;
                // Crop cells are DEM cells: read the swept fields directly, no interpolation needed.
                let (dc, dr) = (crop_c0 + i, crop_r0 + j);
                sun_lit[k] = self.sun_visibility.cell(dc, dr).clamp(0.0, 1.0);
                // Occlusion is about pixels that have an image: one outside the ortho is missing, not occluded.
                if valid[k] != 0 && self.camera_visibility.cell(dc, dr) < 0.5 {
                    occluded += 1;
                    valid[k] = 0;
                }
                if valid[k] == 0 {
                    image[k] = 0.0;
                } else if sun_lit[k] < 0.5 {
                    shadowed += 1;
                }
            }
        }
        let n = (CROP_PX * CROP_PX) as f64;
        let usable = valid.iter().filter(|&&v| v != 0).count();
        if (occluded as f64) / n > params.max_occluded_fraction {
            return Err(Rejection::TooOccluded);
        }
        if (usable as f64) / n < params.min_valid_fraction {
            return Err(Rejection::TooFewValid);
        }
        if shadowed as f64 > params.max_shadowed_fraction * usable as f64 {
            return Err(Rejection::TooShadowed);
        }

        // Geometry in the crop's own ENU frame, from the metadata.
        let (cx, cy) = super::split::crop_centre_m(&dem.transform, col as u32, row as u32);
        let center_h = dem.bilinear(col as f64 - 0.5, row as f64 - 0.5) as f64;
        let frame =
            LocalFrame::new(&dem.crs, cx, cy, center_h).map_err(|_| Rejection::OutsideDem)?;
        let sun_dir = frame.sun_dir_enu(self.meta.sun_body());
        let camera_pos =
            frame.body_point_to_enu(self.meta.spacecraft_for_ground(frame.origin_body));
        let view_dir = camera_pos.normalize();
        let corner = |dc: f64, dr: f64| {
            let (x, y) = dem.transform.pixel_edge(dc, dr);
            frame.map_to_lonlat_deg(x, y)
        };
        let (c0, c1, r0, r1) = (
            crop_c0 as f64,
            (crop_c0 + CROP_PX) as f64,
            crop_r0 as f64,
            (crop_r0 + CROP_PX) as f64,
        );
        let [nw, ne, se, sw] = [
            corner(c0, r0),
            corner(c1, r0),
            corner(c1, r1),
            corner(c0, r1),
        ];
        Ok(Sample {
            sample_id: format!("{}:{col}:{row}", self.meta.ortho_id),
            // The caller places the sample: split and tile come from the assignment table.
            split: dataset::contract::schema::Split::Train,
            tile_id: String::new(),
            ortho_id: self.meta.ortho_id.clone(),
            center_x_m: cx,
            center_y_m: cy,
            center_lon_deg: frame.origin_lon_deg,
            center_lat_deg: frame.origin_lat_deg,
            footprint_lonlat_deg: [nw.0, nw.1, ne.0, ne.1, se.0, se.1, sw.0, sw.1],
            dem_m,
            image,
            valid,
            sun_lit,
            sun_dir_enu: sun_dir.into(),
            camera_pos_enu_m: camera_pos.into(),
            enu_origin_height_m: frame.origin_height_m,
            map_to_en: [
                frame.map_to_en[0][0],
                frame.map_to_en[0][1],
                frame.map_to_en[1][0],
                frame.map_to_en[1][1],
            ],
            camera_att: self.meta.camera_attitude_wxyz,
            fov_deg: self.meta.fov_deg,
            gsd_m: dem.transform.gsd_m(),
            incidence_deg: sun_dir.z.clamp(-1.0, 1.0).acos().to_degrees(),
            emission_deg: view_dir.z.clamp(-1.0, 1.0).acos().to_degrees(),
            phase_deg: sun_dir.dot(view_dir).clamp(-1.0, 1.0).acos().to_degrees(),
            acq_time: self.meta.start_time_utc.clone(),
            provenance: self.provenance.clone(),
            context: None, // cut by `run` from the whole DEM (one `ContextSampler` per stage)
            crater: None, // placed by `run` in the DEM's crater frames, when the manifest names a catalogue
        })
    }
}

/// Where the project stage writes: one sample file per split (row groups of `row_group_rows`, in assignment
/// order, so publish can copy them into shards without decoding), the rejection counts, and the train-split DEM
/// statistic.
pub struct ProjectOutputs<'p> {
    pub split_samples: [&'p std::path::Path; 3],
    pub rejections: &'p std::path::Path,
    pub train_dem: &'p std::path::Path,
}

/// Sum of squared deviations of train crops' heights from each crop's own mean: the dataset's DEM normalisation
/// statistic (std = √(sum / values)), gathered here so that publishing needs no tensor decode.
///
/// Summed per ortho, then the orthos' sums in ortho order: a partitioned build (each partition a run of whole
/// orthos, `crate::partition`) merges its partitions' per-ortho sums into the same bits as one process does.
#[derive(Debug, Default, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TrainDemStatistic {
    pub squared_deviation_sum_m2: f64,
    pub values: u64,
    /// Each ortho's own sum, in the order they were added.
    pub per_ortho: Vec<OrthoDemSum>,
}

/// One ortho's share of [`TrainDemStatistic`].
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct OrthoDemSum {
    pub ortho_id: String,
    pub squared_deviation_sum_m2: f64,
    pub values: u64,
}

impl TrainDemStatistic {
    fn add(&mut self, ortho_id: &str, dem_m: &[f32]) {
        let interior = crop_interior(dem_m);
        let n = (CROP_PX * CROP_PX) as f64;
        let mean = interior.clone().sum::<f64>() / n;
        let deviation: f64 = interior.map(|h| (h - mean) * (h - mean)).sum();
        if self.per_ortho.last().is_none_or(|o| o.ortho_id != ortho_id) {
            self.per_ortho.push(OrthoDemSum {
                ortho_id: ortho_id.to_string(),
                squared_deviation_sum_m2: 0.0,
                values: 0,
            });
        }
        let ortho = self.per_ortho.last_mut().expect("pushed above");
        ortho.squared_deviation_sum_m2 += deviation;
        ortho.values += (CROP_PX * CROP_PX) as u64;
    }

    /// The totals from the per-ortho sums, folded in order.
    fn total(mut self) -> Self {
        self.squared_deviation_sum_m2 = 0.0;
        self.values = 0;
        for ortho in &self.per_ortho {
            self.squared_deviation_sum_m2 += ortho.squared_deviation_sum_m2;
            self.values += ortho.values;
        }
        self
    }

    /// Several statistics (of disjoint, consecutive runs of orthos) as one: what one process would have summed.
    pub fn concat(parts: impl IntoIterator<Item = Self>) -> Self {
        Self {
            per_ortho: parts.into_iter().flat_map(|p| p.per_ortho).collect(),
            ..Default::default()
        }
        .total()
    }

    pub fn std_m(&self) -> f64 {
        if self.values > 0 {
            (self.squared_deviation_sum_m2 / self.values as f64).sqrt()
        } else {
            0.0
        }
    }
}

/// Stage: project every assigned centre, ortho by ortho (sorted), crops in parallel in chunks of one row group,
/// and stream accepted samples into their split's file; rejections are counted per ortho and reason. With
/// `crater_frames` (the catalogue's, or draws of its simulated errors), each sample is placed in its crater's
/// frame; with a `unit_map`, each context window carries its cells' highland fraction.
pub fn run(
    (dem, crater_frames, unit_map): (&Raster, Option<&FramedCatalogue>, Option<&Raster>),
    orthos: &[super::ingest::OrthoRecord],
    assignment_path: &std::path::Path,
    params: &ProjectParams,
    (provenance, row_group_rows): (&str, usize),
    out: &ProjectOutputs,
    progress: &indicatif::ProgressBar,
) -> anyhow::Result<()> {
    use super::split::Split;
    use super::table::{read_table, strings, u32s};
    use rayon::prelude::*;
    use std::collections::BTreeMap;
    let batches = read_table(assignment_path)?;
    let (ids, cols, rows, splits, tiles) = (
        strings(&batches, "ortho_id")?,
        u32s(&batches, "col")?,
        u32s(&batches, "row")?,
        strings(&batches, "split")?,
        strings(&batches, "tile_id")?,
    );
    // Index into `Split::ALL` per position; anything else means the assignment table was not written by split.
    let split_of: Vec<usize> = splits
        .iter()
        .map(|name| {
            Split::ALL
                .iter()
                .position(|s| s.name() == name)
                .ok_or_else(|| {
                    anyhow::anyhow!(
                        "{}: unknown split '{name}'; re-run the split stage",
                        assignment_path.display()
                    )
                })
        })
        .collect::<anyhow::Result<_>>()?;
    progress.set_length(ids.len() as u64);
    let mut rejections: BTreeMap<String, BTreeMap<Rejection, u64>> = BTreeMap::new();
    // Encoding row groups (BYTE_STREAM_SPLIT + zstd) runs on its own thread while rayon projects the next chunk;
    // the channel keeps chunk order, so the files' bytes don't depend on timing. Rendezvous: a chunk is handed
    // over only when the writer takes it. Letting one more chunk (~55 MB) wait measured no faster and, with three
    // split writers buffering partial row groups, took peak RSS past 2 GiB on tycho-full.
    let (send, receive) = std::sync::mpsc::sync_channel::<Vec<(usize, Sample)>>(0);
    let field = &HeightField::new(&dem.data, dem.width, dem.height, dem.transform);
    let context = &ContextSampler::new(dem, params.context_gsd_m);
    let units = &unit_map.map(|map| ContextSampler::new(map, params.context_gsd_m));
    std::thread::scope(|scope| -> anyhow::Result<()> {
        let writer_thread = scope.spawn(move || -> anyhow::Result<TrainDemStatistic> {
            let mut writers = out
                .split_samples
                .iter()
                .map(|path| {
                    Ok(
                        dataset::contract::shard::ShardWriter::create_unhashed(path)?
                            .with_row_group_rows(row_group_rows),
                    )
                })
                .collect::<anyhow::Result<Vec<_>>>()?;
            let mut train_dem = TrainDemStatistic::default();
            for chunk in receive {
                let mut by_split: [Vec<Sample>; 3] = Default::default();
                for (k, sample) in chunk {
                    if Split::ALL[k] == Split::Train {
                        train_dem.add(&sample.ortho_id, &sample.dem_m);
                    }
                    by_split[k].push(sample);
                }
                for (writer, samples) in writers.iter_mut().zip(&by_split) {
                    if !samples.is_empty() {
                        writer.write(samples)?;
                    }
                }
            }
            for writer in writers {
                writer.close()?;
            }
            Ok(train_dem.total())
        });
        // One ortho after another, each with its positions (and their split and tile) in assignment order.
        let wanted: Vec<(&super::ingest::OrthoRecord, Vec<usize>)> = orthos
            .iter()
            .map(|record| {
                let positions = (0..ids.len())
                    .filter(|&i| ids[i] == record.ortho_id)
                    .collect();
                (record, positions)
            })
            .collect();
        // Reading and decoding the next ortho (GDAL) runs on its own thread while rayon projects the current one:
        // serial on the main thread it left the pool idle ~1 s per ortho. Rendezvous channel: at most two orthos
        // are in memory (the one projected, the one read ahead). Building the next projector (its visibility
        // sweeps) ahead as well measured no faster (the stage is CPU-bound) and raised peak RSS by ~0.3 GB.
        let (send_ortho, receive_ortho) =
            std::sync::mpsc::sync_channel::<anyhow::Result<(Raster, AcquisitionMetadata)>>(0);
        let to_read: Vec<&super::ingest::OrthoRecord> = wanted
            .iter()
            .filter(|(_, positions)| !positions.is_empty())
            .map(|(record, _)| *record)
            .collect();
        scope.spawn(move || {
            for record in to_read {
                let loaded = dataset::science::raster::read_raster(&record.image_path)
                    .map_err(anyhow::Error::from)
                    .and_then(|ortho| {
                        Ok((ortho, AcquisitionMetadata::load(&record.metadata_path)?))
                    });
                let failed = loaded.is_err();
                if send_ortho.send(loaded).is_err() || failed {
                    break;
                }
            }
        });
        let projected = (|| -> anyhow::Result<()> {
            for (record, positions) in &wanted {
                let counts = rejections.entry(record.ortho_id.clone()).or_default();
                if positions.is_empty() {
                    continue;
                }
                let (ortho, meta) = receive_ortho
                    .recv()
                    .map_err(|_| anyhow::anyhow!("ortho reader thread stopped early"))??;
                let projector =
                    OrthoProjector::new((dem, field), ortho, meta, params, provenance.to_string())?;
                for chunk in positions.chunks(dataset::contract::shard::ROW_GROUP_ROWS) {
                    let results: Vec<Result<(usize, Sample), Rejection>> = chunk
                        .par_iter()
                        .map(|&i| {
                            let mut sample =
                                projector.project(cols[i] as usize, rows[i] as usize, params)?;
                            sample.context = Some(ContextWindow {
                                gsd_m: params.context_gsd_m,
                                heights_m: context.window(sample.center_x_m, sample.center_y_m),
                                highland: units
                                    .as_ref()
                                    .map(|u| u.window(sample.center_x_m, sample.center_y_m)),
                            });
                            sample.crater = crater_frames.and_then(|frames| {
                                let crop_mean_m = crop_interior(&sample.dem_m).sum::<f64>()
                                    / (CROP_PX * CROP_PX) as f64;
                                frames.position(
                                    &sample.sample_id,
                                    sample.center_x_m,
                                    sample.center_y_m,
                                    crop_mean_m,
                                )
                            });
                            sample.split = Split::ALL[split_of[i]];
                            sample.tile_id = tiles[i].clone();
                            Ok((split_of[i], sample))
                        })
                        .collect();
                    let mut accepted = Vec::with_capacity(results.len());
                    for result in results {
                        match result {
                            Ok(sample) => accepted.push(sample),
                            Err(reason) => *counts.entry(reason).or_default() += 1,
                        }
                    }
                    if send.send(accepted).is_err() {
                        return Ok(()); // the writer failed; its error is reported below
                    }
                    progress.inc(chunk.len() as u64);
                }
            }
            Ok(())
        })();
        drop(receive_ortho); // an early error above must not leave the reader blocked on a send
        drop(send);
        let written = writer_thread
            .join()
            .map_err(|_| anyhow::anyhow!("shard writer thread panicked"))?;
        projected?;
        dataset::files::write_json_atomic(out.train_dem, &written?)?;
        Ok(())
    })?;
    dataset::files::write_json_atomic(out.rejections, &rejections)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use dataset::science::crs::{body_fixed_from_lonlat, LunarCrs};
    use dataset::science::raster::GeoTransform;
    use glam::DVec3;

    const H0: f32 = -1200.0;

    struct Scene {
        dem: Raster,
        ortho: Raster,
        meta: AcquisitionMetadata,
    }

    /// A flat 5 m DEM (2 × 2 km) and a 2 m ortho covering most of it with value = `pattern(x, y)`.
    fn scene(pattern: impl Fn(f64, f64) -> f32) -> Scene {
        let crs = LunarCrs::equirectangular(-43.31, -11.36);
        let (x0, y0) = crs.from_lonlat_deg(-11.36, -43.31).unwrap();
        let (x0, y0) = (
            (x0 / 5.0).round() * 5.0 - 1000.0,
            (y0 / 5.0).round() * 5.0 + 1000.0,
        );
        let dem = Raster::new(
            400,
            400,
            GeoTransform::north_up(x0, y0, 5.0),
            crs.clone(),
            H0,
        );
        let mut ortho = Raster::new(
            900,
            900,
            GeoTransform::north_up(x0 + 100.0, y0 - 100.0, 2.0),
            crs.clone(),
            0.0,
        );
        for r in 0..ortho.height {
            for c in 0..ortho.width {
                let (x, y) = ortho.transform.pixel_center(c as f64, r as f64);
                ortho.data[r * ortho.width + c] = pattern(x, y);
            }
        }
        // Sun 60° from zenith toward east; spacecraft 50 km up, passing north → south over the centre.
        let frame = LocalFrame::new(&crs, x0 + 1000.0, y0 - 1000.0, H0 as f64).unwrap();
        let to_body = |enu: DVec3| frame.enu_to_body_point(enu);
        let sun =
            to_body(DVec3::new(60f64.to_radians().sin(), 0.0, 60f64.to_radians().cos()) * 1.496e11);
        let meta = AcquisitionMetadata {
            ortho_id: "M0000007".into(),
            image_file: "M0000007.tif".into(),
            camera_id: "NAC-L".into(),
            start_time_utc: "2011-05-01T00:00:00.000Z".into(),
            stop_time_utc: "2011-05-01T00:00:02.500Z".into(),
            sun_position_body_m: sun.into(),
            spacecraft_start_body_m: to_body(DVec3::new(0.0, 2000.0, 50_000.0)).into(),
            spacecraft_stop_body_m: to_body(DVec3::new(0.0, -2000.0, 50_000.0)).into(),
            camera_attitude_wxyz: [1.0, 0.0, 0.0, 0.0],
            fov_deg: 2.85,
            pixel_scale_m: 2.0,
            roll_deg: 0.0,
        };
        Scene { dem, ortho, meta }
    }

    impl Scene {
        fn projector(&self, params: &ProjectParams) -> OrthoProjector<'_> {
            let field = HeightField::new(&self.dem.data, 400, 400, self.dem.transform);
            let (ortho, meta) = (self.ortho.clone(), self.meta.clone());
            OrthoProjector::new((&self.dem, &field), ortho, meta, params, "test".into()).unwrap()
        }
    }

    fn params() -> ProjectParams {
        ProjectParams {
            min_valid_fraction: 0.9,
            max_shadowed_fraction: 0.2,
            max_occluded_fraction: 0.01,
            sun_disk_samples: 4,
            context_gsd_m: crate::manifest::DEFAULT_CONTEXT_GSD_M,
            crater_frame_min_diameter_m: dataset::contract::crater_frame::DEFAULT_MIN_DIAMETER_M,
            crater_catalogue_error: None,
        }
    }

    #[test]
    fn analytic_pattern_lands_at_the_right_dem_pixels() {
        let (gx, gy) = (0.001, -0.0004);
        let origin = scene(|_, _| 0.0).dem.transform;
        let ramp = move |x: f64, y: f64| {
            (0.5 + gx * (x - origin.origin_x) + gy * (origin.origin_y - y)) as f32
        };
        let s = scene(ramp);
        let projector = s.projector(&params());
        let (col, row) = (200, 190);
        let sample = projector.project(col, row, &params()).unwrap();
        assert!(sample.valid.iter().all(|&v| v == 1));
        // Independent reference: the box integral of the piecewise-constant ortho over each 5 m cell, by
        // supersampling 10 × 10 points per cell (exactly 4 × 4 per 2 m ortho pixel, so the sum is exact).
        let ortho_at = |x: f64, y: f64| {
            let (c, r) = s.ortho.transform.map_to_pixel(x, y);
            s.ortho
                .get((c + 0.5).floor() as usize, (r + 0.5).floor() as usize) as f64
        };
        let (mut vs_integral, mut vs_centre, mut vs_shifted) = (0f64, 0f64, 0f64);
        for j in 0..CROP_PX {
            for i in 0..CROP_PX {
                let (dc, dr) = ((col - 64 + i) as f64, (row - 64 + j) as f64);
                let (x0, y0) = (origin.origin_x + dc * 5.0, origin.origin_y - dr * 5.0);
                let integral = (0..100)
                    .map(|k| {
                        ortho_at(
                            x0 + 0.25 + 0.5 * (k % 10) as f64,
                            y0 - 0.25 - 0.5 * (k / 10) as f64,
                        )
                    })
                    .sum::<f64>()
                    / 100.0;
                let got = sample.image[j * CROP_PX + i] as f64;
                let (x, y) = s.dem.transform.pixel_center(dc, dr);
                vs_integral = vs_integral.max((got - integral).abs());
                vs_centre = vs_centre.max((got - ramp(x, y) as f64).abs());
                vs_shifted = vs_shifted.max((got - ramp(x + 2.5, y) as f64).abs());
            }
        }
        assert!(
            vs_integral < 1e-6,
            "area average differs from the box integral by {vs_integral}"
        );
        // Box reconstruction of 2 m pixels puts a 5 m cell's centroid ≤ 0.05 px (0.1 m) off its centre: ≤ 1.4e-4
        // here. A half-cell georeferencing shift (2.5 m) would be 2.5e-3: the crop is where it should be.
        assert!(vs_centre < 2e-4, "ramp at cell centres off by {vs_centre}");
        assert!(
            vs_shifted > 2e-3,
            "a half-cell shift must be visible ({vs_shifted})"
        );
        // A bright 10 × 10 m square at known map position lands in exactly 2 × 2 crop cells.
        let bx = origin.origin_x + 5.0 * 190.0; // DEM column 190
        let by = origin.origin_y - 5.0 * 180.0; // DEM row 180
        let s =
            scene(move |x, y| ((x > bx && x < bx + 10.0 && y < by && y > by - 10.0) as u8) as f32);
        let projector = s.projector(&params());
        let sample = projector.project(col, row, &params()).unwrap();
        let lit: Vec<(usize, usize)> = (0..CROP_PX * CROP_PX)
            .filter(|&k| sample.image[k] > 0.0)
            .map(|k| (col - 64 + k % CROP_PX, row - 64 + k / CROP_PX))
            .collect();
        assert_eq!(lit, vec![(190, 180), (191, 180), (190, 181), (191, 181)]);
        assert!(lit
            .iter()
            .all(|&(c, r)| sample.image[(r + 64 - row) * CROP_PX + (c + 64 - col)] == 1.0));
    }

    #[test]
    fn geometry_columns_agree_with_an_independent_computation() {
        let s = scene(|_, _| 0.3);
        let projector = s.projector(&params());
        let (col, row) = (230, 150);
        let sample = projector.project(col, row, &params()).unwrap();
        // Independent route: PROJ for the centre's lon/lat, explicit ENU basis, pushbroom time by bisection.
        let crs = &s.dem.crs;
        let (cx, cy) = (
            s.dem.transform.origin_x + col as f64 * 5.0,
            s.dem.transform.origin_y - row as f64 * 5.0,
        );
        let (lon, lat) = crs.to_lonlat_deg(cx, cy).unwrap();
        let p = body_fixed_from_lonlat(lon, lat, H0 as f64);
        let (sl, cl, sp, cp) = (
            lon.to_radians().sin(),
            lon.to_radians().cos(),
            lat.to_radians().sin(),
            lat.to_radians().cos(),
        );
        let (east, north, up) = (
            DVec3::new(-sl, cl, 0.0),
            DVec3::new(-sp * cl, -sp * sl, cp),
            DVec3::new(cp * cl, cp * sl, sp),
        );
        let enu = |v: DVec3| DVec3::new(v.dot(east), v.dot(north), v.dot(up));
        let sun = enu((DVec3::from(s.meta.sun_position_body_m) - p).normalize());
        let (a, b) = (
            DVec3::from(s.meta.spacecraft_start_body_m),
            DVec3::from(s.meta.spacecraft_stop_body_m),
        );
        // The camera images p when (spacecraft − p) ⟂ velocity: bisect on t.
        let along = |t: f64| {
            (dataset::science::geometry::spacecraft_position_at(a, b, t + 1e-6)
                - dataset::science::geometry::spacecraft_position_at(a, b, t - 1e-6))
            .normalize()
        };
        let f = |t: f64| {
            (dataset::science::geometry::spacecraft_position_at(a, b, t) - p).dot(along(t))
        };
        let (mut lo, mut hi) = (-1.0, 2.0);
        for _ in 0..80 {
            let mid = 0.5 * (lo + hi);
            if f(lo) * f(mid) <= 0.0 {
                hi = mid
            } else {
                lo = mid
            }
        }
        let camera =
            enu(dataset::science::geometry::spacecraft_position_at(a, b, 0.5 * (lo + hi)) - p);
        assert!(
            (DVec3::from(sample.sun_dir_enu) - sun).length() < 1e-9,
            "{:?} vs {sun:?}",
            sample.sun_dir_enu
        );
        assert!(
            (DVec3::from(sample.camera_pos_enu_m) - camera).length() < 1e-3,
            "{:?} vs {camera:?}",
            sample.camera_pos_enu_m
        );
        assert!(
            (sample.incidence_deg - 60.0).abs() < 0.05,
            "flat-scene incidence {}",
            sample.incidence_deg
        );
        assert_eq!((sample.center_lon_deg, sample.center_lat_deg), (lon, lat));
    }

    #[test]
    fn bad_crops_are_rejected_with_a_reason() {
        let mut s = scene(|_, _| 0.3);
        let p = params();
        {
            let projector = s.projector(&p);
            assert_eq!(
                projector.project(10, 200, &p).unwrap_err(),
                Rejection::OutsideDem
            );
            // Centred near the ortho's west edge (ortho starts at DEM column 20): 18 of 128 columns have no image.
            assert_eq!(
                projector.project(66, 200, &p).unwrap_err(),
                Rejection::TooFewValid
            );
        }
        s.dem.data[200 * 400 + 200] = f32::NAN;
        let projector = s.projector(&p);
        assert_eq!(
            projector.project(210, 210, &p).unwrap_err(),
            Rejection::DemNodata
        );
        // A 300 m wall at columns 300–309, sun 30° above the eastern horizon: a 520 m (104-column) shadow westward.
        let mut s = scene(|_, _| 0.3);
        for r in 0..400 {
            for c in 300..310 {
                s.dem.data[r * 400 + c] = H0 + 300.0;
            }
        }
        let projector = s.projector(&p);
        assert_eq!(
            projector.project(250, 200, &p).unwrap_err(),
            Rejection::TooShadowed
        );
    }
}

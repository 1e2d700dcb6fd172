//! Dihedral augmentation (rot90 × flip) applied to a sample's rasters *and* its geometry together.
//!
//! Turning the grid alone would leave the sun and camera where they were, so the rendered image would no longer
//! match the turned photograph (the reference implementation's rotation path had this defect). Here a grid
//! transform `T` (acting on map offsets) comes with the same physical rotation/mirror `Q = T` of the ENU east/north
//! axes: sun and camera vectors become `Q·v`, and the map→ground Jacobian becomes `Q·J·T⁻¹`, so every pixel keeps
//! its ground geometry and `render(augment(s)) = augment(render(s))` (tested against the scalar reference).
//! Caveat: M6's φh is measured from local east, which a rotation moves: that one term is not rotation-invariant.

use dataset::contract::schema::{ContextWindow, Sample, CONTEXT_PX, CROP_PX, DEM_PX};

/// One of the 8 symmetries of the square: `mirror` (east↔west) first, then `quarter_turns` × 90° counter-clockwise.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Dihedral {
    pub quarter_turns: u8,
    pub mirror: bool,
}

impl Dihedral {
    pub const IDENTITY: Dihedral = Dihedral {
        quarter_turns: 0,
        mirror: false,
    };

    pub fn from_index(index: u8) -> Self {
        Self {
            quarter_turns: index % 4,
            mirror: index >= 4,
        }
    }

    /// All 8 symmetries, identity first.
    pub fn all() -> impl Iterator<Item = Self> {
        (0..8).map(Self::from_index)
    }

    /// The symmetry that undoes this one. A mirror followed by turns is a reflection, its own inverse; turns alone
    /// are undone by the remaining turns to a full circle.
    pub fn inverse(self) -> Self {
        if self.mirror {
            self
        } else {
            Self {
                quarter_turns: (4 - self.quarter_turns) % 4,
                mirror: false,
            }
        }
    }

    /// Apply to a square row-major raster of edge `n` (north row first).
    pub fn apply_raster<T: Copy>(self, data: &[T], n: usize) -> Vec<T> {
        assert_eq!(data.len(), n * n);
        let mut out = data.to_vec();
        if self.mirror {
            out = (0..n * n)
                .map(|k| data[(k / n) * n + (n - 1 - k % n)])
                .collect();
        }
        for _ in 0..self.quarter_turns {
            // Counter-clockwise: new[r][c] = old[c][n-1-r].
            let old = out;
            out = (0..n * n)
                .map(|k| old[(k % n) * n + (n - 1 - k / n)])
                .collect();
        }
        out
    }

    /// The 2×2 map (and east/north) transform, row-major `[a, b, c, d]`: (x, y) → (a x + b y, c x + d y).
    pub fn matrix(self) -> [f64; 4] {
        let mut m = if self.mirror {
            [-1.0, 0.0, 0.0, 1.0]
        } else {
            [1.0, 0.0, 0.0, 1.0]
        };
        for _ in 0..self.quarter_turns {
            // (x, y) → (−y, x) applied after m.
            m = [-m[2], -m[3], m[0], m[1]];
        }
        m
    }

    /// Apply to the east/north part of an ENU vector.
    pub fn apply_enu(self, v: [f64; 3]) -> [f64; 3] {
        let m = self.matrix();
        [m[0] * v[0] + m[1] * v[1], m[2] * v[0] + m[3] * v[1], v[2]]
    }

    /// Transform a whole sample: rasters, sun and camera vectors, and the map→ground Jacobian.
    pub fn apply(self, sample: &Sample) -> Sample {
        if self == Self::IDENTITY {
            return sample.clone();
        }
        let q = self.matrix();
        // Q and T are orthogonal with T = Q, so T⁻¹ = Qᵀ and J' = Q·J·Qᵀ.
        let j = sample.map_to_en;
        let qj = [
            q[0] * j[0] + q[1] * j[2],
            q[0] * j[1] + q[1] * j[3],
            q[2] * j[0] + q[3] * j[2],
            q[2] * j[1] + q[3] * j[3],
        ];
        let map_to_en = [
            qj[0] * q[0] + qj[1] * q[1],
            qj[0] * q[2] + qj[1] * q[3],
            qj[2] * q[0] + qj[3] * q[1],
            qj[2] * q[2] + qj[3] * q[3],
        ];
        Sample {
            dem_m: self.apply_raster(&sample.dem_m, DEM_PX),
            image: self.apply_raster(&sample.image, CROP_PX),
            valid: self.apply_raster(&sample.valid, CROP_PX),
            sun_lit: self.apply_raster(&sample.sun_lit, CROP_PX),
            sun_dir_enu: self.apply_enu(sample.sun_dir_enu),
            camera_pos_enu_m: self.apply_enu(sample.camera_pos_enu_m),
            map_to_en,
            // The context window is centred on the crop centre too: the same transform keeps it aligned.
            context: sample.context.as_ref().map(|c| ContextWindow {
                gsd_m: c.gsd_m,
                heights_m: self.apply_raster(&c.heights_m, CONTEXT_PX),
                highland: c
                    .highland
                    .as_ref()
                    .map(|h| self.apply_raster(h, CONTEXT_PX)),
            }),
            ..sample.clone()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quarter_turn_moves_north_row_to_west_column() {
        // 3×3 with values = index; a CCW turn puts the top row (north) on the left column (west), reversed.
        let data: Vec<u8> = (0..9).collect();
        let turned = Dihedral::from_index(1).apply_raster(&data, 3);
        assert_eq!(turned, vec![2, 5, 8, 1, 4, 7, 0, 3, 6]);
        let mirrored = Dihedral::from_index(4).apply_raster(&data, 3);
        assert_eq!(mirrored, vec![2, 1, 0, 5, 4, 3, 8, 7, 6]);
        // A CCW turn sends east (1, 0) to north (0, 1).
        assert_eq!(
            Dihedral::from_index(1).apply_enu([1.0, 0.0, 0.5]),
            [0.0, 1.0, 0.5]
        );
        for i in 0..8 {
            let d = Dihedral::from_index(i);
            let m = d.matrix();
            assert!((m[0] * m[3] - m[1] * m[2]).abs() == 1.0);
            // Four quarter turns (or two mirrors) give the identity on rasters.
            let mut x = data.clone();
            for _ in 0..if d.mirror { 2 } else { 4 } {
                x = d.apply_raster(&x, 3);
            }
            // Every mirrored element of the group is a reflection, hence an involution.
            assert_eq!(x, data, "{d:?}");
        }
    }

    /// Cut the DEM and the context window from one plane z = a·x + b·y (map metres from the crop centre), then
    /// transform: both must still be cut from one plane, so their finite-difference gradients agree.
    #[test]
    fn the_context_window_turns_and_mirrors_with_the_crop() {
        let (a, b, g) = (0.3, -0.7, 512.0);
        let mut sample = crate::testing::synthetic_samples(1, 3).remove(0);
        // DEM pixel (c, r) centre: ((c − 64.5)·5, (64.5 − r)·5); context cell (i, j): ((j − 15.5)·g, (15.5 − i)·g).
        sample.dem_m = (0..DEM_PX * DEM_PX)
            .map(|k| {
                let (c, r) = ((k % DEM_PX) as f64, (k / DEM_PX) as f64);
                (a * (c - 64.5) * 5.0 + b * (64.5 - r) * 5.0) as f32
            })
            .collect();
        sample.context = Some(ContextWindow {
            gsd_m: g,
            heights_m: (0..CONTEXT_PX * CONTEXT_PX)
                .map(|k| {
                    let (j, i) = ((k % CONTEXT_PX) as f64, (k / CONTEXT_PX) as f64);
                    (a * (j - 15.5) * g + b * (15.5 - i) * g) as f32
                })
                .collect(),
            // The unit map's window as the same plane: it must turn as the heights do.
            highland: Some(
                (0..CONTEXT_PX * CONTEXT_PX)
                    .map(|k| {
                        let (j, i) = ((k % CONTEXT_PX) as f64, (k / CONTEXT_PX) as f64);
                        (a * (j - 15.5) * g + b * (15.5 - i) * g) as f32
                    })
                    .collect(),
            ),
        });
        // (east, north) gradient of a row-major north-first raster of cell size `cell`, from two differences.
        let gradient = |z: &[f32], n: usize, cell: f64| {
            let at = |r: usize, c: usize| z[r * n + c] as f64;
            ((at(5, 6) - at(5, 5)) / cell, (at(5, 5) - at(6, 5)) / cell)
        };
        let mut distinct = Vec::new();
        for index in 0..8 {
            let d = Dihedral::from_index(index);
            let turned = d.apply(&sample);
            let dem = gradient(&turned.dem_m, DEM_PX, 5.0);
            let turned_context = turned.context.unwrap();
            let context = gradient(&turned_context.heights_m, CONTEXT_PX, g);
            assert_eq!(turned_context.highland.unwrap(), turned_context.heights_m);
            assert!(
                (dem.0 - context.0).abs() < 1e-4 && (dem.1 - context.1).abs() < 1e-4,
                "{d:?}: DEM gradient {dem:?}, context gradient {context:?}"
            );
            let key = ((dem.0 * 1e3).round() as i64, (dem.1 * 1e3).round() as i64);
            if !distinct.contains(&key) {
                distinct.push(key);
            }
        }
        assert_eq!(
            distinct.len(),
            8,
            "each symmetry moves the plane its own way: {distinct:?}"
        );
    }

    #[test]
    fn inverse_undoes_every_symmetry_on_rasters_and_vectors() {
        let raster: Vec<u32> = (0..25).collect();
        let v = [0.3, -1.7, 0.2];
        for d in Dihedral::all() {
            let back = d.inverse();
            assert_eq!(
                back.apply_raster(&d.apply_raster(&raster, 5), 5),
                raster,
                "{d:?}"
            );
            assert_eq!(
                d.apply_raster(&back.apply_raster(&raster, 5), 5),
                raster,
                "{d:?}"
            );
            assert_eq!(back.apply_enu(d.apply_enu(v)), v, "{d:?}");
        }
        assert_eq!(Dihedral::all().count(), 8);
        assert_eq!(Dihedral::all().next(), Some(Dihedral::IDENTITY));
    }

    #[test]
    fn rendering_a_transformed_sample_equals_transforming_the_rendering() {
        use crate::data::{HostBatch, InputNormalisation};
        use crate::renderer_layer::reference_render;
        use crate::testing::{synthetic_samples, test_params};
        use dataset::science::brdf::BrdfModel;
        let sample = &synthetic_samples(1, 9)[0];
        let npx = CROP_PX * CROP_PX;
        for model in BrdfModel::ALL {
            let mut params = test_params(model, 1, 4);
            if model == BrdfModel::M6 {
                // φh is measured from local east, which a rotation moves (module docs): leave that term out.
                params[2 * npx..3 * npx].iter_mut().for_each(|v| *v = 0.0);
            }
            let plain = reference_render(
                model,
                &HostBatch::from_samples(
                    std::slice::from_ref(sample),
                    &InputNormalisation::relief(1.0),
                ),
                &params,
            );
            let scale = plain.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            for index in 0..8 {
                let d = Dihedral::from_index(index);
                let turned_params: Vec<f64> = params
                    .chunks(npx)
                    .flat_map(|plane| d.apply_raster(plane, CROP_PX))
                    .collect();
                let turned =
                    HostBatch::from_samples(&[d.apply(sample)], &InputNormalisation::relief(1.0));
                let rendered = reference_render(model, &turned, &turned_params);
                let expected = d.apply_raster(&plain, CROP_PX);
                let worst = rendered
                    .iter()
                    .zip(&expected)
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, f64::max);
                assert!(worst <= 1e-12 * scale, "{model:?} {d:?}: {worst:e}");
            }
        }
    }
}

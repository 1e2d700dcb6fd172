//! The lunar science core, in the order a pixel's brightness is built: where it is ([`crs`]), the grid it lives
//! on ([`raster`], [`resample`]), the surface's orientation to sun and camera ([`geometry`]), whether the sun
//! reaches it ([`horizon`]), and how bright it is ([`brdf`], with [`hapke`]'s model in full). Nothing here knows
//! of shards or datasets; the [`crate::contract`] builds on it.

// Where a point is: the lunar sphere, map projections, local east-north-up frames.
pub mod crs;

// The grid it lives on: GeoTIFF IO with the pixel-centre convention.
pub mod raster;

// Moving rasters between grids.
pub mod resample;

// The surface towards sun and camera: normals, cosines, half and difference angles.
pub mod geometry;

// Whether the sun and camera see it: cast shadows, visibility.
pub mod horizon;

// How bright it is: the BRDF models (M1–M6, L2–L4, H1, H3) in f64.
pub mod brdf;

// Hapke's model in full, the reference the BRDF models are measured against, and Lunar-Lambert.
pub mod hapke;

// Fitting a model's coefficients: small linear least squares, unconstrained and non-negative.
pub mod least_squares;

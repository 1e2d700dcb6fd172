//! The parameter maps as a GeoTIFF on the DEM's own grid.

use anyhow::Result;
use dataset::science::brdf::{BRDF_MODEL_KEY, LEAKY_SLOPE};
use dataset::science::raster::{BandOut, BandValues, Raster, RasterLayout};

use super::ParamMaps;

/// Write the maps as a GeoTIFF on the DEM's grid: same CRS and geotransform, NaN nodata, band descriptions naming
/// each parameter's term and stating that the activation is applied.
pub fn write_params_geotiff(
    maps: &ParamMaps,
    dem: &Raster,
    overlap: usize,
    path: &std::path::Path,
) -> Result<()> {
    let descriptions: Vec<String> = maps
        .model
        .term_names()
        .iter()
        .enumerate()
        .map(|(j, term)| format!("p{j}: coefficient of {term} (LeakyReLU({LEAKY_SLOPE}) applied)"))
        .collect();
    let bands: Vec<BandOut> = maps
        .bands
        .iter()
        .zip(&descriptions)
        .map(|(values, description)| BandOut {
            values: BandValues::Grid(values),
            description,
        })
        .collect();
    let layout = RasterLayout {
        width: dem.width,
        height: dem.height,
        transform: dem.transform,
        crs: &dem.crs,
        nodata: f32::NAN,
    };
    dataset::science::raster::write_geotiff(
        path,
        &layout,
        &bands,
        &[
            (BRDF_MODEL_KEY, maps.model.name().to_string()),
            (
                "G2R_ACTIVATION",
                format!("LeakyReLU({LEAKY_SLOPE}) applied; I/F = lit * sum_k p_k * term_k"),
            ),
            ("G2R_OVERLAP_PX", overlap.to_string()),
        ],
    )?;
    Ok(())
}

"""How wrong a many-craters world's delivered unit map is: the share of its 100 m cells whose unit (map/units.tif)
differs from the truth's (truth/terrain_class.tif band 2, the highland fraction, at least one half at the DEM pixel
nearest the cell's centre), over the whole world and over the complex craters' terraced walls (band 1 code 2).

    python docs/scripts/unit_map_error.py WORLD_DIR...

Needs tifffile and imagecodecs (pip install tifffile imagecodecs; the GeoTIFFs use the floating-point predictor).
The map's grid starts at the DEM's corner, its cell an integer number of DEM pixels.
"""
import json
import sys

import numpy as np
import tifffile

for world in sys.argv[1:]:
    manifest = json.load(open(f"{world}/world.json"))
    mapped = tifffile.imread(f"{world}/map/units.tif") == 1.0
    truth = tifffile.imread(f"{world}/truth/terrain_class.tif")
    if truth.shape[0] == 2:
        truth = np.moveaxis(truth, 0, -1)
    step = round(manifest["config"]["unit_map"]["gsd_m"] / manifest["dem_grid"]["gsd_m"])
    rows = np.arange(mapped.shape[0]) * step + step // 2
    cols = np.arange(mapped.shape[1]) * step + step // 2
    rows, cols = rows[rows < truth.shape[0]], cols[cols < truth.shape[1]]
    mapped = mapped[: len(rows), : len(cols)]
    highland = truth[..., 1][np.ix_(rows, cols)] >= 0.5
    wall = truth[..., 0][np.ix_(rows, cols)] == 2
    wrong = highland != mapped
    print(
        f"{world}: {wrong.mean():.3f} of {wrong.size} cells misclassed; "
        f"terraced wall {wrong[wall].mean():.3f} of {wall.sum()}; highland {highland.mean():.3f} true, {mapped.mean():.3f} mapped"
    )

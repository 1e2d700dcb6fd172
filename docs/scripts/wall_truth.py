"""What sets a complex crater's brightness in a many-craters world, from its truth rasters alone: for each crater
(truth/complex_craters.csv), on its melt floor, terraced wall and rim (truth/terrain_class.tif band 1, each DEM pixel
given to the crater it lies fewest radii from), by unit (band 2, the highland fraction, at least one half), the area,
the mean albedo without its independent component (truth/w_morphology.tif, averaged 2 x 2 onto the DEM grid) and
that albedo over the unit's base albedo (the world's w_mare and w_highland mixed by the fraction), beside the
freshness factor the crater's degradation alone would give, 1 + fresh_brightening x (1 - degradation).

    python docs/scripts/wall_truth.py WORLD_DIR...

Needs tifffile and imagecodecs (pip install tifffile imagecodecs). Reads the 2.5 m albedo raster whole: about 3 GiB
of memory a world.
"""
import csv
import json
import math
import sys

import numpy as np
import tifffile

MOON_RADIUS_M = 1_737_400.0
CLASSES = (("melt floor", 1), ("terraced wall", 2), ("rim", 3))


def first_band(raster, bands):
    """Band 0 of a raster read band-interleaved ([bands, rows, cols]) or pixel-interleaved ([rows, cols, bands])."""
    if raster.ndim == 2:
        return raster
    return raster[0] if raster.shape[0] == bands else raster[..., 0]


for world in sys.argv[1:]:
    manifest = json.load(open(f"{world}/world.json"))
    grid, centre = manifest["dem_grid"], manifest["config"]["world"]
    reflectance = manifest["config"]["reflectance"]
    lon0, lat_ts = centre["center_lon_deg"], math.radians(centre["center_lat_deg"])
    terrain = tifffile.imread(f"{world}/truth/terrain_class.tif")
    if terrain.shape[0] == 2:
        ground, highland = terrain[0], terrain[1]
    else:
        ground, highland = terrain[..., 0], terrain[..., 1]
    rows, cols = ground.shape
    albedo = first_band(tifffile.imread(f"{world}/truth/w_morphology.tif"), 1).astype(np.float32)
    albedo = albedo[: 2 * rows, : 2 * cols].reshape(rows, 2, cols, 2).mean(axis=(1, 3))
    x = grid["min_x"] + (np.arange(cols) + 0.5) * grid["gsd_m"]
    y = grid["max_y"] - (np.arange(rows) + 0.5) * grid["gsd_m"]
    craters = []
    for row in csv.DictReader(open(f"{world}/truth/complex_craters.csv")):
        cx = MOON_RADIUS_M * math.radians(float(row["lon_deg"]) - lon0) * math.cos(lat_ts)
        cy = MOON_RADIUS_M * math.radians(float(row["lat_deg"]))
        craters.append((cx, cy, float(row["diameter_m"]), float(row["degradation"])))
    xx, yy = np.meshgrid(x, y)
    nearest = np.stack([np.hypot(xx - cx, yy - cy) / (d / 2) for cx, cy, d, _ in craters]).argmin(0)
    base = reflectance["w_mare"] + (reflectance["w_highland"] - reflectance["w_mare"]) * highland
    pixel_km2 = grid["gsd_m"] ** 2 / 1e6
    print(world)
    for k, (_, _, diameter, degradation) in enumerate(craters):
        fresh = 1 + reflectance["fresh_brightening"] * (1 - degradation)
        for name, code in CLASSES:
            on = (ground == code) & (nearest == k)
            for unit, in_unit in (("highland", highland >= 0.5), ("mare", highland < 0.5)):
                cells = on & in_unit
                n = int(cells.sum())
                if n == 0:
                    continue
                print(
                    f"  crater {k + 1} ({diameter / 1000:.1f} km, degradation {degradation:.2f}) {name}, {unit}: "
                    f"{n * pixel_km2:.2f} km2, albedo {albedo[cells].mean():.3f}, over the unit's base "
                    f"{(albedo[cells] / base[cells]).mean():.3f} (freshness alone {fresh:.3f})"
                )

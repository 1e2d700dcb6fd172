"""The catalogues a test world is scored with beside its exact one (issue 62's perturbed catalogue and negative control).

Reads a synthetic world's exact catalogue (truth/complex_craters.csv) and its grid (world.json), writes two CSVs in
the same columns:

- `perturbed.csv`: every crater's centre moved 300 m (a real catalogue's size of error), in a direction drawn per
  crater, and its diameter scaled by 1.05 or 0.95 (the sign drawn per crater). Fixed sizes, drawn directions: each
  crater is off by exactly the stated amount.
- `phantom.csv`: the exact catalogue plus an 18 km crater the world does not have, centred on the point of the DEM
  (a 500 m grid, 2 km inside its edge) farthest outside every real crater's rim. Its centre lies on ground no real
  crater covers (the clearance is printed and must be positive); on a 40 km world its disc may reach past the DEM's
  edge, and where the real craters crowd, overlap one's outskirts.

Projection: the worlds' equirectangular CRS on the Moon's sphere (R = 1737.4 km, standard parallel lat_ts, central
meridian lon_0, both read from world.json's WKT): x = R cos(lat_ts) (lon - lon_0), y = R lat, angles in radians. On
a many-craters dataset this gives the published center_x / center_y from center_lon / center_lat to within 1e-9 m.

    python3 docs/scripts/catalogue_variants.py WORLD OUT_DIR [SEED]

The seed (default 0) keys the drawn directions and signs; the same world and seed give the same files.
"""
import csv
import json
import math
import re
import sys

import numpy as np

MOON_RADIUS_M = 1737400.0
CENTRE_OFFSET_M = 300.0
DIAMETER_FACTOR = 0.05
PHANTOM_DIAMETER_M = 18000.0
PHANTOM_GRID_M = 500.0


def wkt_parameter(wkt, name):
    found = re.search(r'PARAMETER\["%s",(-?[0-9.eE+-]+)\]' % name, wkt)
    if not found:
        sys.exit(f"world.json: CRS has no {name} parameter: expected the worlds' equirectangular CRS")
    return float(found.group(1))


def main():
    if len(sys.argv) not in (3, 4):
        sys.exit(__doc__)
    world, out = sys.argv[1], sys.argv[2]
    seed = int(sys.argv[3]) if len(sys.argv) == 4 else 0
    meta = json.load(open(f"{world}/world.json"))
    lat_ts = math.radians(wkt_parameter(meta["crs"], "standard_parallel_1"))
    lon_0 = wkt_parameter(meta["crs"], "central_meridian")

    def to_xy(lon, lat):
        return (MOON_RADIUS_M * math.cos(lat_ts) * math.radians(lon - lon_0), MOON_RADIUS_M * math.radians(lat))

    def to_lonlat(x, y):
        return (lon_0 + math.degrees(x / (MOON_RADIUS_M * math.cos(lat_ts))), math.degrees(y / MOON_RADIUS_M))

    with open(f"{world}/truth/complex_craters.csv") as f:
        rows = list(csv.DictReader(f))
    columns = list(rows[0].keys())
    rng = np.random.default_rng([seed, 62])

    perturbed = []
    for row in rows:
        x, y = to_xy(float(row["lon_deg"]), float(row["lat_deg"]))
        azimuth = rng.uniform(0.0, 2.0 * math.pi)
        sign = 1.0 if rng.random() < 0.5 else -1.0
        lon, lat = to_lonlat(x + CENTRE_OFFSET_M * math.cos(azimuth), y + CENTRE_OFFSET_M * math.sin(azimuth))
        moved = dict(row, lon_deg=f"{lon:.9f}", lat_deg=f"{lat:.9f}")
        moved["diameter_m"] = f"{float(row['diameter_m']) * (1.0 + sign * DIAMETER_FACTOR):.3f}"
        perturbed.append(moved)

    grid = meta["dem_grid"]
    min_x, max_y = grid["min_x"], grid["max_y"]
    max_x = min_x + grid["gsd_m"] * grid["width"]
    min_y = max_y - grid["gsd_m"] * grid["height"]
    inset = 2000.0
    real = [(*to_xy(float(r["lon_deg"]), float(r["lat_deg"])), float(r["diameter_m"]) / 2.0) for r in rows]
    best = None
    for x in np.arange(min_x + inset, max_x - inset + 1.0, PHANTOM_GRID_M):
        for y in np.arange(min_y + inset, max_y - inset + 1.0, PHANTOM_GRID_M):
            margin = min(math.hypot(x - cx, y - cy) - cr for cx, cy, cr in real)
            if best is None or margin > best[0]:
                best = (margin, x, y)
    margin, x, y = best
    if margin <= 0.0:
        sys.exit(f"{world}: every point of the DEM lies inside a real crater: no place for a phantom")
    lon, lat = to_lonlat(x, y)
    phantom = rows + [dict({c: "" for c in columns}, lon_deg=f"{lon:.9f}", lat_deg=f"{lat:.9f}",
                           diameter_m=f"{PHANTOM_DIAMETER_M:.3f}", degradation="0", terraces="0")]

    for name, table in (("perturbed.csv", perturbed), ("phantom.csv", phantom)):
        with open(f"{out}/{name}", "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=columns, lineterminator="\n")
            writer.writeheader()
            writer.writerows(table)
    print(f"{out}/perturbed.csv: {len(perturbed)} craters, each moved {CENTRE_OFFSET_M:.0f} m, diameters "
          f"x(1 +/- {DIAMETER_FACTOR})")
    print(f"{out}/phantom.csv: + an {PHANTOM_DIAMETER_M / 1000:.0f} km crater at x {x:.0f} m, y {y:.0f} m "
          f"({lon:.4f}, {lat:.4f}), its centre {margin:.0f} m outside every real rim")


if __name__ == "__main__":
    main()

"""Where a many-craters evaluation's wall and rim error sits, crater by crater: for each `g2r-train eval` output
directory, the crops on a terraced wall or rim grouped by the complex crater they lie nearest to (in its radii) and by
the ground's unit under their centre, with learned / paper-Hapke SSE and the mean level (learned mean brightness over
the ground truth's) of each group. "learned" is the network alone (`learned_network`) where the run keeps a crater
level, so runs with and without one compare.

    python docs/scripts/per_crater_levels.py WORLD_DIR EVAL_DIR...

A crop's place is read from its sample_id (ORTHO:COL:ROW, the crop's corner pixel on the DEM grid of world.json),
which is within a crop's width of its centre: enough to tell craters several kilometres apart.
"""
import csv
import json
import math
import sys

MOON_RADIUS_M = 1_737_400.0

world = sys.argv[1]
manifest = json.load(open(f"{world}/world.json"))
grid, centre = manifest["dem_grid"], manifest["config"]["world"]
lon0, lat_ts = centre["center_lon_deg"], math.radians(centre["center_lat_deg"])
craters = []
for row in csv.DictReader(open(f"{world}/truth/complex_craters.csv")):
    x = MOON_RADIUS_M * math.radians(float(row["lon_deg"]) - lon0) * math.cos(lat_ts)
    y = MOON_RADIUS_M * math.radians(float(row["lat_deg"]))
    craters.append((x, y, float(row["diameter_m"]), float(row["degradation"])))

for evaluation in sys.argv[2:]:
    metrics = json.load(open(f"{evaluation}/metrics.json"))
    groups = {}
    for image in metrics["per_image"]:
        if image["terrain_class"] not in ("terraced_wall", "rim"):
            continue
        key = "learned_network" if "learned_network" in image["metrics"] else "learned"
        _, col, row = image["sample_id"].rsplit(":", 2)
        x = grid["min_x"] + int(col) * grid["gsd_m"]
        y = grid["max_y"] - int(row) * grid["gsd_m"]
        nearest = min(range(len(craters)), key=lambda k: math.hypot(x - craters[k][0], y - craters[k][1]) / craters[k][2])
        unit = "highland" if image["highland"] >= 0.5 else "mare"
        group = groups.setdefault((nearest, image["terrain_class"], unit), [0, 0.0, 0.0, 0.0])
        group[0] += 1
        group[1] += image["metrics"][key]["sse"]
        group[2] += image["metrics"]["hapke_paper"]["sse"]
        group[3] += image["level"][key]
    print(evaluation)
    for (k, ground, unit), (n, learned, hapke, level) in sorted(groups.items()):
        print(
            f"  crater {k + 1} ({craters[k][2] / 1000:.1f} km, degradation {craters[k][3]:.2f}) {ground} {unit}: "
            f"{n} crops, learned / paper-Hapke {learned / hapke:.3f}, level {level / n:.3f}"
        )

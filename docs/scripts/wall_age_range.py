"""Whether a model's terraced walls follow their craters' age: for each (WORLD_DIR, EVAL_DIR) pair, each complex
crater's wall by unit, the truth's albedo over the unit's base (wall_truth.py) against the model's, read as that
factor times the wall's mean level (per_crater_levels.py: learned mean brightness over the truth's; H1 is one scale
on a fixed Hapke shape, so the level is the model's scale over the one the truth's brightness asks for, which grows
a little faster than its albedo). Then, over the groups of at least 10 crops, weighted by crops, the slope of the
model's factor on the truth's (1 when it follows the walls' age across their range), their correlation and means, for
all groups and by unit.

    python docs/scripts/wall_age_range.py WORLD_DIR EVAL_DIR [WORLD_DIR EVAL_DIR ...]

Runs the two scripts beside it (tifffile and imagecodecs for wall_truth.py) and reads their lines.
"""
import os
import re
import subprocess
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
TRUTH_LINE = re.compile(
    r"crater (\d+) \([\d.]+ km, degradation ([\d.]+)\) terraced wall, (\w+): [\d.]+ km2, albedo [\d.]+, "
    r"over the unit's base ([\d.]+)"
)
LEVEL_LINE = re.compile(r"crater (\d+) \([\d.]+ km, degradation [\d.]+\) terraced_wall (\w+): (\d+) crops, .*level ([\d.]+)")
MIN_CROPS = 10


def run(script, *args):
    return subprocess.run(
        [sys.executable, os.path.join(HERE, script), *args], capture_output=True, text=True, check=True
    ).stdout


def fit(groups):
    """Crop-weighted slope of the model's factor on the truth's, correlation, and both means."""
    w = np.array([g["crops"] for g in groups], float)
    t = np.array([g["truth"] for g in groups])
    p = np.array([g["model"] for g in groups])
    tm, pm = np.average(t, weights=w), np.average(p, weights=w)
    cov = np.sum(w * (t - tm) * (p - pm))
    slope = cov / np.sum(w * (t - tm) ** 2)
    r = cov / np.sqrt(np.sum(w * (t - tm) ** 2) * np.sum(w * (p - pm) ** 2))
    return slope, r, tm, pm


pairs = sys.argv[1:]
if len(pairs) < 2 or len(pairs) % 2:
    sys.exit("usage: wall_age_range.py WORLD_DIR EVAL_DIR [WORLD_DIR EVAL_DIR ...]")
groups = []
for world, evaluation in zip(pairs[0::2], pairs[1::2]):
    truth = {(int(m[1]), m[3]): (float(m[2]), float(m[4])) for m in TRUTH_LINE.finditer(run("wall_truth.py", world))}
    for m in LEVEL_LINE.finditer(run("per_crater_levels.py", world, evaluation)):
        key = (int(m[1]), m[2])
        if key not in truth:
            continue
        degradation, factor = truth[key]
        group = dict(world=world, crater=key[0], unit=key[1], degradation=degradation, crops=int(m[3]), truth=factor)
        group["model"] = float(m[4]) * factor
        groups.append(group)
        print(
            f"{world} crater {key[0]} (degradation {degradation:.2f}) wall, {key[1]}: {group['crops']} crops, "
            f"truth {factor:.3f}, model {group['model']:.3f}"
        )
for name in ("all", "highland", "mare"):
    chosen = [g for g in groups if g["crops"] >= MIN_CROPS and (name == "all" or g["unit"] == name)]
    if len(chosen) < 2:
        continue
    slope, r, tm, pm = fit(chosen)
    print(
        f"{name}: {len(chosen)} groups, {sum(g['crops'] for g in chosen)} crops; slope {slope:.3f}, r {r:.3f}; "
        f"mean factor truth {tm:.3f}, model {pm:.3f} (model / truth {pm / tm:.3f})"
    )

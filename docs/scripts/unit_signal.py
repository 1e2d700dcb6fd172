"""Does the delivered DEM carry the geologic unit (mare or highland) under a crop, and on the complex crater's wall?

For every crop of the train and validation splits: its centre, DEM crop and context window (the published shards),
and the truth at its centre (terrain class and highland fraction, the world's truth/terrain_class.tif). Ridge
regressions of the highland fraction on features of the DEM are fitted on train crops and scored on validation
crops, per terrain class: R², and the AUC of highland (fraction ≥ 0.75) against mare (≤ 0.25) crops. One row uses
the truth (the crop's radius in the complex crater) to bound what the DEM's level says once the crop's place on
the crater's profile is known. Two rows use what a crater catalogue gives (the crater's centre and radius, here
from the world's config, as manifests/tycho-full-craters.csv lists them): the crop's height against the crater's
azimuthal median profile, the median DEM height in rings of 0.005 radii out to 3 radii (what the pipeline
publishes as crater_relative_height_m, computed here independently from every DEM pixel).
docs/crater-diagnosis.md quotes the output.

    python3 docs/scripts/unit_signal.py out/tycho-dataset/dataset out/tycho-world

With a second dataset and its world, the regressions fitted on the first's train crops are scored on the second's
validation crops instead: whether what the features say about the unit holds on another world.

    python3 docs/scripts/unit_signal.py out/tycho-dataset/dataset out/tycho-world \
        out/tycho-dataset43/dataset out/tycho-world43

Needs numpy, pyarrow and tifffile (+ imagecodecs for the GeoTIFF's compression). Reads about 70k crops (≈ 1 min).
"""
import glob
import json
import sys

import numpy as np
import pyarrow.parquet as pq
import tifffile

CLASSES = {2: "terraced wall", 3: "rim", 4: "ejecta", 5: "plains"}
LAMBDAS = (1e-3, 1e-2, 1e-1)


def load_truth(world):
    page = tifffile.TiffFile(f"{world}/truth/terrain_class.tif").pages[0]
    grid = page.asarray()
    tie, scale = page.tags["ModelTiepointTag"].value, page.tags["ModelPixelScaleTag"].value
    x0, y0, gsd = tie[3], tie[4], scale[0]

    def at(x, y):
        col = np.clip(((x - x0) / gsd).astype(int), 0, grid.shape[1] - 1)
        row = np.clip(((y0 - y) / gsd).astype(int), 0, grid.shape[0] - 1)
        return grid[row, col, 0].astype(int), grid[row, col, 1]

    meta = json.load(open(f"{world}/world.json"))
    g, w, cc = meta["dem_grid"], meta["config"]["world"], meta["config"]["complex_crater"]
    centre = (
        g["min_x"] + w["width_m"] / 2 + cc["offset_east_m"],
        g["max_y"] - w["height_m"] / 2 + cc["offset_north_m"],
    )
    return at, centre, cc["diameter_m"] / 2


def median_profile(world, centre, radius, step=0.005, reach=3.0):
    """The delivered DEM's median height in rings of `step` radii around the crater, out to `reach` radii, as a
    function of ρ (linear between ring centres, the end rings' heights beyond them)."""
    page = tifffile.TiffFile(f"{world}/dem/dem.tif").pages[0]
    dem = page.asarray().astype(np.float64)
    tie, scale = page.tags["ModelTiepointTag"].value, page.tags["ModelPixelScaleTag"].value
    x = tie[3] + (np.arange(dem.shape[1]) + 0.5) * scale[0]
    y = tie[4] - (np.arange(dem.shape[0]) + 0.5) * scale[0]
    rho = np.hypot(x[None, :] - centre[0], y[:, None] - centre[1]) / radius
    keep = np.isfinite(dem) & (dem > -30000) & (rho < reach)  # GeoTIFF nodata is -32768
    ring, z = (rho[keep] / step).astype(int), dem[keep]
    order = np.argsort(ring, kind="stable")
    ring, z = ring[order], z[order]
    edges = np.searchsorted(ring, np.arange(int(round(reach / step)) + 1))
    medians = np.array([np.median(z[a:b]) if b > a else np.nan for a, b in zip(edges[:-1], edges[1:])])
    centres = (np.arange(len(medians)) + 0.5) * step
    filled = np.isfinite(medians)
    return lambda r: np.interp(np.minimum(r, reach), centres[filled], medians[filled])


def load_split(data, split, truth_at):
    parts = {k: [] for k in ("x", "y", "z", "ctx")}
    for path in sorted(glob.glob(f"{data}/{split}-*.parquet")):
        t = pq.read_table(path, columns=["center_x", "center_y", "dem", "context_dem"])
        dem = t.column("dem").combine_chunks().flatten().to_numpy().reshape(-1, 130, 130)[:, 1:-1, 1:-1]
        ctx = t.column("context_dem").combine_chunks().flatten().to_numpy().reshape(-1, 1024)
        parts["x"].append(t.column("center_x").to_numpy())
        parts["y"].append(t.column("center_y").to_numpy())
        parts["z"].append(np.nanmean(dem, axis=(1, 2)))
        parts["ctx"].append(ctx)
    d = {k: np.concatenate(v) for k, v in parts.items()}
    # Cells off the DEM read as the crop's own height.
    d["ctx"] = np.where(np.isfinite(d["ctx"]), d["ctx"], d["z"][:, None])
    d["cls"], d["highland"] = truth_at(d["x"], d["y"])
    return d


def features(d, kind, centre, radius, profile):
    z = d["z"][:, None]
    rho = np.hypot(d["x"] - centre[0], d["y"] - centre[1]) / radius
    quantiles = np.percentile(d["ctx"], np.arange(0, 101, 5), axis=1).T
    if kind == "crop elevation":
        return z
    if kind == "context quantiles, relative":
        return quantiles - z
    if kind == "context quantiles, absolute + crop elevation":
        return np.hstack([quantiles, z])
    if kind == "context cells, north-up, relative":
        return d["ctx"] - z
    if kind == "crop height against the crater's median profile (catalogue)":
        return z - profile(rho)[:, None]
    if kind == "the same + crop elevation":
        return np.hstack([z - profile(rho)[:, None], z])
    if kind == "crop elevation + true radius (truth)":
        basis = np.stack([np.exp(-(((rho - c) / 0.03) ** 2)) for c in np.linspace(0.3, 1.6, 60)], axis=1)
        return np.hstack([basis, z])
    raise ValueError(kind)


KINDS = (
    "crop elevation",
    "context quantiles, relative",
    "context quantiles, absolute + crop elevation",
    "context cells, north-up, relative",
    "crop height against the crater's median profile (catalogue)",
    "the same + crop elevation",
    "crop elevation + true radius (truth)",
)


def ridge(x_train, y_train, x_test, lam):
    mu, sd = x_train.mean(0), x_train.std(0) + 1e-9
    a, b = (x_train - mu) / sd, (x_test - mu) / sd
    w = np.linalg.solve(a.T @ a + lam * len(a) * np.eye(a.shape[1]), a.T @ (y_train - y_train.mean()))
    return b @ w + y_train.mean()


def auc(score, highland):
    pos, neg = score[highland >= 0.75], score[highland <= 0.25]
    if len(pos) == 0 or len(neg) == 0:
        return float("nan")
    ranks = np.argsort(np.argsort(np.concatenate([pos, neg]))) + 1
    return (ranks[: len(pos)].sum() - len(pos) * (len(pos) + 1) / 2) / (len(pos) * len(neg))


def main(data, world, score_data, score_world):
    truth_at, centre, radius = load_truth(world)
    score_truth_at, score_centre, score_radius = load_truth(score_world)
    train, val = load_split(data, "train", truth_at), load_split(score_data, "val", score_truth_at)
    profile, score_profile = median_profile(world, centre, radius), median_profile(score_world, score_centre, score_radius)
    print(f"train crops {len(train['x'])} ({data}), validation crops {len(val['x'])} ({score_data})")
    print("| ground | features | λ | R² (val) | AUC highland vs mare (val) |")
    print("|---|---|---|---|---|")
    for cls, name in CLASSES.items():
        in_train, in_val = train["cls"] == cls, val["cls"] == cls
        y = val["highland"][in_val]
        for kind in KINDS:
            x_train = features(train, kind, centre, radius, profile)[in_train]
            x_val = features(val, kind, score_centre, score_radius, score_profile)[in_val]
            # λ chosen on validation R²: this measures how much the features can carry, not a model to ship.
            best = None
            for lam in LAMBDAS:
                p = ridge(x_train, train["highland"][in_train], x_val, lam)
                r2 = 1 - ((p - y) ** 2).mean() / y.var()
                if best is None or r2 > best[1]:
                    best = (lam, r2, auc(p, y))
            label = f"{name} ({in_train.sum()} / {in_val.sum()})"
            print(f"| {label} | {kind} | {best[0]:g} | {best[1]:.3f} | {best[2]:.3f} |")


if __name__ == "__main__":
    if len(sys.argv) not in (3, 5):
        sys.exit(
            "usage: unit_signal.py DATASET_DIR WORLD_DIR [SCORE_DATASET_DIR SCORE_WORLD_DIR] "
            "(e.g. out/tycho-dataset/dataset out/tycho-world)"
        )
    args = sys.argv[1:]
    # Without a second pair, score on the first dataset's own validation crops.
    main(*(args * 2 if len(args) == 2 else args))

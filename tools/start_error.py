"""The refracted start's error, intersected as today (least squares in distance) and robustly
(`snell.robust_closest_points`: angular weights, Cauchy), against the synthetic dataset's ground truth.

`python -m tools.start_error DATA`: DATA's cached tracks (triangulated once, minutes) through its true water.
Prints one Markdown table: per intersection and per depth third, the wet points, their vertical error
against the true bed under them (median, p95 of its size, share within 1 % of the maximum depth), and the
TIN of the points as the reference row grids it (F1 at 1 / 3 % of depth, wet cover); beside them the
robust intersection with its worst-spread tracks left out (`--drop Q`: the top Q of the spread, default
0.1)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def intersections(root: Path, fingerprint: str, cameras: dict, water, drop: float) -> dict[str, np.ndarray]:
    """{name: [P', 3] wet points} of the dataset's tracks intersected through `water` each way."""
    from ragsplat.dataset.colmap import STAMP, TRACKS, triangulated_points
    from ragsplat.snell import closest_points, robust_closest_points, water_rays

    pts = np.load(triangulated_points(root, fingerprint))
    obs = np.load(Path(root) / TRACKS)
    names = json.loads((Path(root) / STAMP).read_text())["images"]
    point, image = obs[:, 0].astype(np.int64), obs[:, 1].astype(np.int64)
    origins, dirs = np.zeros((len(obs), 3)), np.zeros((len(obs), 3))
    for k, name in enumerate(names):
        rows = image == k
        origins[rows], dirs[rows] = water_rays(cameras[name], obs[rows, 2:], water)
    wet = water.depth(pts[:, :3]) > 0
    use = wet[point] & np.isfinite(origins).all(1)
    plain = closest_points(origins[use], dirs[use], point[use], len(pts))[wet]
    robust, spread = robust_closest_points(origins[use], dirs[use], point[use], len(pts))
    robust, spread = robust[wet], spread[wet]
    keep = np.isfinite(spread) & (spread <= np.nanquantile(spread, 1 - drop))
    return {"least squares (today)": plain, "robust": robust,
            f"robust, worst {drop:.0%} dropped": robust[keep]}


def main(argv: list[str] | None = None) -> None:
    from scipy.interpolate import LinearNDInterpolator

    from ragsplat.dataset.load import load_dataset
    from ragsplat.eval.evaluate import score_grid
    from ragsplat.eval.references import gridded

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--drop", type=float, default=0.1)
    args = ap.parse_args(argv)
    ds = load_dataset(args.data, splits=("train",), ground_truth=True)
    truth = ds.ground_truth
    gt = truth.grid
    bed = LinearNDInterpolator(gt[:, :2], gt[:, 2])
    good = 0.01 * truth.max_depth
    thirds = np.linspace(0, truth.max_depth, 4)
    print(f"{args.data}: max depth {truth.max_depth:.2f} m, 1 % of it {100 * good:.1f} cm")
    print("| start | depth third | wet points | median error | p95 of the error's size | within 1 % "
          "| TIN F1@1% / F1@3% | TIN wet cover |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    clouds = intersections(ds.root, ds.fingerprint, {v.file_path: v.camera for v in ds.train}, ds.water,
                           args.drop)
    for name, cloud in clouds.items():
        cloud = cloud[np.isfinite(cloud).all(1)]
        true_z = bed(cloud[:, :2])
        depth = ds.water.height(cloud[:, :2]) - true_z
        inside = np.isfinite(true_z) & (depth > 0)
        err, depth = cloud[inside, 2] - true_z[inside], depth[inside]
        s = score_grid(gridded(cloud, truth.nodes), truth)
        f1, cover = (100 * s["f1"]["1%"], 100 * s["f1"]["3%"]), 100 * s["survey"]["wet"]["cover"]
        for k in range(3):
            sel = (depth >= thirds[k]) & (depth < thirds[k + 1] if k < 2 else depth >= thirds[k])
            e = err[sel]
            row = (f"{len(e)} | {100 * np.median(e):+.1f} cm | {100 * np.quantile(np.abs(e), 0.95):.1f} cm | "
                   f"{100 * np.mean(np.abs(e) <= good):.1f} %") if len(e) else "0 | | | "
            tail = f"{f1[0]:.1f} / {f1[1]:.1f} | {cover:.1f} %" if k == 0 else " | "
            print(f"| {name if k == 0 else ''} | {thirds[k]:.2f}-{thirds[k + 1]:.2f} m | {row} | {tail} |")


if __name__ == "__main__":
    main()

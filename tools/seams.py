"""A tiled survey's DEM error by distance to the nearest border between two tiles' cores.

    python -m tools.seams RUN --truth DATA [--bands 0 1 2 5 10]

RUN is a finished `ragsplat survey --out RUN` that was split into tiles (RUN/tiles.json, RUN/dem.tif); DATA
the synthetic dataset whose ground truth scores it (`ragsplat score`'s reading of the DEM: the truth's cells).
Each wet cell's distance is to the nearest finite edge of the core that holds it (an edge open to the survey's
outside is no seam). Prints one row per distance band: cells, bias, RMSE, p95 of |dz| and the shares within 1
% and 3 % of the maximum depth and within 5 cm. A band of worse cells at the seams shows as a first row worse
than the others.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
from pathlib import Path

import numpy as np

from ragsplat.eval.evaluate import height_error
from ragsplat.eval.score_file import score_file
from ragsplat.survey.tiles import inside


def border_distance(xy: np.ndarray, cores: list[list[float | None]]) -> np.ndarray:
    """[N] metres from each point [N, 2] to the nearest finite edge of the core holding it (inf: no core
    holds it or its core has no finite edge). `cores`: tiles.json's [xmin, ymin, xmax, ymax], None open."""
    out = np.full(len(xy), np.inf)
    for core in cores:
        box = [(-math.inf if e < 2 else math.inf) if v is None else v for e, v in enumerate(core)]
        mine = inside(xy, box)  # the merge's own ownership rule
        lo, hi = np.array(box[:2]), np.array(box[2:])
        gaps = np.concatenate([xy[mine] - lo, hi - xy[mine]], axis=1)  # [M, 4], inf at an open edge
        out[mine] = gaps.min(axis=1)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.seams", description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--truth", type=Path, required=True)
    ap.add_argument("--bands", type=float, nargs="+", default=[0.0, 1.0, 2.0, 5.0, 10.0],
                    help="lower edges of the distance bands (m)")
    args = ap.parse_args(argv)
    tiles = json.loads((args.run / "tiles.json").read_text())
    cores = [t["core"] for t in tiles["tiles"]]
    offset = np.asarray(tiles.get("offset", [0.0, 0.0])[:2], np.float64)  # the planning frame's origin
    _, grid, truth, _ = score_file(args.run / "dem.tif", args.truth)
    dz, depth = height_error(grid, truth)
    wet = depth > 0
    dist = border_distance(grid[wet, :2] - offset, cores)
    dz, depth = dz[wet], depth[wet]
    top = truth.max_depth
    print("| distance to a seam (m) | wet cells | bias (cm) | RMSE (cm) | p95 (cm) | within 1 % of "
          f"{top:.2f} m | within 3 % | within 5 cm |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    edges = list(args.bands) + [math.inf]
    for lo, hi in itertools.pairwise(edges):
        e = dz[(dist >= lo) & (dist < hi)]
        if not len(e):
            continue
        a = np.abs(e)
        print(f"| {lo:g}-{hi:g} | {len(e)} | {100 * e.mean():+.1f} | {100 * np.sqrt((e**2).mean()):.1f} |"
              f" {100 * np.quantile(a, 0.95):.1f} | {100 * (a < 0.01 * top).mean():.1f} |"
              f" {100 * (a < 0.03 * top).mean():.1f} | {100 * (a < 0.05).mean():.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

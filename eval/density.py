"""Where the method gains over the tracks: the wet cells of a DEM and of the refracted tracks' TIN, binned by how
many refracted tracks lie near each cell, with the error of each in every bin.

`python -m eval.density DEM.tif DATA [RADIUS]`: the DEM (`ragsplat export` / `ragsplat survey`) of a run on the
synthetic dataset DATA, against DATA's ground truth; RADIUS (metres, default 0.5) is the disc the tracks are
counted in. Prints one Markdown table."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

BINS = ((0, 0), (1, 2), (3, 5), (6, 10), (11, 10**9))  # tracks within the radius


def by_density(dem: Path, data: Path, radius: float = 0.5) -> list[dict]:
    """[{"tracks": (lo, hi), "cells", "dem": {...}, "tin": {...}}] per bin of `BINS`: the wet ground-truth
    cells, the |dz| median and 95th percentile and the bias (cm) of the DEM and of the refracted tracks'
    TIN there (a cell either leaves out counts as not covered)."""
    from scipy.spatial import cKDTree

    from eval.ablation import TrainEval
    from eval.references import track_grids
    from eval.score import dem_points
    from ragsplat_core.dataset.colmap import refracted_points
    from ragsplat_core.dataset.layout import GT_GRID_STEP
    from ragsplat_core.tracks import track_filter

    runner = TrainEval(data)
    ds, truth = runner.ds, runner.truth
    cams = {v.file_path: v.camera for v in ds.train}
    tracks = refracted_points(ds.root, ds.fingerprint, cams, ds.water)[:, :3]
    tracks = tracks[track_filter(tracks)]
    gt = truth.grid  # [G, 3] the wet nodes
    count = np.array([len(n) for n in cKDTree(tracks[:, :2]).query_ball_point(gt[:, :2], radius)])
    tin = track_grids(ds.root, ds.fingerprint, cams, ds.water, gt[:, :2])["triangulation (refracted)"]

    def heights(points):  # the predicted height at each GT node, NaN where none
        d, i = cKDTree(points[:, :2]).query(gt[:, :2], distance_upper_bound=0.5 * GT_GRID_STEP)  # as score_grid
        z = np.full(len(gt), np.nan)
        z[np.isfinite(d)] = points[i[np.isfinite(d)], 2]
        return z

    z = {"dem": heights(dem_points(dem, ds.georef)), "tin": heights(tin)}
    out = []
    for lo, hi in BINS:
        cells = (count >= lo) & (count <= hi)
        row = {"tracks": (lo, hi), "cells": int(cells.sum())}
        for name, zp in z.items():
            dz = (zp - gt[:, 2])[cells]
            ok = np.isfinite(dz)
            row[name] = {"cover": float(ok.mean()) if cells.any() else None,
                         "median_cm": float(np.median(np.abs(dz[ok])) * 100) if ok.any() else None,
                         "p95_cm": float(np.percentile(np.abs(dz[ok]), 95) * 100) if ok.any() else None,
                         "bias_cm": float(dz[ok].mean() * 100) if ok.any() else None}
        out.append(row)
    return out


def table(rows: list[dict], radius: float) -> str:
    def fmt(v, f="{:.1f}"):
        return "-" if v is None else f.format(v)

    head = (f"| tracks within {radius:g} m | wet cells | DEM cover | DEM abs(dz) median / p95 (cm) | DEM bias (cm) | "
            "TIN cover | TIN abs(dz) median / p95 (cm) | TIN bias (cm) |")
    lines = [head, "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lo, hi = r["tracks"]
        band = f"{lo}" if lo == hi else (f"{lo}+" if hi > 10**6 else f"{lo}-{hi}")
        cells = [band, str(r["cells"])]
        for name in ("dem", "tin"):
            m = r[name]
            cells += [fmt(None if m["cover"] is None else 100 * m["cover"], "{:.0f} %"),
                      f"{fmt(m['median_cm'])} / {fmt(m['p95_cm'])}", fmt(m["bias_cm"], "{:+.1f}")]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) not in (2, 3):
        print(__doc__, file=sys.stderr)
        return 2
    radius = float(args[2]) if len(args) == 3 else 0.5
    print(table(by_density(Path(args[0]), Path(args[1]), radius), radius))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

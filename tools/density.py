"""Where a DEM gains or loses against the tracks: the wet ground-truth cells binned three ways, with the error
of the DEM and of the refracted tracks' TIN (the best reference row) in every bin:

- `tracks`: refracted tracks within RADIUS of the cell (where a start from the tracks is dense or sparse);
- `views`: training views whose image holds the cell's apparent point (seen through the water);
- `relief`: the true bed above the median of the true bed within 0.3 m (a stone's top; 0 on a flat bed).

`python -m tools.density DEM.tif DATA [RADIUS]`: the DEM (`ragsplat export` / `ragsplat survey`) of a run on
the synthetic dataset DATA, against DATA's ground truth; RADIUS (metres, default 0.5) is the disc the tracks
are counted in. Prints one Markdown table per binning."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from ragsplat.scoring import quantile_with_holes

BINS = {"tracks": ((0, 0), (1, 2), (3, 5), (6, 10), (11, None)),  # counts, both ends included
        "views": ((0, 19), (20, 39), (40, 59), (60, None)),
        "relief": ((None, 1), (1, 3), (3, 6), (6, None))}  # cm, [lo, hi)
RELIEF_RADIUS = 0.3  # metres: wider than the reach's gravel, narrower than its pools
GOOD = 0.03  # metres: the share of cells within it, the 1 % of depth of the reach's F1


def views_seeing(points: np.ndarray, cameras, water) -> np.ndarray:
    """[N] how many of `cameras` have the apparent point (through `water`) of each point [N, 3] inside their
    image and in front of them."""
    from ragsplat.refraction import apparent_points

    pts = torch.as_tensor(points, dtype=torch.float64)
    count = np.zeros(len(points), dtype=np.int64)
    for cam in cameras:
        centre = torch.as_tensor(np.asarray(cam.camera_center, dtype=np.float64))
        uv, z = cam.project(apparent_points(pts, centre, water).numpy())
        count += ((z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0)
                  & (uv[:, 1] < cam.height))
    return count


def relief(points: np.ndarray, radius: float = RELIEF_RADIUS) -> np.ndarray:
    """[N] each point's height above the median height of the points [N, 3] within `radius` (horizontal)."""
    near = cKDTree(points[:, :2]).query_ball_point(points[:, :2], radius)
    return points[:, 2] - np.array([np.median(points[i, 2]) for i in near])


def in_bin(values: np.ndarray, lo, hi, closed: bool) -> np.ndarray:
    """values >= lo and (<= hi if closed else < hi); None: no bound."""
    m = np.ones(len(values), dtype=bool) if lo is None else values >= lo
    if hi is not None:
        m &= (values <= hi) if closed else (values < hi)
    return m


def summary(dz: np.ndarray) -> dict:
    """Cover, share within GOOD, |dz| median and 95th percentile (cm) and bias (cm) of the errors dz [C]
    (NaN: a cell left out). As `ragsplat.eval.evaluate.survey_figures`: a hole counts as a miss in the share
    within GOOD and as beyond every error in the p95 (None when more than about 5 % are holes); the median and
    bias are over the covered cells."""
    ok = np.isfinite(dz)
    e = dz[ok]
    if not ok.any():
        return {"cover": float(ok.mean()) if len(dz) else None, "good": 0.0 if len(dz) else None,
                "median_cm": None, "p95_cm": None, "bias_cm": None}
    p95 = quantile_with_holes(np.abs(e), int((~ok).sum()), 0.95)
    return {"cover": float(ok.mean()), "good": float((np.abs(e) < GOOD).sum() / len(dz)),
            "median_cm": float(np.median(np.abs(e)) * 100), "p95_cm": None if p95 is None else p95 * 100,
            "bias_cm": float(e.mean() * 100)}


def breakdown(dz: dict[str, np.ndarray], keys: dict[str, np.ndarray]) -> dict[str, list[dict]]:
    """{binning: [{"bin": (lo, hi), "cells", NAME: summary} per bin of BINS]} for the errors dz {NAME: [G]} of
    each bed and the covariates keys {binning: [G]}."""
    out = {}
    for key, values in keys.items():
        rows = []
        for lo, hi in BINS[key]:
            cells = in_bin(values, lo, hi, closed=key != "relief")
            rows.append({"bin": (lo, hi), "cells": int(cells.sum()),
                         **{name: summary(e[cells]) for name, e in dz.items()}})
        out[key] = rows
    return out


def by_place(dem: Path, data: Path, radius: float = 0.5) -> dict[str, list[dict]]:
    """`breakdown` of the DEM's and the refracted tracks' TIN's errors at the wet ground-truth nodes."""
    from ragsplat.dataset.colmap import refracted_points
    from ragsplat.dataset.layout import GT_GRID_STEP
    from ragsplat.eval.ablation import TrainEval
    from ragsplat.eval.references import despiked, track_grids
    from ragsplat.eval.score_run import dem_points

    runner = TrainEval(data)
    ds, truth = runner.ds, runner.truth
    cams = {v.file_path: v.camera for v in ds.train}
    tracks = refracted_points(ds.root, ds.fingerprint, cams, ds.water)[:, :3]
    tracks = despiked(tracks)
    gt = truth.grid  # [G, 3] the wet nodes
    tin = track_grids(ds.root, ds.fingerprint, cams, ds.water, gt[:, :2])["triangulation (refracted)"]

    def errors(points):  # predicted - true height at each GT node, NaN where none
        # as score_grid
        d, i = cKDTree(points[:, :2]).query(gt[:, :2], distance_upper_bound=0.5 * GT_GRID_STEP)
        z = np.full(len(gt), np.nan)
        z[np.isfinite(d)] = points[i[np.isfinite(d)], 2]
        return z - gt[:, 2]

    keys = {"tracks": np.array([len(n) for n in cKDTree(tracks[:, :2]).query_ball_point(gt[:, :2], radius)]),
            "views": views_seeing(gt, list(cams.values()), ds.water),
            "relief": 100 * relief(gt)}
    return breakdown({"dem": errors(dem_points(dem, ds.georef)), "tin": errors(tin)}, keys)


def table(rows: list[dict], key: str, radius: float = 0.5) -> str:
    def fmt(v, f="{:.1f}"):
        return "-" if v is None else f.format(v)

    title = {"tracks": f"tracks within {radius:g} m", "views": "views that see it",
             "relief": f"relief over {RELIEF_RADIUS:g} m (cm)"}[key]
    head = (f"| {title} | wet cells | DEM cover | DEM within {GOOD * 100:g} cm | DEM abs(dz) median / p95 "
            f"(cm) | DEM bias (cm) | TIN within {GOOD * 100:g} cm | TIN abs(dz) median / p95 (cm) | TIN bias "
            "(cm) |")
    lines = [head, "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lo, hi = r["bin"]
        band = (f"< {hi}" if lo is None
                else (f"{lo}+" if hi is None else (f"{lo}" if lo == hi else f"{lo}-{hi}")))
        dem, tin = r["dem"], r["tin"]
        cells = [band, str(r["cells"]), fmt(None if dem["cover"] is None else 100 * dem["cover"], "{:.0f} %")]
        for m in (dem, tin):
            cells += [fmt(None if m["good"] is None else 100 * m["good"], "{:.0f} %"),
                      f"{fmt(m['median_cm'])} / {fmt(m['p95_cm'])}", fmt(m["bias_cm"], "{:+.1f}")]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) not in (2, 3):
        print(__doc__, file=sys.stderr)
        return 2
    radius = float(args[2]) if len(args) == 3 else 0.5
    for key, rows in by_place(Path(args[0]), Path(args[1]), radius).items():
        print(table(rows, key, radius) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

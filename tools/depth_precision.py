"""What a flight's geometry allows: the first-order precision of a submerged bed point triangulated through
the water from a dataset's training cameras, at the true bed (the ground truth's wet nodes, a random sample).
Each camera whose image holds the point's apparent position adds J^T J, J the 2 x 3 Jacobian of its pixel
with respect to the true point (the exact refraction, `refraction.apparent_points`, then the pinhole);
sigma_z is the square root of the inverse's z entry, per pixel of image noise on every observation. Photos
trained at a smaller size scale it by the size's ratio (--scale 0.5: 600 px of 1 200).

With --bed, a bed file's error against the truth by how many of the cameras see each wet node (`by_views`):
a survey product's beside the run's own tracks through the water as a TIN, read as `ragsplat score` reads
them (--band and --kind as its).

    python -m tools.depth_precision DATA [--points 500] [--scale 1.0] [--seed 0]
    python -m tools.depth_precision DATA --bed RUN/dem.tif [--band 2 --kind depth]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def _pixels(cam, pc, scale: float = 1.0):
    """(u [N], v [N], inside [N]) of camera-frame points pc [N, 3] (a tensor or an array): the pixel
    coordinates in the image scaled by `scale`, and whether each lies in front of the camera and inside it."""
    u = scale * (cam.fx * pc[:, 0] / pc[:, 2] + cam.cx)
    v = scale * (cam.fy * pc[:, 1] / pc[:, 2] + cam.cy)
    inside = (pc[:, 2] > 0) & (u >= 0) & (u < scale * cam.width) & (v >= 0) & (v < scale * cam.height)
    return u, v, inside


def sigma_z(points: np.ndarray, cams: list, water, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """([N] sigma_z (m per pixel of image noise; inf where fewer than two cameras see it), [N] how many
    cameras see it) of true points [N, 3] under `water` (`WaterSurface`) from `cams` (`camera.Camera`, OpenCV
    w2c), their images scaled by `scale`."""
    import torch

    from ragsplat.refraction import apparent_points

    X = torch.tensor(points, dtype=torch.float64, requires_grad=True)  # [N, 3]
    info, seen = torch.zeros(len(X), 3, 3, dtype=torch.float64), torch.zeros(len(X), dtype=torch.int64)
    for cam in cams:
        R, t = torch.tensor(cam.R, dtype=torch.float64), torch.tensor(cam.t, dtype=torch.float64)
        pc = apparent_points(X, torch.tensor(cam.camera_center), water) @ R.T + t  # [N, 3] camera frame
        u, v, inside = _pixels(cam, pc, scale)
        uv = torch.stack([u, v], -1)  # [N, 2] scaled pixels
        # the points are independent, so the gradient of a pixel coordinate's sum is each point's own row
        J = torch.stack([torch.autograd.grad(uv[:, k].sum(), X, retain_graph=True)[0] for k in (0, 1)], 1)
        inside = inside.detach()
        info[inside] += (J.transpose(1, 2) @ J)[inside]
        seen += inside
    sigma = np.full(len(X), np.inf)
    ok = (seen >= 2).numpy()
    sigma[ok] = torch.linalg.inv(info[ok])[:, 2, 2].sqrt().numpy()
    return sigma, seen.numpy()


def views(points: np.ndarray, cams: list, water) -> np.ndarray:
    """[N] how many of `cams` (`camera.Camera`) hold the apparent position of each true point [N, 3] under
    `water` in their image (`refraction.views_through_water`)."""
    from ragsplat.refraction import views_through_water

    return views_through_water(points, np.array([c.R for c in cams]),
                               np.array([c.camera_center for c in cams]),
                               np.array([[c.fx, c.fy, c.cx, c.cy] for c in cams]),
                               np.array([[c.width, c.height] for c in cams]), water)


def by_views(data: Path, bed: Path, **read) -> dict:
    """{row: [{"views", "nodes", "cover", "bias_m", "rmse_m"} per `refraction.VIEW_BINS`]} of the bed in the
    file `bed` (`eval.score_file.score_file` with `read`) and, for a survey's product, the run's own tracks'
    TIN, on `data`'s wet ground-truth nodes grouped by how many of its training cameras see them (`views`)."""
    from scipy.spatial import cKDTree

    from ragsplat.dataset.load import load_dataset
    from ragsplat.eval.references import SURVEY_TRACKS
    from ragsplat.eval.score_file import score_file
    from ragsplat.refraction import VIEW_BINS

    _, grid, truth, refs = score_file(bed, data, **read)
    rows = {"bed": grid, **({SURVEY_TRACKS: refs[SURVEY_TRACKS]} if SURVEY_TRACKS in refs else {})}
    cams = [v.camera for v in load_dataset(data, splits=("train",), load_dry=False).train]
    wet = truth.grid[truth.water.height(truth.grid[:, :2]) > truth.grid[:, 2]]
    seen = views(wet, cams, truth.water)
    out = {}
    for name, g in rows.items():
        dist, at = cKDTree(g[:, :2]).query(wet[:, :2], distance_upper_bound=1e-3)
        has = np.isfinite(dist)
        dz = np.full(len(wet), np.nan)
        dz[has] = g[at[has], 2] - wet[has, 2]
        out[name] = []
        for lo, hi in VIEW_BINS:
            pick = (seen >= lo) & (seen <= (np.inf if hi is None else hi))
            d = dz[pick][np.isfinite(dz[pick])]
            out[name].append({"views": f"{lo}-{hi}" if hi else f"{lo}+", "nodes": int(pick.sum()),
                              "cover": float(len(d) / max(pick.sum(), 1)),
                              "bias_m": float(d.mean()) if len(d) else None,
                              "rmse_m": float(np.sqrt((d ** 2).mean())) if len(d) else None})
    return out


def precision(data: Path, points: int = 500, scale: float = 1.0, seed: int = 0) -> dict:
    """{"sigma_z_per_px_m": median and p90, "views": median, "depth_m": median, "points", ...} of `sigma_z`
    at `points` wet nodes of `data`'s ground truth seen by at least two of its training cameras."""
    from ragsplat.dataset.load import load_dataset

    ds = load_dataset(data, splits=("train",), load_dry=False, ground_truth=True)
    truth, cams = ds.ground_truth, [v.camera for v in ds.train]
    depth = truth.water.height(truth.grid[:, :2]) - truth.grid[:, 2]
    wet = np.flatnonzero(depth > 0)
    pick = np.random.default_rng(seed).choice(wet, min(points, len(wet)), replace=False)
    sigma, seen = sigma_z(truth.grid[pick], cams, truth.water, scale)
    ok = np.isfinite(sigma)
    s = sigma[ok]
    return {"sigma_z_per_px_m": {"median": float(np.median(s)), "p90": float(np.percentile(s, 90))},
            "views": float(np.median(seen[ok])), "depth_m": float(np.median(depth[pick][ok])),
            "points": int(ok.sum()), "scale": scale, "cameras": len(cams)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("data", type=Path)
    p.add_argument("--points", type=int, default=500)
    p.add_argument("--scale", type=float, default=1.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--bed", type=Path, metavar="FILE", help="a bed file's error by views instead")
    p.add_argument("--band", type=int, default=1, help="with --bed: a DEM's band")
    p.add_argument("--kind", choices=["height", "depth"], default="height", help="with --bed: its values")
    a = p.parse_args(argv)
    if a.bed is not None:
        print("| row | views | wet nodes | cover (%) | bias (cm) | RMSE (cm) |\n|---|---|---|---|---|---|")
        for name, bins in by_views(a.data, a.bed, band=a.band, depth=a.kind == "depth").items():
            for b in bins:
                bias, rmse = (("n/a" if b[k] is None else f"{100 * b[k]:{f}}") for k, f in
                              (("bias_m", "+.1f"), ("rmse_m", ".1f")))
                print(f"| {name} | {b['views']} | {b['nodes']} | {100 * b['cover']:.1f} | {bias} | {rmse} |")
        return 0
    r = precision(a.data, a.points, a.scale, a.seed)
    s = r["sigma_z_per_px_m"]
    print(f"{r['points']} wet points (median depth {r['depth_m']:.2f} m) from {r['cameras']} cameras, median "
          f"{r['views']:.0f} views each, images x {r['scale']:g}: sigma_z {100 * s['median']:.1f} cm per "
          f"pixel of image noise (median; p90 {100 * s['p90']:.1f} cm)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

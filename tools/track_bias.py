"""What a survey's tracks say with everything else exact: each track of RUN/model (the photos' keypoints),
carried to the truth by a similarity of its cameras, triangulated again with the twin's true cameras,
through its true water surface where the track is over the wet bed, and its height compared with the
truth's (gt/bed_grid.npy, gt/bank_grid.npy) at the same place. The cameras, the frame and the level then
take no part: an offset left is in the keypoints (or the render). Printed as JSON: the dry and the
submerged tracks' mean and median height error (m), the submerged ones by true depth.

    python -m tools.track_bias RUN DATA [--tracks 4000]   # DATA: the dataset (or stretch) of the photos
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np

NEAR = 0.03  # m: a track counts where a truth node lies this close to it
WET = 0.1  # m: submerged tracks at least this deep, clear of the waterline's mixed neighbours


def _observations(rec, names, points):
    """(track index [K], camera index [K], keypoints [K, 2]) of the tracks `points` (ids)."""
    index = {n: i for i, n in enumerate(names)}
    track, camera, xy = [], [], []
    for k, pid in enumerate(points):
        for el in rec.points3D[pid].track.elements:
            im = rec.images[el.image_id]
            track.append(k)
            camera.append(index[Path(im.name).stem])
            xy.append(im.points2D[el.point2D_idx].xy)
    return np.array(track), np.array(camera), np.array(xy)


def triangulate(start, track, camera, xy, cams, water, iterations: int = 8):
    """Tracks [T, 3] refined from `start` by Gauss-Newton on their reprojection through `water` (None: in air)
    into the true cameras `cams` (a list, indexed by `camera`). Central differences for the 3 x 3 blocks."""
    import torch

    from ragsplat.refraction import apparent_points_each

    R = torch.tensor(np.array([c.R for c in cams]))[camera]
    t = torch.tensor(np.array([c.t for c in cams]))[camera]
    centre = torch.tensor(np.array([c.camera_center for c in cams]))[camera]
    f = torch.tensor([[c.fx, c.fy] for c in cams])[camera]
    pp = torch.tensor([[c.cx, c.cy] for c in cams])[camera]
    track, uv, X = torch.tensor(track), torch.tensor(xy), torch.tensor(start)

    def residual(X):  # [K, 2] pixels
        P = X[track] if water is None else apparent_points_each(X[track], centre, water)
        pc = (R @ P[:, :, None])[..., 0] + t
        return f * pc[:, :2] / pc[:, 2:] + pp - uv

    for _ in range(iterations):
        r = residual(X)
        steps = 1e-6 * torch.eye(3, dtype=X.dtype)
        J = torch.stack([(residual(X + e) - residual(X - e)) / 2e-6 for e in steps], -1)  # [K, 2, 3]
        Jt = J.transpose(1, 2)
        JtJ = torch.zeros(len(X), 3, 3, dtype=X.dtype).index_add_(0, track, Jt @ J)
        Jtr = torch.zeros(len(X), 3, dtype=X.dtype).index_add_(0, track, (Jt @ r[:, :, None])[..., 0])
        X = X - torch.linalg.solve(JtJ, Jtr)
    return X.numpy()


def track_bias(run: Path, truth: Path, tracks: int = 4000) -> dict:
    import pycolmap
    from scipy.spatial import cKDTree

    from ragsplat.dataset.load import load_dataset
    from ragsplat.eval.score_file import survey_geotags
    from ragsplat.survey.georef import fit_similarity
    from ragsplat.water_surface import WaterSurface

    views = load_dataset(truth, splits=("train",), load_dry=False)
    by_name = {Path(v.file_path).stem: v.camera for v in views.train}
    names = sorted(by_name)
    cams = [by_name[n] for n in names]
    rec = pycolmap.Reconstruction(str(run / "model"))
    # the model carried to the truth by its cameras' similarity: a start and a place for each track
    geotags = survey_geotags(truth)
    offset = np.asarray(geotags.offset) if geotags is not None else np.zeros(3)
    seen = [i for i in rec.reg_image_ids() if Path(rec.images[i].name).stem in by_name]
    fit = fit_similarity(np.array([rec.images[i].projection_center() for i in seen]) - offset,
                         np.array([by_name[Path(rec.images[i].name).stem].camera_center for i in seen]))
    w = json.loads((truth / "scene.json").read_text())["water"]
    water = WaterSurface(w["level"], w["n"], tuple(w.get("slope", (0.0, 0.0))))
    slope = np.asarray(w.get("slope", [0.0, 0.0]), float)
    out = {}
    for kind, grid in (("dry", "bank_grid.npy"), ("submerged", "bed_grid.npy")):
        truth_z = np.load(truth / "gt" / grid)
        tree = cKDTree(truth_z[:, :2])
        ids = [pid for pid, p in rec.points3D.items() if len(p.track.elements) >= 3
               and all(Path(rec.images[el.image_id].name).stem in by_name for el in p.track.elements)]
        start = fit.apply(np.array([rec.points3D[i].xyz for i in ids]) - offset)
        dist, near = tree.query(start[:, :2])
        keep = dist < NEAR
        if kind == "submerged":
            keep &= w["level"] + start[:, :2] @ slope - truth_z[near, 2] > WET
        rows = np.flatnonzero(keep)[:tracks]
        if not len(rows):
            continue
        track, camera, xy = _observations(rec, names, [ids[i] for i in rows])
        X = triangulate(start[rows], track, camera, xy, cams,
                        water if kind == "submerged" else None)
        dist, near = tree.query(X[:, :2])
        ok = dist < NEAR
        err = X[ok, 2] - truth_z[near[ok], 2]
        row = {"tracks": int(ok.sum()), "mean_m": float(err.mean()), "median_m": float(np.median(err))}
        if kind == "submerged":
            depth = w["level"] + X[ok, :2] @ slope - truth_z[near[ok], 2]
            bands = [WET, 0.5, 1.0, 2.0, np.inf]
            row["mean_by_true_depth_m"] = {f"{lo:g}-{hi:g} m": float(err[(depth >= lo) & (depth < hi)].mean())
                                           for lo, hi in itertools.pairwise(bands)
                                           if ((depth >= lo) & (depth < hi)).any()}
        out[kind] = row
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("data", type=Path)
    parser.add_argument("--tracks", type=int, default=4000, help="tracks of each kind (the model's first)")
    args = parser.parse_args()
    print(json.dumps(track_bias(args.run, args.data, args.tracks), indent=1))


if __name__ == "__main__":
    main()

"""Reference answers for Table 2, scored by the same metrics as every variant: what a method must clearly
beat before its numbers mean anything.

- `init`: the initial Gaussians (a horizontal grid at the preset depth, or the start's points), no training,
  through the variants' extraction with every Gaussian counted (`start_extraction`; the trainer builds
  them, see `ragsplat.eval.ablation.TrainEval.initial`);
- `3dgs x n`: the refraction-unaware 3DGS bed with every submerged depth multiplied by n (the field's
  classical correction, the paper's Table 3): `depth_times_n` of the 3dgs variant's extracted grid;
- `oracle plane`: the least-squares tilted plane through the submerged ground truth, over every ground-truth
  cell (wet and banks); `oracle median plane`: a flat plane at the ground truth's median submerged height
  (the second null). Both read the answer, so they are marked as using the ground truth.

What a surveyor would do without ragsplat, from the dataset's own tracks (SIFT matches of the training photos
triangulated with the known poses, `dataset.colmap`), each cleaned by the local outlier filter of a DEM
(`tracks.track_filter`, its settings `TIN_FILTER`) and gridded by linear interpolation on their Delaunay
triangulation (`tracks.tin`):
- `triangulation (refracted)`: the tracks intersected through the water (`colmap.refracted_points`, the
  start the variants train from);
- `triangulation x n`: the straight-ray tracks with their submerged depths x n;
- `dietrich (tracks)`: the straight-ray tracks corrected by Dietrich's (2017) multi-camera rule (`dietrich`,
  its angle filter and reduction `DIETRICH_TRACKS`);
- `dietrich (3dgs)`: the same rule applied to the 3dgs row's dense apparent bed, every training camera that
  sees a cell voting (the dense-cloud workflow).

The water they are given (a `WaterSurface`: the dataset's, or one level, `ragsplat ablation --one-level`) is
read as the field reads a river's: depths below the surface's height above each point (`water.height`, a
sloping plane's too), Dietrich's water surface elevation per point as pyBathySfM takes it, wet where a point
lies below the surface there, the refracted rays bent at its tilted normal (`snell.water_rays`).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from ragsplat.outputs import source_digest
from ragsplat.surface import ExtractConfig
from ragsplat.tracks import tin, track_filter

# This module's source as imported: part of every reference row's key (read once, so that a file edited during
# a long run cannot key a row computed with the settings loaded before the edit)
REFERENCES_CODE = source_digest("eval/references.py")

# In table order: what a surveyor would do without ragsplat first, then the trivial answers. `init` stays in
# results.json but not in the tables (drawn as 3DGS blobs, the start scores near 0 by construction).
REFERENCES = ("triangulation (refracted)", "dietrich (tracks)", "dietrich (3dgs)", "triangulation x n",
              "3dgs x n", "oracle plane", "oracle median plane", "init")
NOT_IN_TABLES = ("init",)
ORACLES = ("oracle plane", "oracle median plane")
SEEDLESS = (*ORACLES, "triangulation (refracted)", "dietrich (tracks)", "triangulation x n")  # no training
USES_GROUND_TRUTH = ORACLES
# A survey run's own tracks, adjusted through the water (`ragsplat score` of a survey's product): the
# refracted triangulation from the photos alone, beside the run's trained bed.
SURVEY_TRACKS = "survey's tracks (refracted)"
# and the field's practice from the same photos: the run's pinhole structure from motion, georeferenced as the
# run is, each depth below the run's water surface times n.
SURVEY_PINHOLE = "survey's pinhole model x n"
# Where each reference's height grid comes from, as the tables label it (no fused variant: 3dgs x n
# corrects the 3dgs row's volume bed, init is the untrained start).
EXTRACTION = {"init": "volume", "3dgs x n": "volume", "oracle plane": "-", "oracle median plane": "-",
              "triangulation (refracted)": "TIN", "triangulation x n": "TIN", "dietrich (tracks)": "TIN",
              "dietrich (3dgs)": "volume", SURVEY_TRACKS: "TIN", SURVEY_PINHOLE: "TIN"}
# The references' own settings, chosen on the development reach by the method's rule (`python -m
# tools.tune_references data/small-dev`; the figures in docs/lab/history.md, "The references' settings"): the
# tracks' outlier filter before the TIN (`tracks.track_filter`), and Dietrich's per-camera angle filter and
# reduction (pyBathySfM's defaults, 35 degrees and the mean, as the starting point).
TIN_FILTER = {"radius": 1.0, "tol": 0.3, "min_neighbours": 8}
DIETRICH_TRACKS = {"max_angle_deg": None, "reduce": "mean"}
# The same rule on the 3dgs row's dense apparent bed (`dietrich_grid`), chosen on the development reach's 3dgs
# bed (`--bed`): the angle filter in degrees and the reduction.
DIETRICH_MAX_ANGLE = 40.0
DIETRICH_DENSE_REDUCE = "median"
REDUCE = {"mean": np.mean, "median": np.median}


def start_extraction(cfg: ExtractConfig) -> ExtractConfig:
    """The extraction of the `init` row: the table's, with no opacity or size cull. Every start has the same
    opacity (`init_opacity`, 0.1) and scales set by the spacing of its points, training choices rather than
    fitted values, so the table's culls would remove most or all of it and score the start near 0 by
    construction."""
    return replace(cfg, min_opacity=0.0, max_scale_gsd=math.inf)


def depth_times_n(grid: np.ndarray, water) -> np.ndarray:
    """[P, 3] heights -> the same cells with every depth below the surface `water` (a `WaterSurface`: its
    height above each cell, a sloping river's too) multiplied by its n (the apparent depth of a nadir view is
    the true depth / n, so an uncorrected reconstruction is scaled back by n)."""
    out = np.array(grid, dtype=np.float64, copy=True)
    height = np.asarray(water.height(out[:, :2]), dtype=np.float64)
    wet = out[:, 2] < height
    out[wet, 2] = height[wet] - float(water.n) * (height[wet] - out[wet, 2])
    return out


def oracle_grids(truth) -> dict[str, np.ndarray]:
    """{name: [P, 3]} the two planes of `ORACLES` over every ground-truth node (submerged bed and banks): the
    least-squares plane z = a + b x + c y through the submerged ground truth, and the flat plane at its median
    height."""
    nodes, wet = truth.nodes, truth.grid
    A = np.column_stack([np.ones(len(wet)), wet[:, :2]])
    coef = np.linalg.lstsq(A, wet[:, 2], rcond=None)[0]
    tilted = np.column_stack([np.ones(len(nodes)), nodes[:, :2]]) @ coef
    flat = np.full(len(nodes), float(np.median(wet[:, 2])))
    return {"oracle plane": np.column_stack([nodes[:, :2], tilted]),
            "oracle median plane": np.column_stack([nodes[:, :2], flat])}


def dietrich(apparent: np.ndarray, centres: np.ndarray, point: np.ndarray, camera: np.ndarray, water,
             max_angle_deg: float | None = None, reduce=np.median) -> np.ndarray:
    """[P, 3] Dietrich's (2017) multi-camera refraction correction of apparent points [P, 3] seen by the
    cameras with centres [C, 3] (observation k: point[k] seen by camera[k]) through `water` (a
    `WaterSurface`). As pyBathySfM, each point takes the water surface elevation above it (its own: the
    sloping surface's height at the point's x, y, where pyBathySfM interpolates the surveyor's edge points).
    Each camera gives the depth h = h_a tan(r) / tan(i) from its own view of the point: h_a its apparent
    depth below that elevation, r the air ray's angle from the vertical, sin(r) = n sin(i) (at nadir h = n
    h_a); the point takes the `reduce` (median, or mean) over its cameras, with `max_angle_deg` leaving out
    cameras that see it more obliquely (the paper's angle filter), and lies at that elevation - h. The point
    keeps its horizontal position (the rule's assumption: the true point lies below the apparent one). Points
    at or above the surface are unchanged; a submerged point with no camera left gets NaN."""
    app = np.asarray(apparent, float)
    out = app.copy()
    n = float(water.n)
    surface = np.asarray(water.height(app[:, :2]), dtype=np.float64)  # [P] the elevation above each point
    ha = surface - app[:, 2]
    wet = ha > 0
    use = wet[point]
    p, c = point[use], camera[use]
    horizontal = np.linalg.norm(app[p, :2] - centres[c, :2], axis=1)
    r = np.arctan2(horizontal, centres[c, 2] - app[p, 2])  # the ray camera -> apparent point, from vertical
    i = np.arcsin(np.sin(r) / n)
    with np.errstate(invalid="ignore", divide="ignore"):
        factor = np.where(r > 1e-9, np.tan(r) / np.tan(i), n)  # tan r / tan i -> n at nadir
    ok = np.ones(len(p), dtype=bool) if max_angle_deg is None else np.degrees(r) <= max_angle_deg
    h = np.full(len(app), np.nan)
    order = np.argsort(p[ok], kind="stable")
    ps, hs = p[ok][order], (ha[p] * factor)[ok][order]
    starts = np.flatnonzero(np.r_[True, ps[1:] != ps[:-1]]) if len(ps) else np.zeros(0, int)
    for a, b in zip(starts, np.r_[starts[1:], len(ps)]):
        h[ps[a]] = reduce(hs[a:b])
    out[wet, 2] = surface[wet] - h[wet]
    return out


def seen_by(points: np.ndarray, cameras) -> tuple[np.ndarray, np.ndarray]:
    """(point [M], camera [M]): every pair of a point [P, 3] and a camera (of `cameras`) whose image holds
    its straight-ray projection, in front of it."""
    pairs = []
    for k, cam in enumerate(cameras):
        uv, z = cam.project(np.asarray(points, float))
        inside = ((z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0)
                  & (uv[:, 1] < cam.height))
        pairs.append(np.column_stack([np.flatnonzero(inside), np.full(inside.sum(), k)]))
    both = np.concatenate(pairs) if pairs else np.zeros((0, 2), int)
    return both[:, 0], both[:, 1]


def track_grids(root, fingerprint: str, cameras: dict, water, nodes: np.ndarray,
                tin_filter: dict | None = TIN_FILTER,
                dietrich_tracks: dict = DIETRICH_TRACKS) -> dict[str, np.ndarray]:
    """{reference name: height grid [G', 3] on `nodes` [G, 2]} for the tracks' references (module docstring)
    of the dataset `root` (its cached triangulation; `cameras`: image name -> Camera), with the outlier filter
    `tin_filter` (`track_filter`'s keywords, or None: none) and Dietrich's `dietrich_tracks` (`max_angle_deg`,
    None: every camera; `reduce`: a name of `REDUCE`). Raises DatasetError when nothing can be
    triangulated."""
    clouds = track_clouds(root, fingerprint, cameras, water, dietrich_tracks)
    return {name: gridded(pts, nodes, tin_filter) for name, pts in clouds.items()}


def despiked(points: np.ndarray, tin_filter: dict | None = TIN_FILTER) -> np.ndarray:
    """[P', 3+] the points [P, 3+] the outlier filter keeps (`track_filter` with `tin_filter`; None: all)."""
    return points if tin_filter is None else points[track_filter(points, **tin_filter)]


def gridded(points: np.ndarray, nodes: np.ndarray, tin_filter: dict | None = TIN_FILTER) -> np.ndarray:
    """[G', 3] a point cloud [P, 3+] as a surveyor grids it: outlier-filtered (`despiked`) and interpolated
    linearly on its Delaunay triangulation at `nodes` [G, 2]."""
    return tin(despiked(points, tin_filter), nodes)


def track_clouds(root, fingerprint: str, cameras: dict, water, dietrich_tracks: dict = DIETRICH_TRACKS
                 ) -> dict[str, np.ndarray]:
    """{reference name: point cloud [P, 3]} of the tracks' references before gridding (`track_grids`)."""
    import json
    from pathlib import Path

    from ragsplat.dataset.colmap import STAMP, TRACKS, refracted_points, triangulated_points

    path = triangulated_points(root, fingerprint)
    straight = np.load(path)[:, :3]
    obs = np.load(Path(root) / TRACKS)
    names = json.loads((Path(root) / STAMP).read_text())["images"]
    centres = np.array([cameras[name].camera_center for name in names])
    corrected = dietrich(straight, centres, obs[:, 0].astype(np.int64), obs[:, 1].astype(np.int64), water,
                         dietrich_tracks["max_angle_deg"], REDUCE[dietrich_tracks["reduce"]])
    return {"triangulation (refracted)": refracted_points(root, fingerprint, cameras, water)[:, :3],
            "dietrich (tracks)": corrected[np.isfinite(corrected).all(1)],
            "triangulation x n": depth_times_n(straight, water)}


def dietrich_grid(bed: np.ndarray, cameras, water, max_angle_deg: float | None = DIETRICH_MAX_ANGLE,
                  reduce: str = DIETRICH_DENSE_REDUCE) -> np.ndarray:
    """[G', 3] Dietrich's correction of a dense apparent bed [G, 3] (the 3dgs row's), every camera whose image
    holds a cell voting, within the angle filter `max_angle_deg` (None: none), by `reduce` (a name of
    `REDUCE`); cells no camera keeps are dropped."""
    point, camera = seen_by(bed, cameras)
    centres = np.array([c.camera_center for c in cameras]).reshape(-1, 3)
    out = dietrich(bed, centres, point, camera, water, max_angle_deg, REDUCE[reduce])
    return out[np.isfinite(out).all(1)]

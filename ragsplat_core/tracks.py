"""Sparse tracks as a bed, the way a surveyor grids them: an outlier filter, a linear (TIN) DEM, and the
start's fill of the gaps between them.

Points are [P, 3] (x, y, z; z up) or [P, 6] (with colours), numpy, on the CPU: they are cached files of a
dataset, not tensors of a model.
"""

from __future__ import annotations

import numpy as np

# The tracks' outlier filter: the DEM's despiking rule (`surface.ExtractConfig`, chosen on the development
# reach for trained beds), a point dropped when more than TRACK_TOL from the median of its neighbours within
# TRACK_RADIUS; not tuned again for tracks.
TRACK_RADIUS, TRACK_TOL, TRACK_MIN_NEIGHBOURS = 1.0, 0.3, 8


def track_filter(points: np.ndarray, radius: float = TRACK_RADIUS, tol: float = TRACK_TOL,
                 min_neighbours: int = TRACK_MIN_NEIGHBOURS) -> np.ndarray:
    """bool [P]: the points [P, 3+] to keep: a point is dropped when its height is more than `tol` metres from
    the median height of the other points within `radius` metres (horizontally), given at least
    `min_neighbours` of them; a point with fewer neighbours is kept (nothing to judge it by)."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, float)
    keep = np.ones(len(pts), dtype=bool)
    for i, near in enumerate(cKDTree(pts[:, :2]).query_ball_point(pts[:, :2], radius)):
        others = [j for j in near if j != i]
        if len(others) >= min_neighbours and abs(pts[i, 2] - np.median(pts[others, 2])) > tol:
            keep[i] = False
    return keep


def tin(points: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """[G', 3]: the nodes [G, 2] inside the convex hull of the points [P, 3+] with heights interpolated
    linearly on the points' Delaunay triangulation (the DEM a surveyor grids from a sparse cloud)."""
    from scipy.interpolate import LinearNDInterpolator

    pts = np.asarray(points, float)
    z = LinearNDInterpolator(pts[:, :2], pts[:, 2])(np.asarray(nodes, float)[:, :2])
    inside = np.isfinite(z)
    return np.column_stack([nodes[inside, :2], z[inside]])


def gap_nodes(tree, lo: np.ndarray, hi: np.ndarray, spacing: float, chunk: int = 1_000_000) -> np.ndarray:
    """[G, 2]: the nodes of the `spacing` grid (a node at the origin) over the box lo..hi [2] with no point of
    `tree` (a cKDTree of [P, 2]) within `spacing`, in x-major order; built `chunk` nodes at a time, so that a
    survey of square kilometres needs no grid of tens of millions of nodes at once."""
    xs, ys = (np.arange(np.floor(a / spacing), np.ceil(b / spacing) + 1) * spacing for a, b in zip(lo, hi))
    step = max(1, chunk // len(ys))  # x columns per chunk
    out = []
    for i in range(0, len(xs), step):
        nodes = np.stack(np.meshgrid(xs[i:i + step], ys, indexing="ij"), -1).reshape(-1, 2)
        out.append(nodes[tree.query(nodes, distance_upper_bound=spacing * (1 + 1e-9))[0] > spacing])
    return np.concatenate(out)


def fill_gaps(points: np.ndarray, spacing: float) -> np.ndarray:
    """[F, C] points for the gaps of a sparse cloud [P, C] (C = 3, or 6 with colours): the nodes of a square
    grid of `spacing` metres (a node at the origin) that lie inside the cloud's convex hull and have no point
    within `spacing` horizontally, at the height of the filtered cloud's TIN (`track_filter`, `tin`), with
    the colour of their nearest point.

    Why: where tracks are missing (texture-poor or deep bed, a steep bank), a start from the tracks alone
    leaves the bed empty, and training does not grow Gaussians into a hole it has nothing in; the TIN's
    surface there is what a surveyor would take, and the training refines it."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, float)
    if not spacing > 0:
        raise ValueError(f"spacing must be > 0, got {spacing}")
    none = np.zeros((0, pts.shape[1]))
    if len(pts) < 3:
        return none
    tree = cKDTree(pts[:, :2])
    gaps = gap_nodes(tree, pts[:, :2].min(0), pts[:, :2].max(0), spacing)
    kept = pts[track_filter(pts)] if len(gaps) else none  # the filter only when there is a gap to fill
    if len(kept) < 3:
        return none
    z = tin(kept, gaps)
    if not len(z):
        return none
    colours = pts[tree.query(z[:, :2])[1], 3:]
    return np.column_stack([z, colours])

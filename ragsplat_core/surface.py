"""The bed surface of trained Gaussians as a height grid: what the evaluation scores against the GT grid
(Table 2) and what `ragsplat export` writes as a DEM.

Extraction (the paper's Section 3, "Geometry Extraction"):
1. cull Gaussians below an opacity threshold, those whose largest standard deviation exceeds
   `max_scale_gsd` ground sample distances of the views (`gsd`, `Dataset.gsd`) or `max_scale_m` metres
   (`max_scale`), and, when a region is
   given, those whose centre lies more than `region_margin` outside it (samples spent far away say nothing
   about the bed);
2. draw `n_samples` points, split between Gaussians in proportion to their volume (product of the three
   standard deviations) with largest-remainder rounding, so the total is exact; each point is a draw of the
   Gaussian truncated to Mahalanobis radius `sigma_cut` (2 sigma);
3. local-plane noise filter (CloudCompare's "noise filter", relative mode): for every point, fit a plane
   to its neighbours within `filter_radius` (at most `filter_max_neighbours` nearest), drop the point when
   its distance to that plane exceeds `filter_k` x the standard deviation of the neighbours' distances
   (never below `filter_min_tol`, so exactly planar patches do not reject on rounding), and drop points
   with fewer than `filter_min_neighbours` neighbours (isolated);
4. a horizontal grid of `cell` metres with a node at `origin` (pass a node of the GT grid so both grids
   share their nodes; otherwise a half-cell offset alone costs ~2.5 cm of Chamfer): one point per occupied
   cell at its node (the cell centre) with the median height of the cell's points;
5. despiking (a DEM's usual last step): a cell whose height is more than `despike_tol` from the median of
   the occupied cells within `despike_radius` is dropped (`despike`). Floaters that are opaque and small
   enough to pass steps 1-3 gather in patches of a few tens of cells metres above or below the bed; the
   point filter keeps them because each patch is a plane of its own;
6. hole filling, as a surveyor grids a DEM (`fill_gap_cells`, 1 by default; 0: off): every empty cell
   whose nearest occupied cell is at most that many cells away gets the height of the occupied cells'
   linear (Delaunay) interpolation (`fill_holes`). Where deep Gaussians were culled or sampled thinly the
   grid has scattered one-cell holes; wider gaps stay empty.

The evaluation scores the grid with `ragsplat.scoring.geometry_metrics` (`ragsplat.eval.evaluate`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace

import numpy as np
import torch
from numba import njit, prange
from scipy.spatial import cKDTree

from ragsplat.errors import ConfigError
from ragsplat.gaussians import quat_to_rotmat
from ragsplat.tuning import record

# The culls, despiking and fill were chosen on the development reach (dataset seed 1), each by a rule fixed
# before its sweep: ragsplat_core/tuning/extract.json (docs/lab/history.md, "The extraction's settings").
EXTRACT_TUNING = record("extract")


@dataclass(frozen=True)
class ExtractConfig:
    # the paper's 0.1 keeps faint Gaussians floating off the bed: 0.7, the best F1@3% that keeps 85 % of the
    # wet cells (tuning/extract.json, "min_opacity" and "both")
    min_opacity: float = field(default=0.7, metadata={"help": (
        "only Gaussians at least this opaque make the bed (default: the evaluation's, chosen on the "
        "development reach; lower it for a short or sparse run)")})
    # largest standard deviation, in ground sample distances: a Gaussian many pixels wide is not what the
    # views resolve and cannot place one cell's height, yet volume weighting gives it the most samples.
    # 6 as chosen with the opacity (tuning/extract.json, "both"; the paper: no limit). In pixels, not cells:
    # the DEM's cell is the user's choice.
    max_scale_gsd: float = field(default=6.0, metadata={"help": (
        "only Gaussians whose largest standard deviation is at most K ground sample distances of the views "
        "(at the water surface) make the bed (default: the evaluation's, chosen on the development reach; "
        "inf: no limit, needed for a dry scene)")})
    # ...and at most this many metres, but never below `RELIEF_FLOOR_GSD` pixels: a flat surfel wider than
    # the bed's relief cannot follow it, however coarse the pixels. On `small`'s pixels it changes nothing; on
    # the long reach's coarser ones the pixels' cap alone left a speckle of wide surfels too deep
    # (tuning/extract.json, "long"). inf: the pixels alone. That is for surfels trained with the ray's z;
    # a run's extraction takes its own training's (`size_cap_m`).
    max_scale_m: float = field(default=0.14, metadata={"help": (
        "and at most M metres, where that is at least 3 ground sample distances (default: by the run's "
        "surfel depth, chosen on the long reach's development stretch: 0.14 with the ray's, inf with the "
        "centre's; inf: the ground sample distances alone)")})
    gsd: float | None = None  # metres per pixel (`Dataset.gsd`); needed when max_scale_gsd is finite
    n_samples: int = 200_000
    sigma_cut: float = 2.0
    region_margin: float = 0.5  # metres around the evaluation region whose Gaussians are sampled
    filter_radius: float = 0.10
    filter_max_neighbours: int = 32
    filter_min_neighbours: int = 6
    filter_k: float = 2.0
    filter_min_tol: float = 1e-3  # metres
    cell: float = 0.05
    # the least RMSE that takes spikes, not bed (tuning/extract.json, "despike"); the disc needs
    # `despike_min_neighbours` occupied cells to judge (a DEM cell of 1 m has only 4 within 1 m: nothing is
    # dropped there). despike_tol = inf: no despiking.
    despike_radius: float = field(default=1.0, metadata={"help": (
        "a DEM cell is compared with the median of the cells within M metres (default: the evaluation's, "
        "chosen on the development reach)")})
    despike_tol: float = field(default=0.3, metadata={"help": (
        "and dropped when more than M metres from it (default: the evaluation's; inf: keep every cell)")})
    despike_min_neighbours: int = 8
    # step 6: the best F1@1% (tuning/extract.json, "fill")
    fill_gap_cells: float = field(default=1.0, metadata={"help": (
        "fill the holes: an empty cell at most K cells from a filled one gets the linear interpolation of "
        "the filled cells (default: the evaluation's, 0: none)")})
    seed: int = 0

    def to_dict(self) -> dict:
        return asdict(self)


def _np(x) -> np.ndarray:
    """Tensor or array -> float64 numpy (detached, on the CPU)."""
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def largest_remainder(weights: np.ndarray, total: int) -> np.ndarray:
    """Non-negative integer counts proportional to `weights` summing exactly to `total`.

    Floors of the quotas, then one extra to each of the largest fractional parts (ties: lower index).
    """
    weights = np.asarray(weights, dtype=np.float64)
    if total < 0 or (weights < 0).any() or not np.isfinite(weights).all():
        raise ValueError("largest_remainder needs finite non-negative weights and total >= 0")
    if total == 0 or weights.sum() <= 0:
        return np.zeros(len(weights), dtype=np.int64)
    quota = weights * (total / weights.sum())
    counts = np.floor(quota).astype(np.int64)
    short = total - int(counts.sum())
    if short > 0:
        order = np.argsort(-(quota - counts), kind="stable")
        counts[order[:short]] += 1
    return counts


def truncated_normal(n: int, cut: float, rng: np.random.Generator) -> np.ndarray:
    """[n, 3] standard normal draws conditioned on norm <= cut (rejection sampling)."""
    out, have = np.empty((n, 3)), 0
    while have < n:
        z = rng.standard_normal((max(2 * (n - have), 64), 3))
        z = z[np.einsum("ij,ij->i", z, z) <= cut * cut][: n - have]
        out[have: have + len(z)] = z
        have += len(z)
    return out


# Below 3 pixels the bed has holes: on the long reach's development stretch 2.5 pixels kept 86 % and 2 pixels
# 66 % of the wet cells, 3 pixels 96 % (tuning/extract.json, "long").
RELIEF_FLOOR_GSD = 3.0


# `ExtractConfig.max_scale_m` by the z a model's surfels were trained with (`TrainConfig.surfel_depth`): the
# ray's keeps the 14 cm cap (tuning/extract.json, "long"); with the centre's z the same development stretch
# picks the pixels alone, 6 of them, over six training seeds (extract.json, "long" / "centre").
SIZE_CAP_M = {"ray": EXTRACT_TUNING["long"]["chosen"]["max_scale_m"],
              "centre": float(EXTRACT_TUNING["long"]["centre"]["picks"]["max_scale_m"])}


def size_cap_m(train) -> float:
    """`ExtractConfig.max_scale_m` for a model trained under `train` (a `TrainConfig`): its surfels' depth's
    (`SIZE_CAP_M`); the ray's for 3D Gaussians, which the choice of depth does not touch."""
    return SIZE_CAP_M[train.surfel_depth if train.surfels else "ray"]


def max_scale(cfg: ExtractConfig) -> float:
    """The size cull in metres (inf: none): `max_scale_gsd` pixels, or `max_scale_m` where that is smaller
    and still at least `RELIEF_FLOOR_GSD` pixels. Raises ConfigError when it needs a ground sample distance
    and has none (a dry scene: no water surface to measure it at)."""
    if math.isinf(cfg.max_scale_gsd):
        return math.inf
    if cfg.gsd is None or not cfg.gsd > 0:
        raise ConfigError(f"the size cull ({cfg.max_scale_gsd:g} ground sample distances) needs the views' "
                          f"ground sample distance, got {cfg.gsd}; pass it, or lift the cull (max_scale_gsd "
                          "= inf)")
    return min(cfg.max_scale_gsd, max(cfg.max_scale_m / cfg.gsd, RELIEF_FLOOR_GSD)) * cfg.gsd


def culled(scales: np.ndarray, opacities: np.ndarray, means: np.ndarray, cfg: ExtractConfig,
           region: dict | None) -> np.ndarray:
    """Step 1: bool mask [N] of the Gaussians sampled."""
    keep = (opacities >= cfg.min_opacity) & (scales.max(1) <= max_scale(cfg))
    if region is not None:
        keep &= in_region(means, region, tol=cfg.region_margin)
    return keep


def sample_gaussians(means, scales, quats, opacities, cfg: ExtractConfig, region: dict | None = None,
                     rng: np.random.Generator | None = None, chunk: int = 262_144):
    """Steps 1-2: points [M, 3] (M = cfg.n_samples unless nothing survives culling) and the kept mask [N];
    drawn with `rng` (default: one seeded with cfg.seed). The samples are turned by their Gaussians'
    rotations `chunk` at a time (the same arithmetic row by row; [chunk, 3, 3] at once, not [M, 3, 3])."""
    means, scales, quats, opac = _np(means), _np(scales), _np(quats), _np(opacities).reshape(-1)
    keep = culled(scales, opac, means, cfg, region)
    idx = np.flatnonzero(keep)
    counts = largest_remainder(np.prod(scales[idx], axis=1), cfg.n_samples)
    owner = np.repeat(idx, counts)  # [M]
    rng = np.random.default_rng(cfg.seed) if rng is None else rng
    z = truncated_normal(len(owner), cfg.sigma_cut, rng) * scales[owner]  # [M, 3] in local axes
    points = means[owner]
    for s in range(0, len(owner), chunk):
        rot = quat_to_rotmat(torch.from_numpy(quats[owner[s: s + chunk]])).numpy()  # [chunk, 3, 3]
        points[s: s + chunk] += np.einsum("mij,mj->mi", rot, z[s: s + chunk])
    return points, keep


def plane_filter(points: np.ndarray, cfg: ExtractConfig, chunk: int = 20_000,
                 fast: bool = True) -> np.ndarray:
    """Step 3: bool mask [M] of the points the local-plane noise filter keeps.

    `fast`: each point's plane test in one numba kernel (`_plane_keep`); otherwise in numpy, its twin."""
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    points = np.ascontiguousarray(points, dtype=np.float64)
    # the sliding-midpoint tree: the same neighbours, built 3x and queried 1.5x faster here (measured on
    # the reach's 445 k samples)
    tree = cKDTree(points, balanced_tree=False, compact_nodes=False)
    k = min(cfg.filter_max_neighbours + 1, len(points))  # +1: the query point finds itself first
    keep = np.zeros(len(points), dtype=bool)
    for s in range(0, len(points), chunk):
        p = points[s: s + chunk]  # [C, 3]
        dist, nb = tree.query(p, k=k, distance_upper_bound=cfg.filter_radius, workers=-1)
        dist, nb = dist.reshape(len(p), k)[:, 1:], nb.reshape(len(p), k)[:, 1:]  # drop the point itself
        valid = np.isfinite(dist)  # [C, K]; a missing neighbour has index len(points)
        test = _plane_keep if fast else _plane_keep_numpy
        keep[s: s + chunk] = test(points, p, np.ascontiguousarray(nb), valid, cfg.filter_min_neighbours,
                                  cfg.filter_k, cfg.filter_min_tol)
    return keep


def _plane_keep_numpy(points, p, nb, valid, min_neighbours: int, k: float, min_tol: float) -> np.ndarray:
    """[C] bool: the plane test of points p [C, 3] against their neighbours points[nb] [C, K] (where
    valid)."""
    cnt = valid.sum(1)
    q = points[np.where(valid, nb, 0)]  # [C, K, 3]
    w = valid[..., None].astype(np.float64)
    centre = (q * w).sum(1) / np.maximum(cnt, 1)[:, None]  # [C, 3]
    d = (q - centre[:, None]) * w
    cov = np.einsum("cki,ckj->cij", d, d)
    normal = np.linalg.eigh(cov)[1][:, :, 0]  # [C, 3] smallest-eigenvalue direction
    nd = np.einsum("cki,ci->ck", d, normal)  # neighbours' signed plane distances (0 where invalid)
    std = np.sqrt((nd**2).sum(1) / np.maximum(cnt, 1))
    own = np.abs(np.einsum("ci,ci->c", p - centre, normal))
    tol = np.maximum(k * std, min_tol)
    return (cnt >= min_neighbours) & (own <= tol)


@njit(cache=True, parallel=True)
def _plane_keep(points, p, nb, valid, min_neighbours, k, min_tol):  # the same as `_plane_keep_numpy`
    out = np.zeros(len(p), dtype=np.bool_)
    for c in prange(len(p)):
        cnt = 0
        centre = np.zeros(3)
        for j in range(nb.shape[1]):
            if valid[c, j]:
                cnt += 1
                centre += points[nb[c, j]]
        if cnt < min_neighbours:
            continue
        centre /= max(cnt, 1)  # as the twin: an isolated point kept by min_neighbours = 0 is tested at 0
        cov = np.zeros((3, 3))
        for j in range(nb.shape[1]):
            if valid[c, j]:
                d = points[nb[c, j]] - centre
                for a in range(3):
                    for b in range(3):
                        cov[a, b] += d[a] * d[b]
        normal = np.linalg.eigh(cov)[1][:, 0]  # smallest-eigenvalue direction
        ss = 0.0
        for j in range(nb.shape[1]):
            if valid[c, j]:
                nd = 0.0
                for a in range(3):
                    nd += (points[nb[c, j], a] - centre[a]) * normal[a]
                ss += nd * nd
        own = 0.0
        for a in range(3):
            own += (p[c, a] - centre[a]) * normal[a]
        out[c] = abs(own) <= max(k * np.sqrt(ss / max(cnt, 1)), min_tol)
    return out


def grid_median(points: np.ndarray, cell: float, origin: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """Step 4: [G, 3] grid nodes origin + (i, j) * cell, each with the median z of the points in its cell
    (the square of side `cell` centred on the node), sorted by cell."""
    if len(points) == 0:
        return np.zeros((0, 3))
    ij = np.floor((points[:, :2] - np.asarray(origin)) / cell + 0.5).astype(np.int64)  # [M, 2]
    cells, inv = np.unique(ij, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    order = np.lexsort((points[:, 2], inv))  # by cell, then height
    z_sorted, cell_sorted = points[order, 2], inv[order]
    starts = np.searchsorted(cell_sorted, np.arange(len(cells)))
    ends = np.append(starts[1:], len(points))
    lo, hi = (starts + ends - 1) // 2, (starts + ends) // 2
    med = 0.5 * (z_sorted[lo] + z_sorted[hi])
    xy = cells * cell + np.asarray(origin)
    return np.column_stack([xy, med])


def despike(grid: np.ndarray, cell: float, radius: float, tol: float,
            min_neighbours: int = ExtractConfig.despike_min_neighbours, block: int = 128, chunk: int = 4096
            ) -> np.ndarray:
    """Step 5: bool mask [G] of the cells of a height grid [G, 3] (nodes `cell` apart) to keep: a cell is
    dropped when its height differs by more than `tol` metres from the median height of the other occupied
    cells within `radius` metres (a disc), provided there are at least `min_neighbours` of them. A patch of
    floaters smaller than about half the disc cannot hold its own median; relief that varies smoothly keeps
    its cells near it. Memory is bounded by `block` x `block` cells at a time (one far floater must not
    make a dense array of everything between it and the bed), `chunk` cells' discs at a time."""
    if len(grid) == 0 or not np.isfinite(tol):
        return np.ones(len(grid), dtype=bool)
    ij = np.rint((grid[:, :2] - grid[:, :2].min(0)) / cell).astype(np.int64)  # [G, 2] node indices
    r = math.floor(radius / cell + 1e-9)  # 1.0 / 0.05 must give 20 cells, not 19
    di, dj = np.meshgrid(np.arange(-r, r + 1), np.arange(-r, r + 1), indexing="ij")
    disc = (di**2 + dj**2 <= r * r) & ((di != 0) | (dj != 0))  # the cell itself is not its own neighbour
    di, dj = di[disc], dj[disc]  # [K]
    keep = np.ones(len(grid), dtype=bool)
    tiles, tile_of = np.unique(ij // block, axis=0, return_inverse=True)
    for t, corner in enumerate(tiles * block - r):  # each tile with the cells within r of it
        near = np.flatnonzero(((ij >= corner) & (ij < corner + block + 2 * r)).all(1))
        dense = np.full((block + 2 * r, block + 2 * r), np.nan)  # NaN = no height
        dense[ij[near, 0] - corner[0], ij[near, 1] - corner[1]] = grid[near, 2]
        mine = np.flatnonzero(tile_of.reshape(-1) == t)
        for s in range(0, len(mine), chunk):
            cells = mine[s: s + chunk]
            c = ij[cells] - corner  # [C, 2]
            window = np.sort(dense[c[:, :1] + di, c[:, 1:] + dj], axis=1)  # [C, K], NaNs last
            count = np.isfinite(window).sum(1)
            # the median of each row's `count` heights (np.nanmedian loops over rows in Python at this K)
            lo = np.take_along_axis(window, np.maximum(count - 1, 0)[:, None] // 2, 1)[:, 0]
            hi = np.take_along_axis(window, count[:, None] // 2, 1)[:, 0]
            far = np.abs(grid[cells, 2] - 0.5 * (lo + hi)) > tol
            keep[cells] = (count < max(min_neighbours, 1)) | ~far
    return keep


def in_region(points: np.ndarray, region: dict, tol: float = 0.0) -> np.ndarray:  # [M] bool, horizontal only
    """Inside the region grown by `tol` (so grid nodes computed as origin + i * cell that land a rounding
    error past an edge still count)."""
    return ((points[:, 0] >= region["xmin"] - tol) & (points[:, 0] <= region["xmax"] + tol)
            & (points[:, 1] >= region["ymin"] - tol) & (points[:, 1] <= region["ymax"] + tol))


def extract_surface(means, scales, quats, opacities, cfg: ExtractConfig = ExtractConfig(),
                    region: dict | None = None, origin: tuple[float, float] | None = None,
                    rng: np.random.Generator | None = None, window: tuple | None = None, cells: bool = False
                    ) -> tuple[np.ndarray, dict]:
    """Gaussians (means [N,3], scales [N,3] linear, quats [N,4] wxyz, opacities [N] in [0,1]; tensors or
    arrays) -> height-grid points [G, 3] (inside `region` when given) and counts of every stage.

    `origin` is a node of the output grid: pass one of the GT grid (default: region (xmin, ymin), else 0).
    `rng`: the samples' draw (`sample_gaussians`); `window` (lo [2], hi [2]): only the samples inside it are
    kept (a block of `extract_surface_blocks` with its margin). `cells`: the stats also hold "cells", per
    node of the grid, the filtered samples' count and height spread in its cell (`cell_spread`) and whether
    step 6 filled it (the uncertainty's features, `ragsplat.uncertainty`); the grid is the same.
    """
    pts, kept = sample_gaussians(means, scales, quats, opacities, cfg, region, rng=rng)
    if window is not None:
        pts = pts[((pts[:, :2] >= window[0]) & (pts[:, :2] <= window[1])).all(1)]
    mask = plane_filter(pts, cfg)
    if origin is None:
        origin = (region["xmin"], region["ymin"]) if region is not None else (0.0, 0.0)
    origin = (float(origin[0]), float(origin[1]))
    grid = grid_median(pts[mask], cfg.cell, origin)
    smooth = despike(grid, cfg.cell, cfg.despike_radius, cfg.despike_tol, cfg.despike_min_neighbours)
    spikes = int((~smooth).sum())
    # before the crop, so that cells at the region's edge have their neighbours outside it
    grid = grid[smooth]
    if region is not None:
        grid = grid[in_region(grid, region, tol=1e-6 * cfg.cell)]
    extracted = len(grid)
    grid = fill_holes(grid, cfg.cell, origin, cfg.fill_gap_cells)
    stats = {"gaussians": len(kept), "gaussians_sampled": int(kept.sum()), "samples": len(pts),
             "samples_after_filter": int(mask.sum()), "grid_spikes": spikes,
             "grid_filled": len(grid) - extracted, "grid_points": len(grid),
             "config": cfg.to_dict(), "grid_origin": list(origin)}
    if cells:
        count, spread = cell_spread(pts[mask], grid, cfg.cell, origin)
        stats["cells"] = {"samples": count, "spread": spread, "filled": np.arange(len(grid)) >= extracted}
    return grid, stats


def cell_spread(points: np.ndarray, grid: np.ndarray, cell: float, origin: tuple[float, float]
                ) -> tuple[np.ndarray, np.ndarray]:
    """Per node of `grid` [G, 3]: (the number [G] of `points` [M, 3] in its cell, as `grid_median` bins them,
    and the robust spread [G] of their heights, 0.7413 x the interquartile range: the standard deviation for
    normal heights, blind to a few strays; NaN with fewer than 2 points)."""
    count, spread = np.zeros(len(grid), dtype=np.int64), np.full(len(grid), np.nan)
    if not len(points) or not len(grid):
        return count, spread
    o = np.asarray(origin, float)
    ij = np.floor((points[:, :2] - o) / cell + 0.5).astype(np.int64)  # [M, 2] grid_median's cells
    node = np.rint((grid[:, :2] - o) / cell).astype(np.int64)  # [G, 2]
    lo = np.minimum(ij.min(0), node.min(0))
    width = int(max(ij[:, 1].max(), node[:, 1].max()) - lo[1] + 1)
    key_p, key_g = ((ij[:, 0] - lo[0]) * width + ij[:, 1] - lo[1],
                    (node[:, 0] - lo[0]) * width + node[:, 1] - lo[1])
    order = np.lexsort((points[:, 2], key_p))  # by cell, then height
    key_s, z = key_p[order], points[order, 2]
    start, end = np.searchsorted(key_s, key_g, "left"), np.searchsorted(key_s, key_g, "right")
    count = end - start
    ok = count >= 2
    first, last, n = start[ok], end[ok] - 1, count[ok]

    def quantile(f):  # numpy's linear rule within each cell's sorted run
        pos = f * (n - 1)
        k = np.floor(pos).astype(np.int64)
        return z[first + k] + (pos - k) * (z[np.minimum(first + k + 1, last)] - z[first + k])

    spread[ok] = 0.7413 * (quantile(0.75) - quantile(0.25))
    return count, spread


def extract_surface_blocks(means, scales, quats, opacities, cfg: ExtractConfig, block_cells: int,
                           origin: tuple[float, float], region: dict | None = None, on_block=None,
                           cells: bool = False) -> tuple[np.ndarray, dict]:
    """`extract_surface` of a bed too large to sample at once, in square blocks of `block_cells` x
    `block_cells` grid nodes over the region (without one, over the sampled Gaussians' reach, as one pass
    covers): the same steps in each, so that memory is
    bounded by a block's samples whatever the area. Each block samples the Gaussians that can reach it or
    its margin, at the density of the whole (cfg.n_samples over the volume of every Gaussian kept), filters
    and grids the samples of the block and its margin (as wide as the noise filter's and the despiking's
    neighbourhoods, and a hole's fill), and keeps its own nodes. A block's own random stream (cfg.seed and its
    index), so the result does not depend on the order the blocks are done in; it is not the one-pass
    result's draw, and the holes are filled within each block's margin. `on_block(done, total)` after each.
    `cells`: stats["cells"] as `extract_surface` records it, each block's for its own nodes."""
    means, scales, quats, opac = _np(means), _np(scales), _np(quats), _np(opacities).reshape(-1)
    keep = culled(scales, opac, means, cfg, region)
    idx = np.flatnonzero(keep)
    volume = np.prod(scales[idx], axis=1)
    density = cfg.n_samples / max(volume.sum(), 1e-300)  # samples per unit volume, as in one pass
    reach = cfg.sigma_cut * (scales[idx].max() if len(idx) else 0.0)  # how far a kept Gaussian's draws go
    margin = cfg.filter_radius + cfg.despike_radius + (cfg.fill_gap_cells + 2) * cfg.cell
    origin = np.asarray(origin, float)
    if region is not None:
        box = np.array([region["xmin"], region["ymin"]]), np.array([region["xmax"], region["ymax"]])
    else:
        box = (means[idx, :2].min(0) - reach, means[idx, :2].max(0) + reach) if len(idx) else (origin, origin)
    first = np.ceil((box[0] - origin) / cfg.cell - 1e-6).astype(np.int64)  # the nodes [2] in the box
    last = np.floor((box[1] - origin) / cfg.cell + 1e-6).astype(np.int64)
    grids, samples, kept_samples, records = [], 0, 0, []
    corners = [(bi, bj) for bi in range(first[0], last[0] + 1, block_cells)
               for bj in range(first[1], last[1] + 1, block_cells)]
    for done, (bi, bj) in enumerate(corners, 1):
        own_lo = np.array([bi, bj])  # the block's nodes: own_lo <= index < own_hi
        own_hi = np.minimum(own_lo + block_cells, last + 1)
        lo, hi = origin + (own_lo - 0.5) * cfg.cell - margin, origin + (own_hi - 0.5) * cfg.cell + margin
        near = idx[((means[idx, :2] >= lo - reach) & (means[idx, :2] <= hi + reach)).all(1)]
        n = round(density * np.prod(scales[near], axis=1).sum())
        rng = np.random.default_rng([cfg.seed, int(bi - first[0]), int(bj - first[1])])
        grid, counts = extract_surface(means[near], scales[near], quats[near], opac[near],
                                       replace(cfg, n_samples=n), region, tuple(origin), rng=rng,
                                       window=(lo, hi), cells=cells)
        samples += counts["samples"]
        kept_samples += counts["samples_after_filter"]
        ij = np.rint((grid[:, :2] - origin) / cfg.cell).astype(np.int64)
        own = ((ij >= own_lo) & (ij < own_hi)).all(1)
        grids.append(grid[own])
        if cells:
            records.append({k: v[own] for k, v in counts["cells"].items()})
        if on_block is not None:
            on_block(done, len(corners))
    grid = np.vstack(grids) if grids else np.zeros((0, 3))
    stats = {"gaussians": len(keep), "gaussians_sampled": len(idx), "samples": samples,
             "samples_after_filter": kept_samples, "grid_points": len(grid), "blocks": len(corners),
             "block_cells": block_cells, "config": cfg.to_dict(), "grid_origin": origin.tolist()}
    if cells:
        stats["cells"] = {k: np.concatenate([r[k] for r in records]) if records else np.zeros(0)
                          for k in ("samples", "spread", "filled")}
    return grid, stats


def fill_holes(grid: np.ndarray, cell: float, origin: tuple[float, float], gap_cells: float) -> np.ndarray:
    """`grid` [G, 3] (one point per occupied cell at its node, nodes at origin + k cell) and, after it, a
    point at every empty node of its bounding box whose nearest occupied node is at most `gap_cells` cells
    away and that lies inside the occupied nodes' convex hull, its height linear on their Delaunay
    triangulation (`tracks.tin`). gap_cells <= 0, or occupied nodes on one line (a hull with no inside):
    `grid` itself."""
    if gap_cells <= 0 or len(grid) < 3:
        return grid
    from scipy.ndimage import distance_transform_edt
    from scipy.spatial import QhullError

    from ragsplat.tracks import tin

    ij = np.round((grid[:, :2] - np.asarray(origin)) / cell).astype(np.int64)  # [G, 2]
    lo = ij.min(0)
    occupied = np.zeros(ij.max(0) - lo + 1, dtype=bool)
    occupied[tuple((ij - lo).T)] = True
    near = ~occupied & (distance_transform_edt(~occupied) <= gap_cells + 1e-9)  # in cells
    nodes = (np.argwhere(near) + lo) * cell + np.asarray(origin)  # [H, 2]
    if not len(nodes):
        return grid
    try:
        return np.vstack([grid, tin(grid, nodes)])
    except QhullError:  # every occupied node on one line (a one-row DEM): no triangle to interpolate in
        return grid

"""A survey split into overlapping tiles, each trained on its own, and their beds merged into one.

The tiles cut the survey's extent (its model points' 1-99 % box, horizontal, the survey's local frame) into
a grid of equal cores no larger than the tile size; a tile's outer box is its core grown by the overlap on
every side, and it holds the photos whose footprint on the water (`footprints`) has at least `MIN_SEEN` of its
box inside the outer box. The outer cores reach to infinity, so every point of the plane lies in exactly one
core (`owner`): the merged bed takes each cell from the tile whose core holds it, and the cells two tiles both
made (the overlap) measure how well they agree at the seams (`merge`'s report). A survey whose extent fits in
one tile is one tile (`plan` gives a single tile with no bounds). The grid is planned by photos as well as by
ground: a tile no photo sees is left out (nothing there to train), and the grid is made coarser until every
other tile holds at least `MIN_TILE_PHOTOS`. numpy only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

MIN_SEEN = 0.1  # a photo joins a tile when this share of its footprint's box lies in the tile's outer box
# a ray closer to the horizon than this (its run over its drop) meets the water no farther than this many
# flying heights away: an oblique's upper image edge would otherwise reach the horizon
MAX_REACH = 3.0
# A tile trains on its own photos only: its structure needs two to triangulate, and its refracted start and
# training need each point of its core seen from several. A nadir grid at 70 % forward and 60 % side overlap
# sees a point in about 1 / (0.3 x 0.4) = 8 photos; a tile of at least 12 holds those and part of a ring.
MIN_TILE_PHOTOS = 12


@dataclass(frozen=True)
class Tile:
    index: int
    grid: tuple[int, int]  # (column along x, row along y)
    # xmin, ymin, xmax, ymax (m, local frame; +-inf at the survey's edge)
    core: tuple[float, float, float, float]
    # the core grown by the overlap (the edge tiles' outside unbounded)
    outer: tuple[float, float, float, float]
    photos: tuple[str, ...]

    def to_json(self) -> dict:
        """The tile for a run's JSON (boxes in the frame they were planned in; None: open)."""
        def box(b):
            return [v if math.isfinite(v) else None for v in b]

        return {"index": self.index, "grid": list(self.grid), "core": box(self.core),
                "outer": box(self.outer), "photos": len(self.photos)}


def footprints(R: np.ndarray, C: np.ndarray, intrinsics: np.ndarray, sizes: np.ndarray, water) -> np.ndarray:
    """Each camera's footprint on the water surface as a box [V, 4] (xmin, ymin, xmax, ymax): the rays through
    a 5 x 5 lattice of its image (R [V, 3, 3] world -> camera, centres C [V, 3], intrinsics [V, 4] fx, fy, cx,
    cy, sizes [V, 2] width, height) met with the surface's height below the camera (a sloping surface's
    change across one footprint is centimetres), each at most `MAX_REACH` flying heights away."""
    t = np.linspace(0.0, 1.0, 5)
    boxes = np.empty((len(C), 4))
    for k in range(len(C)):
        fx, fy, cx, cy = intrinsics[k]
        u, v = np.meshgrid(t * sizes[k, 0], t * sizes[k, 1])
        rays = np.stack([(u.ravel() - cx) / fx, (v.ravel() - cy) / fy, np.ones(u.size)], -1) @ R[k]  # [25, 3]
        height = max(float(C[k, 2] - water.height(C[k, :2])), 1e-6)  # above the water
        run = np.hypot(rays[:, 0], rays[:, 1])
        reach = np.where(rays[:, 2] < 0, height * run / np.maximum(-rays[:, 2], 1e-12), np.inf)
        reach = np.minimum(reach, MAX_REACH * height)
        xy = C[k, :2] + rays[:, :2] / np.maximum(run, 1e-12)[:, None] * reach[:, None]
        boxes[k] = [*xy.min(0), *xy.max(0)]
    return boxes


def plan(lo, hi, boxes: np.ndarray, names: list[str], size: float, overlap: float,
         min_photos: int = MIN_TILE_PHOTOS) -> list[Tile]:
    """The tiles of a survey whose points span the box [lo, hi] ((x, y) each, m) with photos `names` [V]
    whose footprints are `boxes` [V, 4]: nx x ny equal cores no larger than `size`, each grown by `overlap`,
    numbered in order. One tile (no bounds, every photo) when the extent fits in `size` both ways. Tiles that
    no photo sees are left out; while another holds fewer than `min_photos`, the grid is made coarser (the
    axis cut into more cores loses one), so a tile's cores may grow past `size`."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    counts = [max(1, math.ceil((b - a) / size - 1e-9)) for a, b in zip(lo, hi)]
    while True:
        tiles = [t for t in _grid(lo, hi, boxes, names, counts, overlap) if t.photos]
        if counts == [1, 1] or tiles and all(len(t.photos) >= min_photos for t in tiles):
            return [replace(t, index=k) for k, t in enumerate(tiles)]
        counts[int(counts[1] > counts[0])] -= 1


def _grid(lo, hi, boxes: np.ndarray, names: list[str], counts: list[int], overlap: float) -> list[Tile]:
    """`plan`'s tiles of a grid of counts[0] x counts[1] cores, the photos that see each (possibly none)."""
    if counts == [1, 1]:
        inf = (-math.inf, -math.inf, math.inf, math.inf)
        return [Tile(0, (0, 0), inf, inf, tuple(names))]
    tiles = []
    for j in range(counts[1]):
        for i in range(counts[0]):
            (x0, x1), (y0, y1) = (_cut(lo, hi, counts, (i, j), axis) for axis in (0, 1))
            core = [x0, y0, x1, y1]
            outer = [core[0] - overlap, core[1] - overlap, core[2] + overlap, core[3] + overlap]
            seen = _share_inside(boxes, outer)
            photos = tuple(n for n, s in zip(names, seen) if s >= MIN_SEEN)
            open_edges = (i == 0, j == 0, i == counts[0] - 1, j == counts[1] - 1)
            sign = (-1, -1, 1, 1)
            core = [sign[e] * math.inf if open_edges[e] else core[e] for e in range(4)]
            outer = [sign[e] * math.inf if open_edges[e] else outer[e] for e in range(4)]
            tiles.append(Tile(len(tiles), (i, j), tuple(core), tuple(outer), photos))
    return tiles


def _cut(lo, hi, counts, ij, axis) -> tuple[float, float]:
    """(start, end) of core `ij`'s along `axis` (an inner core's; the edge ones are opened by `plan`)."""
    width = (hi[axis] - lo[axis]) / counts[axis]
    return lo[axis] + ij[axis] * width, lo[axis] + (ij[axis] + 1) * width


def _share_inside(boxes: np.ndarray, outer) -> np.ndarray:
    """The share [V] of each box [V, 4]'s area inside the box `outer` (zero-area boxes: 0)."""
    w = np.clip(np.minimum(boxes[:, 2], outer[2]) - np.maximum(boxes[:, 0], outer[0]), 0, None)
    h = np.clip(np.minimum(boxes[:, 3], outer[3]) - np.maximum(boxes[:, 1], outer[1]), 0, None)
    area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    return np.where(area > 0, w * h / np.where(area > 0, area, 1.0), 0.0)


def inside(xy: np.ndarray, box) -> np.ndarray:
    """Whether each point xy [N, 2] lies in the half-open box [xmin, xmax) x [ymin, ymax): a point on a shared
    edge belongs to one box only."""
    return (xy[:, 0] >= box[0]) & (xy[:, 0] < box[2]) & (xy[:, 1] >= box[1]) & (xy[:, 1] < box[3])


def merge(beds: list[np.ndarray], tiles: list[Tile],
          resolution: float) -> tuple[np.ndarray, np.ndarray, dict]:
    """One bed from the tiles' beds (each [G_t, 3] cell centres and heights in the same frame, on one grid of
    `resolution`; further columns, a cell's TVU95, go with their cell): each cell from the tile whose core
    holds it, or, where that tile left it empty, from the first other tile that made it (the overlap fills a
    hole at a seam). Returns (grid [G, 3] (as wide as the beds), the tile each cell came from [G], the report:
    cells per tile, the holes filled, and for each pair of tiles that made common cells their number and the
    height difference's median, rms and p95 of its absolute value, m)."""
    keys = []  # each bed holds a cell once (one extracted point per cell)
    for bed in beds:
        ij = np.round(bed[:, :2] / resolution).astype(np.int64)  # the cell's integer index on the common grid
        keys.append(((ij[:, 0] + 2**31) << 32) + (ij[:, 1] + 2**31))
    mine = [inside(bed[:, :2], tile.core) for tile, bed in zip(tiles, beds)]
    taken = np.unique(np.concatenate([k[m] for k, m in zip(keys, mine)])) if beds else np.zeros(0, np.int64)
    kept, owner, report = [], [], {"cells": {}, "filled": 0, "overlap": []}
    for tile, bed, key, m in zip(tiles, beds, keys, mine):
        fill = ~m & ~np.isin(key, taken)
        taken = np.union1d(taken, key[fill])
        use = m | fill
        kept.append(bed[use])
        owner.append(np.full(int(use.sum()), tile.index))
        report["cells"][str(tile.index)] = int(use.sum())
        report["filled"] += int(fill.sum())
    for a in range(len(tiles)):
        for b in range(a + 1, len(tiles)):
            _, ia, ib = np.intersect1d(keys[a], keys[b], assume_unique=True, return_indices=True)
            if not len(ia):
                continue
            dz = beds[a][ia, 2] - beds[b][ib, 2]
            report["overlap"].append({"tiles": [a, b], "cells": len(ia), "median_m": float(np.median(dz)),
                                      "rms_m": float(np.sqrt(np.mean(dz**2))),
                                      "p95_abs_m": float(np.percentile(np.abs(dz), 95))})
    grid = np.concatenate(kept) if kept else np.zeros((0, 3))
    return grid, np.concatenate(owner) if owner else np.zeros(0, int), report

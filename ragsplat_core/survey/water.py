"""The water surface from points on its edge, as a surveyor measures them with RTK along both banks.

A river's surface falls downstream (0.1-1 % on gravel-bed rivers), and the field's correction takes a water
surface elevation per point for that reason (pyBathySfM interpolates it from such edge points). Here the
points give one level, the tilted plane z = level + sx x + sy y (`water_surface.WaterSurface`), or that plane
and a profile along the reach's main axis (`water_surface.Profile`: the medians of the plane's residuals in
stretches of at least `PROFILE_POINTS` points, a smooth curve through them), whichever the points support:
each is fitted robustly (Huber weights on the residuals' MAD, the worst points out beyond 3.5 of it) and
the model with the lowest Bayesian information criterion is kept, which asks a fall (a bend of the profile)
well above the points' scatter for each number more. Points along one bank only (a line) fix no cross
slope: the plane then tilts along that line alone.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from ragsplat.errors import DatasetError
from ragsplat.water_surface import Profile

MIN_SIGMA = 0.002  # m: a scatter below this (RTK's own) is not taken as a fit better than RTK can measure
OUTLIER = 3.5  # robust standard deviations
PROFILE_POINTS = 6  # edge points per stretch of a profile (both banks together); 3 stretches at least


@dataclass(frozen=True)
class EdgeFit:
    """The fitted surface (in the points' frame) and how the points lie around it."""

    kind: str  # "level", "plane" or "profile"
    level: float  # height at x = y = 0
    slope: tuple[float, float]  # (dz/dx, dz/dy); (0, 0) for one level
    residuals: np.ndarray  # [K] point z - surface height
    inliers: np.ndarray  # [K] bool
    bic: dict[str, float]  # of each model, on the inliers
    profile: Profile | None = None  # added to the plane ("profile")

    def report(self) -> dict:
        r = self.residuals[self.inliers]
        return {"kind": self.kind, "level_at_origin": self.level, "slope": list(self.slope),
                "profile": None if self.profile is None else {"stations": list(self.profile.stations),
                                                               "offsets": list(self.profile.offsets)},
                "fall_percent": 100 * math.hypot(*self.slope), "points": len(self.residuals),
                "inliers": int(self.inliers.sum()), "rms_m": float(np.sqrt(np.mean(r * r))),
                "max_abs_m": float(np.abs(r).max()), "bic": self.bic,
                "residual_m": [round(float(v), 4) for v in self.residuals]}


def _robust_lstsq(A: np.ndarray, z: np.ndarray, iterations: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """(coefficients, inliers) of A c ~ z by Huber-weighted least squares, then refitted on the inliers."""
    w = np.ones(len(z))
    for _ in range(iterations):
        c = np.linalg.lstsq(A * w[:, None], z * w, rcond=None)[0]
        r = z - A @ c
        sigma = max(1.4826 * np.median(np.abs(r - np.median(r))), MIN_SIGMA)
        w = np.sqrt(np.minimum(1.0, 1.345 * sigma / np.maximum(np.abs(r), 1e-12)))
    inliers = np.abs(r) <= OUTLIER * sigma
    c = np.linalg.lstsq(A[inliers], z[inliers], rcond=None)[0]
    return c, inliers


def fit_edge(points: np.ndarray) -> EdgeFit:
    """One level or a tilted plane through the water's edge points [K, 3] (see the module docstring).
    Raises DatasetError for fewer than 3 points or non-finite ones."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 3 or not np.isfinite(points).all():
        raise DatasetError(f"the water's edge needs at least 3 finite points x,y,z, got {points.shape}")
    mean = points.mean(0)
    xy = points[:, :2] - mean[:2]
    z = points[:, 2]
    # principal axes of the points: along the reach (u) and across it (v)
    _, s, vt = np.linalg.svd(xy, full_matrices=False)
    across = len(s) > 1 and s[1] > 0.05 * s[0]
    axes = vt if across else vt[:1]
    uv = xy @ axes.T  # [K, 1 or 2]
    ones = np.ones((len(z), 1))
    (c_level,), in_level = _robust_lstsq(ones, z)
    c_plane, in_plane = _robust_lstsq(np.hstack([ones, uv]), z)

    def bic(residual, k):  # on the points both fits keep, with the scatter floored at RTK's
        both = in_level & in_plane
        m = int(both.sum())
        rss = max(float(np.sum(residual[both] ** 2)), m * MIN_SIGMA**2)
        return m * math.log(rss / m) + k * math.log(m)

    r_level = z - c_level
    gradient = c_plane[1:] @ axes  # dz/d(x, y)
    r_plane = z - c_plane[0] - xy @ gradient
    scores = {"level": bic(r_level, 1), "plane": bic(r_plane, 1 + len(axes))}
    plane = (float(c_plane[0] - gradient @ mean[:2]), (float(gradient[0]), float(gradient[1])))
    profile = _profile(uv[:, 0], r_plane, in_plane, mean[:2], vt[0])
    if profile is not None:
        r_profile = r_plane - profile.value_and_slope(profile.along(points[:, :2]))[0]
        scores["profile"] = bic(r_profile, 1 + len(axes) + len(profile.stations))
    best = min(scores, key=scores.get)
    if math.hypot(*gradient) >= 1 or best == "level":
        return EdgeFit("level", float(c_level), (0.0, 0.0), r_level, in_level, scores)
    if best == "plane":
        return EdgeFit("plane", *plane, r_plane, in_plane, scores)
    return EdgeFit("profile", *plane, r_profile, in_plane & (np.abs(r_profile) <= OUTLIER * max(
        1.4826 * np.median(np.abs(r_profile[in_plane])), MIN_SIGMA)), scores, profile)


def _profile(u: np.ndarray, residual: np.ndarray, keep: np.ndarray, origin, direction) -> Profile | None:
    """The plane's residuals along the main axis as a `Profile`: the median residual and station of each
    stretch of `PROFILE_POINTS` kept points (None for fewer than 3 stretches)."""
    order = np.argsort(u[keep])
    bins = len(order) // PROFILE_POINTS
    if bins < 3:
        return None
    parts = np.array_split(order, bins)
    stations = np.array([np.median(u[keep][p]) for p in parts])
    offsets = np.array([np.median(residual[keep][p]) for p in parts])
    if not np.all(np.diff(stations) > 0):
        return None
    return Profile(tuple(origin), tuple(direction / np.linalg.norm(direction)), tuple(stations),
                   tuple(offsets))


def profile(points: np.ndarray, height: np.ndarray, axis_points: np.ndarray, bins: int = 5) -> list[dict]:
    """How points [P, 3] lie around the surface (`height` [P] of it under each) along the reach, in `bins`
    equal stretches of the main axis of `axis_points` [K, 2] (the edge points'): per stretch the count below
    and above it and the 1st percentile of heights above it (the lowest dry points, which a right surface
    puts just above zero everywhere along the reach)."""
    xy = np.asarray(axis_points, float)[:, :2]
    mean = xy.mean(0)
    u_axis = np.linalg.svd(xy - mean, full_matrices=False)[2][0]
    u = (points[:, :2] - mean) @ u_axis
    lo, hi = ((xy - mean) @ u_axis).min(), ((xy - mean) @ u_axis).max()
    edges = np.linspace(lo, hi, bins + 1)
    out = []
    for a, b in itertools.pairwise(edges):
        dz = points[(u >= a) & (u <= b), 2] - height[(u >= a) & (u <= b)]
        above = dz[dz >= 0]
        out.append({"from_m": round(float(a), 2), "to_m": round(float(b), 2), "below": int((dz < 0).sum()),
                    "above": len(above),
                    "lowest_above_m": float(np.percentile(above, 1)) if len(above) else None})
    return out


def start_level(points: np.ndarray) -> float:
    """Where the adjustment through the water starts looking for an unmeasured level: the 90th percentile of
    the heights of the aligned model's points [P, 3]. A pinhole model puts the submerged points at their
    apparent depths, between the bed and the surface, so most points lie below the level and the highest
    tenth are mostly dry ground near it; the adjustment converged from 0.8 m below and 3.7 m above on
    `small`."""
    return float(np.percentile(points[:, 2], 90))


# The shoreline's level: each point's neighbourhood and the heights searched around the start.
SHORE_NEIGHBOURS = 30  # a point's neighbours (horizontally) for its local plane
SHORE_STEP = 0.002  # m between the levels tried
SHORE_STRADDLING = 30  # neighbourhoods with points on both sides of the level: fewer find no shoreline
SHORE_RESAMPLES = 200  # bootstrap resamples of the neighbourhoods for the level's uncertainty
SHORE_BLOCK = 2.0  # the bootstrap's blocks, in neighbourhood radii
SHORE_SIGNIFICANCE = 3.0  # the bend's gain over the ground as seen, in standard errors, to be a shoreline


@dataclass(frozen=True)
class Shoreline:
    """The level at which the model's points stop bending, and how sure it is."""

    level: float
    sigma: float  # the bootstrap's standard deviation of `level` (m), at least one step
    straddling: int  # neighbourhoods with points above and below `level`
    span: tuple[float, float]  # the heights searched

    def report(self) -> dict:
        return {"level": self.level, "sigma_m": self.sigma, "straddling": self.straddling,
                "searched_m": list(self.span)}


def shoreline_level(points: np.ndarray, n: float, start: float, span: float) -> Shoreline | None:
    """The water's level from the shoreline in a pinhole model's points [P, 3] (z up, the frame level),
    searched within `start` +- `span`; None where too few points lie across the shore to find it.

    A camera that ignores refraction sees the ground under water raised: a point d below the level appears
    about d / n below it (near nadir). So the model's ground bends where it enters the water, its slope
    divided by n, and only the true level takes that bend out: for each level L tried, the points below L
    are put back to L + n (z - L), and the local planes (each point with its `SHORE_NEIGHBOURS` nearest,
    a point put back weighted 1 / n, as its noise grew n) fit best at the L the shore gives. Away from the
    shore a wrong L shifts whole neighbourhoods alike and costs nothing, so the minimum is set by ground
    that crosses the waterline, a beach or a bank, not by a flat bed. Oblique rays raise the ground more
    than 1 / n; the bend still starts at the level. The uncertainty is the spread of the minimum over the
    neighbourhoods resampled in blocks of ground (neighbouring ones share points).
    """
    from scipy.spatial import cKDTree

    pts = np.asarray(points, dtype=np.float64)
    levels = np.arange(start - span, start + span + SHORE_STEP / 2, SHORE_STEP)  # [L]
    near = (pts[:, 2] > levels[0] - span) & (pts[:, 2] < levels[-1] + span)
    if near.sum() <= SHORE_NEIGHBOURS:
        return None
    idx = cKDTree(pts[:, :2]).query(pts[near, :2], k=SHORE_NEIGHBOURS)[1]  # [Q, k], each point its own first
    xy = pts[idx, :2] - pts[near, None, :2]
    A = np.concatenate([np.ones(idx.shape + (1,)), xy], axis=2)  # [Q, k, 3]
    z = pts[idx, 2]  # [Q, k]
    cost = np.empty((len(idx), len(levels)))  # [Q, L]: each neighbourhood's squared residual at each level
    for j, L in enumerate(levels):
        below = z < L
        zt = np.where(below, L + n * (z - L), z)
        w = np.where(below, 1.0 / n, 1.0)  # residuals in the photos' terms: put back, a point's noise grows n
        Aw = A * w[..., None]
        c = np.linalg.solve(np.einsum("qki,qkj->qij", Aw, Aw), np.einsum("qki,qk->qi", Aw, zt * w))
        r = w * (zt - np.einsum("qki,qi->qk", A, c))
        cost[:, j] = np.sum(r * r, axis=1)
    unbent = np.sum((z - np.einsum("qki,qi->qk", A, np.einsum("qik,qk->qi", np.linalg.pinv(A), z))) ** 2, 1)
    # neighbourhoods overlap, so they are judged and resampled in blocks of ground several of them wide
    radius = np.sqrt(np.mean(np.sum(xy[:, -1] ** 2, axis=1)))  # to a neighbourhood's farthest point
    cell = np.floor(pts[near, :2] / (SHORE_BLOCK * max(radius, 1e-6))).astype(np.int64)
    block = np.unique(cell, axis=0, return_inverse=True)[1].ravel()
    per_block = np.stack([cost[block == b].sum(0) for b in range(block.max() + 1)])  # [B, L]
    gain = np.array([unbent[block == b].sum() for b in range(len(per_block))])[:, None] - per_block  # [B, L]
    gain = gain[np.ptp(gain, axis=1) > 1e-9 * max(float(unbent.sum()), 1e-300)]  # blocks the level touches
    if len(gain) < 2:
        return None
    best = int(np.argmax(gain.sum(0)))
    level = float(levels[best])
    straddling = int(np.sum((z.min(1) < level) & (z.max(1) > level)))
    # a bend the blocks agree on: the gain over the ground as seen, in its blocks' standard errors
    significance = gain[:, best].sum() / max(gain[:, best].std() * np.sqrt(len(gain)), 1e-300)
    if straddling < SHORE_STRADDLING or best in (0, len(levels) - 1) or significance < SHORE_SIGNIFICANCE:
        return None
    rng = np.random.default_rng(0)
    picks = [levels[np.argmax(gain[rng.integers(0, len(gain), len(gain))].sum(0))]
             for _ in range(SHORE_RESAMPLES)]
    return Shoreline(level, max(float(np.std(picks)), SHORE_STEP), straddling,
                     (float(levels[0]), float(levels[-1])))

"""Where a camera ray meets a horizontal plane under the water: the refracted footprint and the bent rays.

A ray leaving the camera at `angle` from the vertical crosses the water plane and continues at
asin(sin(angle) / n) (Snell), so over `altitude` metres of air and `depth` metres of water it travels
altitude tan(angle) + depth tan(asin(sin(angle) / n)) horizontally. Refraction makes the footprint on the
bed narrower than the dry (altitude + depth) tan(angle). numpy only: the flight planner uses it too.
"""

from __future__ import annotations

import math

import numpy as np


def ground_offset(angle: float, altitude: float, depth: float, n: float) -> float:
    """Horizontal distance (m) from the camera to where a ray at `angle` (rad from the downward vertical,
    < pi/2) meets the plane `depth` metres under the water, the camera `altitude` metres above it."""
    return altitude * math.tan(angle) + depth * math.tan(math.asin(math.sin(angle) / n))


def footprint(cameras, water, z: float) -> tuple[float, float, float, float]:
    """(xmin, xmax, ymin, ymax) where the image-corner rays of `cameras` meet the plane `z`, refracted at
    the water (`water`: a `WaterSurface`, or None) when it lies above the plane; rays that never reach the
    plane are ignored. A sloping surface is taken at its height under each camera (a bound for planning,
    not a ray trace). Raises ValueError when no ray does."""
    xs, ys = [], []
    for cam in cameras:
        corners = np.array([[0, 0], [cam.width, 0], [0, cam.height], [cam.width, cam.height]], float)
        centre = cam.camera_center
        rays = cam.unproject(corners, np.ones(4)) - centre  # [4, 3]
        level = None if water is None else float(water.height(centre[:2]))
        wet = water is not None and level > z and centre[2] > level
        altitude, depth, n = ((centre[2] - level, level - z, water.n) if wet
                              else (centre[2] - z, 0.0, 1.0))
        if altitude <= 0:
            continue
        for ray in rays:
            horizontal = math.hypot(ray[0], ray[1])
            if ray[2] >= 0:  # level or upward: never meets the plane below
                continue
            offset = ground_offset(math.atan2(horizontal, -ray[2]), altitude, depth, n)
            unit = ray[:2] / horizontal if horizontal > 0 else np.zeros(2)
            xs.append(centre[0] + unit[0] * offset)
            ys.append(centre[1] + unit[1] * offset)
    if not xs:
        raise ValueError(f"no camera sees the plane z = {z}")
    return float(min(xs)), float(max(xs)), float(min(ys)), float(max(ys))


def water_rays(camera, pixels: np.ndarray, water) -> tuple[np.ndarray, np.ndarray]:
    """The light paths under the water of `pixels` [M, 2] (continuous, centres at i + 0.5) of `camera`:
    (points [M, 3] where the rays cross the water's plane, unit directions [M, 3] inside the water, bent by
    Snell's law at its normal; `water`: a `WaterSurface`, flat or tilted). A camera ray that never reaches
    the plane from above gets NaN."""
    centre = camera.camera_center
    d = camera.unproject(np.asarray(pixels, float), np.ones(len(pixels))) - centre  # [M, 3], camera z = 1
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    sx, sy = (float(v) for v in water.slope)
    normal = np.array([-sx, -sy, 1.0]) / np.sqrt(1 + sx * sx + sy * sy)  # upward; exactly (0, 0, 1) when flat
    cos_i = -d @ normal
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(cos_i > 0, (float(water.level) - centre @ [-sx, -sy, 1.0]) / (d @ [-sx, -sy, 1.0]),
                     np.nan)
    origin = centre + t[:, None] * d
    # Snell in vector form: the part along the surface shrinks by 1 / n
    eta = 1.0 / float(water.n)
    cos_t = np.sqrt(1.0 - eta * eta * (1.0 - cos_i * cos_i))
    bent = eta * d + (eta * cos_i - cos_t)[:, None] * normal
    return origin, bent / np.linalg.norm(bent, axis=1, keepdims=True)


def closest_points(origins: np.ndarray, dirs: np.ndarray, group: np.ndarray, count: int,
                   min_angle: float = math.radians(1.0), weights: np.ndarray | None = None) -> np.ndarray:
    """[count, 3] least-squares intersection of the lines (origins [M, 3], unit dirs [M, 3]) of each group
    (group [M] in 0..count-1): the point that minimises the sum of squared distances to its lines, each
    squared distance times its line's weight (`weights` [M] >= 0; default 1). A group whose lines of
    positive weight span less than `min_angle` (or fewer than two such lines) is ill-posed: NaN."""
    w = np.ones(len(dirs)) if weights is None else np.asarray(weights, dtype=np.float64)
    P = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]  # [M, 3, 3] projectors across each line
    A, b, spread = np.zeros((count, 3, 3)), np.zeros((count, 3)), np.zeros((count, 3, 3))
    np.add.at(A, group, w[:, None, None] * P)
    np.add.at(b, group, w[:, None] * np.einsum("mij,mj->mi", P, origins))
    np.add.at(spread, group[w > 0], P[w > 0])
    lines = np.bincount(group[w > 0], minlength=count)
    # The smallest eigenvalue of sum(I - d d^T) / m is about sin^2 of the spread of the directions.
    floor = np.maximum(lines, 1) * math.sin(min_angle) ** 2 / 2
    ok = (lines >= 2) & (np.linalg.eigvalsh(spread)[:, 0] >= floor)
    ok &= np.linalg.eigvalsh(A)[:, 0] > 0  # weights may leave a well-spread group singular all the same
    out = np.full((count, 3), np.nan)
    out[ok] = np.linalg.solve(A[ok], b[ok][..., None])[..., 0]
    return out


def angular_residuals(points: np.ndarray, origins: np.ndarray, dirs: np.ndarray,
                      group: np.ndarray) -> np.ndarray:
    """[M] the angle (rad) at each line's origin between the line (origins [M, 3], unit dirs [M, 3]) and
    its group's point (points [count, 3], group [M]); over pi / 2 for a point behind the origin, NaN for a
    NaN point."""
    v = points[group] - origins
    along = np.einsum("mi,mi->m", v, dirs)
    across = np.linalg.norm(v - along[:, None] * dirs, axis=1)
    return np.arctan2(across, along)


def robust_closest_points(origins: np.ndarray, dirs: np.ndarray, group: np.ndarray, count: int,
                          min_angle: float = math.radians(1.0), iterations: int = 5,
                          cut: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """(points [count, 3], each group's robust angular spread [count], rad) of the lines of each group as
    `closest_points` intersects them, but weighted for noise in the lines' angles rather than in their
    distances, and robust to lines that belong elsewhere (iteratively reweighted least squares):

    - a line's squared distance to the point is divided by the squared length along it from its origin, so
      each line counts by its angular error: a ray bent by a ripple misses the bed by its angle times its
      path in the water, and a long oblique path would otherwise weigh more the more it misses;
    - that angular error is weighted by Cauchy's function, its scale `cut` times the median absolute
      angular residual of all lines (their common noise), so a line several times off counts little.

    The spread is the weighted rms of a group's angular residuals (NaN where its point is). NaN points as
    `closest_points`'s; a group whose lines all lose their weight is NaN too."""
    points = closest_points(origins, dirs, group, count, min_angle)
    for _ in range(iterations):
        angle = angular_residuals(points, origins, dirs, group)
        finite = np.isfinite(angle)
        if not finite.any():
            break
        scale = cut * max(float(np.median(angle[finite])), 1e-12)
        along = np.einsum("mi,mi->m", points[group] - origins, dirs)
        w = np.where(finite & (along > 0), 1.0 / (1.0 + (angle / scale) ** 2), 0.0)
        w /= np.where(w > 0, np.maximum(along, 1e-9) ** 2, 1.0)
        points = closest_points(origins, dirs, group, count, min_angle, weights=w)
    angle = angular_residuals(points, origins, dirs, group)
    finite = np.isfinite(angle)
    scale = cut * max(float(np.median(angle[finite])), 1e-12) if finite.any() else 1.0
    w = np.where(finite, 1.0 / (1.0 + (np.nan_to_num(angle) / scale) ** 2), 0.0)
    total = np.bincount(group, weights=w, minlength=count)
    with np.errstate(invalid="ignore", divide="ignore"):
        spread = np.sqrt(np.bincount(group, weights=w * np.nan_to_num(angle) ** 2, minlength=count) / total)
    spread[~np.isfinite(points).all(1)] = np.nan
    return points, spread

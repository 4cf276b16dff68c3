"""Where a camera ray meets a horizontal plane under flat water: the refracted footprint.

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
    the water (`water`: an object with `level` and `n`, or None) when it lies above the plane; rays that
    never reach the plane are ignored. Raises ValueError when no ray does."""
    xs, ys = [], []
    for cam in cameras:
        corners = np.array([[0, 0], [cam.width, 0], [0, cam.height], [cam.width, cam.height]], float)
        centre = cam.camera_center
        rays = cam.unproject(corners, np.ones(4)) - centre  # [4, 3]
        wet = water is not None and water.level > z and centre[2] > water.level
        altitude, depth, n = ((centre[2] - water.level, water.level - z, water.n) if wet
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

"""`tools.depth_precision` from physics: two parallel nadir cameras without water give stereo's
sqrt(2) Z^2 / (f B); through water at small angles, n times that at the apparent depth; half-size images
double it."""

import math

import numpy as np
import pytest

from ragsplat.camera import Camera
from ragsplat.water_surface import WaterSurface
from tools.depth_precision import sigma_z

H, B, DEPTH = 10.0, 0.2, 1.0


def pair(fov: float = 60.0):
    return [Camera.look_at((x, 0.0, H), (x, 0.0, 0.0), 400, 300, fov) for x in (-B / 2, B / 2)]


def test_stereo_without_water():
    cams = pair()
    sigma, seen = sigma_z(np.array([[0.0, 0.0, -DEPTH]]), cams, WaterSurface(0.0, 1.0))
    assert seen[0] == 2
    assert sigma[0] == pytest.approx(math.sqrt(2) * (H + DEPTH) ** 2 / (cams[0].fx * B), rel=1e-9)


def test_through_water_n_times_at_the_apparent_depth_and_half_size_doubles():
    cams, n = pair(), 1.33
    sigma, _ = sigma_z(np.array([[0.0, 0.0, -DEPTH]]), cams, WaterSurface(0.0, n))
    paraxial = n * math.sqrt(2) * (H + DEPTH / n) ** 2 / (cams[0].fx * B)
    assert sigma[0] == pytest.approx(paraxial, rel=1e-3)
    half, _ = sigma_z(np.array([[0.0, 0.0, -DEPTH]]), cams, WaterSurface(0.0, n), scale=0.5)
    assert half[0] == pytest.approx(2 * sigma[0], rel=1e-12)


def test_a_point_one_camera_sees_has_no_precision():
    sigma, seen = sigma_z(np.array([[0.0, 0.0, -DEPTH], [50.0, 0.0, -DEPTH]]), pair()[:1] + pair(5.0)[1:],
                          WaterSurface(0.0, 1.33))
    assert seen.tolist() == [2, 0] and np.isfinite(sigma[0]) and np.isinf(sigma[1])


def test_views_are_the_footprint_through_the_water():
    """A nadir camera's footprint: in air the pinhole's; under water the edge ray, bent toward the normal,
    reaches H tan(theta_a) + d tan(theta_w) on the bed, sin(theta_a) = n sin(theta_w), and no further."""
    from tools.depth_precision import views

    cam = Camera.look_at((0.0, 0.0, H), (0.0, 0.0, 0.0), 400, 300, 60.0)
    half = (cam.width / 2) / cam.fx  # tan of the half-angle across the width
    ta = math.atan(half)
    tw = math.asin(math.sin(ta) / 1.33)
    edge = H * half + DEPTH * math.tan(tw)  # where the image's edge ray meets the bed at DEPTH
    pts = np.array([[0.0, 0.0, -DEPTH], [0.99 * edge, 0.0, -DEPTH], [1.01 * edge, 0.0, -DEPTH],
                    [0.0, 0.0, H + 1.0]])  # the last behind the camera
    assert views(pts, [cam], WaterSurface(0.0, 1.33)).tolist() == [1, 1, 0, 0]
    air = (H + DEPTH) * half  # without water: the pinhole's own footprint
    assert views(np.array([[0.99 * air, 0, -DEPTH], [1.01 * air, 0, -DEPTH]]), [cam, cam],
                 WaterSurface(0.0, 1.0)).tolist() == [2, 0]
    assert edge < air  # bent toward the normal, the ray reaches less far on the bed

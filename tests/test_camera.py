"""Camera conventions: anything that a wrong axis, sign or half-pixel would break."""

import math

import numpy as np
import pytest
import torch

from ragsplat.camera import Camera, ground_sample_distance

NADIR_R = np.diag([1.0, -1.0, -1.0])  # camera x = world x, camera y = world -y, looks down world -z


def nadir(height=10.0, width=64, fov=90.0):
    return Camera.from_fov(width, width, fov, NADIR_R, -NADIR_R @ np.array([0.0, 0.0, height]))


def test_point_on_optical_axis_lands_on_principal_point():
    cam = Camera.look_at([3.0, -2.0, 7.0], [1.0, 1.0, -1.0], 80, 60, 70.0)
    on_axis = cam.camera_center + 5.0 * cam.R[2]  # 5 m along the viewing direction
    uv, depth = cam.project(on_axis[None])
    np.testing.assert_allclose(uv[0], [cam.cx, cam.cy], atol=1e-9)
    np.testing.assert_allclose(depth, [5.0], atol=1e-12)
    assert (cam.cx, cam.cy) == (40.0, 30.0)  # centre of an 80 x 60 image with pixel centres at i + 0.5


def test_nadir_projection_matches_hand_computation():
    # 90 degree fov on 64 px: f = 32. Camera 10 m above the origin looking down.
    cam = nadir()
    assert cam.fx == pytest.approx(32.0)
    uv, depth = cam.project(np.array([[2.0, 1.0, -5.0]]))
    # depth 15 m; world +x is image right, world +y is image up (row index decreases).
    np.testing.assert_allclose(depth, [15.0])
    np.testing.assert_allclose(uv[0], [32 + 32 * 2 / 15, 32 - 32 * 1 / 15])


def test_look_at_nadir_equals_explicit_nadir():
    cam = Camera.look_at([0.0, 0.0, 10.0], [0.0, 0.0, 0.0], 64, 64, 90.0)
    np.testing.assert_allclose(cam.R, NADIR_R, atol=1e-12)


def test_tilted_camera_projection_matches_hand_computation():
    # Camera at height 10 tilted 30 degrees from nadir towards +y, looking at (0, 10 tan 30, 0).
    tilt = math.radians(30)
    target = [0.0, 10 * math.tan(tilt), 0.0]
    cam = Camera.look_at([0.0, 0.0, 10.0], target, 100, 100, 60.0)
    f = 50 / math.tan(math.radians(30))
    # The ground point at y = 10 tan(60 deg) is 30 degrees above the axis in the image (towards the top).
    y_ground = 10 * math.tan(math.radians(60))
    uv, depth = cam.project(np.array([[0.0, y_ground, 0.0]]))
    np.testing.assert_allclose(uv[0], [50.0, 50 - f * math.tan(tilt)], atol=1e-9)
    dist = math.hypot(10.0, y_ground)
    np.testing.assert_allclose(depth, [dist * math.cos(tilt)], atol=1e-9)
    # Tilting towards +y: the camera's viewing direction has a +y and a -z component.
    np.testing.assert_allclose(cam.R[2], [0.0, math.sin(tilt), -math.cos(tilt)], atol=1e-12)


def test_ground_sample_distance_at_the_water():
    # nadir at 10 m over a plane at z = -2 (90 degrees over 64 px: fx = 32): 12 m / 32 px
    assert ground_sample_distance([nadir(10.0)], -2.0) == pytest.approx(12.0 / 32)
    # tilted 40 degrees: the axis meets the plane 12 / cos 40 m away, which is also that point's z-depth
    tilted = Camera.look_at([0.0, 0.0, 10.0], [0.0, 12 * math.tan(math.radians(40)), -2.0], 64, 64, 90.0)
    assert ground_sample_distance([tilted], -2.0) == pytest.approx(12.0 / math.cos(math.radians(40)) / 32)
    # the median over the views; a camera below the plane or looking up does not count
    up = Camera.look_at([0.0, 0.0, 10.0], [0.0, 0.0, 20.0], 64, 64, 90.0, up=(0.0, 1.0, 0.0))
    views = [nadir(10.0), nadir(14.0), nadir(18.0), up, nadir(-5.0)]
    assert ground_sample_distance(views, -2.0) == pytest.approx(16.0 / 32)
    assert ground_sample_distance([up], -2.0) is None


def test_c2w_round_trip_and_blender_axes():
    cam = Camera.look_at([4.0, 5.0, 20.0], [0.5, -1.0, -9.0], 120, 90, 70.0)
    c2w = cam.c2w_gl
    # OpenGL camera looks down its local -z: the third column points away from the view direction.
    np.testing.assert_allclose(-c2w[:3, 2], cam.R[2], atol=1e-12)
    np.testing.assert_allclose(c2w[:3, 3], [4.0, 5.0, 20.0], atol=1e-12)
    back = Camera.from_c2w_gl(c2w, 120, 90, intrinsics=(cam.fx, cam.fy, cam.cx, cam.cy))
    np.testing.assert_allclose(back.R, cam.R, atol=1e-12)
    np.testing.assert_allclose(back.t, cam.t, atol=1e-12)
    np.testing.assert_allclose(back.c2w_gl, c2w, atol=1e-12)
    np.testing.assert_allclose(np.linalg.inv(cam.w2c), c2w @ np.diag([1.0, -1, -1, 1]), atol=1e-12)


def test_blender_default_camera_looks_down_when_identity():
    # A Blender camera with identity rotation looks straight down world -z with image up = world +y.
    cam = Camera.from_c2w_gl(np.eye(4) + np.diag([0, 0, 0, 0]), 64, 64, fov_x_deg=90.0)
    np.testing.assert_allclose(cam.R, NADIR_R, atol=1e-12)


def test_unproject_inverts_project():
    cam = Camera.look_at([1.0, 2.0, 12.0], [0.0, 0.0, -10.0], 64, 48, 70.0)
    pts = np.random.default_rng(0).uniform([-5, -5, -12], [5, 5, -8], size=(50, 3))
    uv, depth = cam.project(pts)
    np.testing.assert_allclose(cam.unproject(uv, depth), pts, atol=1e-9)


def test_torch_and_numpy_agree():
    cam = Camera.look_at([1.0, 2.0, 12.0], [0.0, 0.0, -10.0], 64, 48, 70.0)
    pts = np.random.default_rng(1).normal(size=(10, 3))
    uv_np, d_np = cam.project(pts)
    uv_t, d_t = cam.project(torch.tensor(pts, dtype=torch.float32))
    assert uv_t.dtype == torch.float32
    np.testing.assert_allclose(uv_t.numpy(), uv_np, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(d_t.numpy(), d_np, rtol=1e-5)


def test_dict_round_trip():
    cam = Camera.look_at([1.0, 2.0, 12.0], [0.0, 0.0, -10.0], 64, 48, 70.0)
    back = Camera.from_dict(cam.to_dict())
    np.testing.assert_array_equal(back.w2c, cam.w2c)
    assert back.fov_x_deg == pytest.approx(70.0)


@pytest.mark.parametrize("fov", [0.0, 180.0, -10.0, float("nan"), 200.0])
def test_fov_out_of_range_raises(fov):
    with pytest.raises(ValueError, match="field of view"):
        Camera.from_fov(64, 64, fov, np.eye(3), np.zeros(3))


def test_non_finite_pose_raises():
    with pytest.raises(ValueError, match="finite"):
        Camera.from_fov(64, 64, 70.0, np.eye(3), [0.0, float("inf"), 0.0])
    c2w = np.eye(4)
    c2w[0, 3] = float("nan")
    with pytest.raises(ValueError, match="finite"):
        Camera.from_c2w_gl(c2w, 64, 64, fov_x_deg=70.0)


def test_non_orthonormal_rotation_raises():
    with pytest.raises(ValueError, match="orthonormal"):
        Camera.from_fov(64, 64, 70.0, np.diag([1.0, 1.0, 1.1]), np.zeros(3))
    with pytest.raises(ValueError, match="orthonormal"):
        Camera.from_fov(64, 64, 70.0, np.diag([1.0, 1.0, -1.0]), np.zeros(3))  # a reflection
    c2w = np.eye(4)
    c2w[:3, :3] *= 2.0
    with pytest.raises(ValueError, match="orthonormal"):
        Camera.from_c2w_gl(c2w, 64, 64, fov_x_deg=70.0)


def test_bad_intrinsics_raise():
    with pytest.raises(ValueError, match="image size"):
        Camera(0, 64, 10.0, 10.0, 0.0, 32.0, np.eye(3), np.zeros(3))
    with pytest.raises(ValueError, match="focal"):
        Camera(64, 64, -10.0, 10.0, 32.0, 32.0, np.eye(3), np.zeros(3))
    with pytest.raises(ValueError, match="up"):
        Camera.look_at([0, 0, 10.0], [0, 0, 0.0], 64, 64, 70.0, up=(0, 0, 1.0))


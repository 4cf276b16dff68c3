"""Backscatter (issue 50): each pixel's in-water length from its rendered depth, from physics, and the veil
B_inf (1 - exp(-c_b L)) it adds in linear light."""

import math

import pytest
import torch

from ragsplat_core.refraction import (
    WaterSurface,
    add_backscatter,
    apparent_points,
    linear_to_srgb,
    pixel_water_paths,
    plane_frame,
    srgb_to_linear,
    water_paths,
)

f64 = torch.float64
CAM = torch.tensor([1.0, -2.0, 30.0], dtype=f64)
WATER = WaterSurface(level=0.5, n=1.33)
H = float(CAM[2]) - WATER.level


def seen(true_points, water=WATER, scale=0.37):
    """(rays [N, 3], depth [N]) of the pixels that render the apparent images of true_points: P' = C + depth
    ray, the ray's length arbitrary (a camera's unit-z rays are not unit)."""
    p = apparent_points(true_points, CAM, water)
    return (p - CAM) * scale, torch.full((len(p),), 1 / scale, dtype=f64)


def test_nadir_path_is_n_times_the_apparent_depth():
    rays = torch.tensor([[0.0, 0.0, -1.0]], dtype=f64)
    d_app = 2.5
    L = pixel_water_paths(rays, torch.tensor([H + d_app], dtype=f64), CAM, WATER)
    assert float(L[0]) == pytest.approx(WATER.n * d_app, rel=1e-14)


@pytest.mark.parametrize("theta_a", [5.0, 30.0, 60.0, 80.0])
def test_path_at_a_known_air_angle_is_depth_over_cos_theta_w(theta_a):
    """The true point built forwards by Snell; its apparent point found by the forward transform: the pixel
    that renders it gets the bent ray's length d / cos(theta_w), the same as `water_paths` of the true point."""
    d, az = 6.0, 0.7
    ta = math.radians(theta_a)
    tw = math.asin(math.sin(ta) / WATER.n)
    r = H * math.tan(ta) + d * math.tan(tw)
    p = torch.tensor([[CAM[0] + r * math.cos(az), CAM[1] + r * math.sin(az), WATER.level - d]], dtype=f64)
    L = pixel_water_paths(*seen(p), CAM, WATER)
    assert float(L[0]) == pytest.approx(d / math.cos(tw), rel=1e-10)
    # the closed form in the angles: n d' cos^2(theta_w) / cos^3(theta_a)
    d_app = WATER.level - float(apparent_points(p, CAM, WATER)[0, 2])
    assert float(L[0]) == pytest.approx(WATER.n * d_app * math.cos(tw) ** 2 / math.cos(ta) ** 3, rel=1e-10)


def test_matches_the_true_points_paths_everywhere():
    g = torch.Generator().manual_seed(0)
    p = torch.cat([(torch.rand(200, 2, generator=g, dtype=f64) - 0.5) * 120,
                   WATER.level - 0.01 - 15 * torch.rand(200, 1, generator=g, dtype=f64)], 1)
    torch.testing.assert_close(pixel_water_paths(*seen(p), CAM, WATER), water_paths(p, CAM, WATER), rtol=1e-10,
                               atol=1e-12)


def test_n_one_is_the_straight_ray_below_the_level():
    water = WaterSurface(WATER.level, 1.0)
    g = torch.Generator().manual_seed(1)
    p = torch.cat([(torch.rand(50, 2, generator=g, dtype=f64) - 0.5) * 80,
                   WATER.level - 0.01 - 15 * torch.rand(50, 1, generator=g, dtype=f64)], 1)
    u = (WATER.level - p[:, 2]) / (CAM[2] - p[:, 2])
    rays, depth = (p - CAM) * 0.1, torch.full((50,), 10.0, dtype=f64)
    torch.testing.assert_close(pixel_water_paths(rays, depth, CAM, water), u * torch.linalg.norm(CAM - p, dim=1),
                               rtol=1e-12, atol=0)


def test_no_path_above_the_level_or_where_nothing_is_rendered():
    rays = torch.tensor([[0.1, 0.0, -1.0], [0.1, 0.0, -1.0], [0.3, 0.2, -1.0], [0.0, 0.0, -1.0],
                         [1.0, 0.0, 0.2]], dtype=f64)  # the last looks up
    depth = torch.tensor([H - 3, H, H + 2, 0.0, 5.0], dtype=f64)  # a bank, the level, under water, empty
    L = pixel_water_paths(rays.requires_grad_(), depth.requires_grad_(), CAM, WATER)
    assert L[0] == 0 and L[1] == 0 and L[2] > 2 and L[3] == 0 and L[4] == 0
    L.sum().backward()
    assert torch.isfinite(rays.grad).all() and torch.isfinite(depth.grad).all()
    assert depth.grad[0] == 0 and depth.grad[2] > 0


def test_tilted_plane_is_exact_in_its_frame():
    water = WaterSurface(0.3, 1.33, (-0.02, 0.01))
    g = torch.Generator().manual_seed(2)
    p = torch.cat([(torch.rand(40, 2, generator=g, dtype=f64) - 0.5) * 40,
                   -1 - 10 * torch.rand(40, 1, generator=g, dtype=f64)], 1)
    L = pixel_water_paths(*seen(p, water), CAM, water)
    torch.testing.assert_close(L, water_paths(p, CAM, water), rtol=1e-10, atol=1e-12)
    R, p0 = plane_frame(water, p)  # and the flat case in the plane's frame
    rays, depth = seen(p, water)
    torch.testing.assert_close(L, pixel_water_paths(rays @ R.T, depth, R @ (CAM - p0), WaterSurface(0.0, 1.33)),
                               rtol=1e-12, atol=1e-12)


def test_gradients_match_finite_differences():
    g = torch.Generator().manual_seed(3)
    p = torch.cat([(torch.rand(6, 2, generator=g, dtype=f64) - 0.5) * 50,
                   WATER.level - 0.5 - 10 * torch.rand(6, 1, generator=g, dtype=f64)], 1)
    p[0, :2] = CAM[:2]  # nadir
    level = torch.tensor(WATER.level, dtype=f64, requires_grad=True)
    for water in (WATER, WaterSurface(0.3, 1.33, (-0.02, 0.01))):
        rays, depth = seen(p, water)
        assert torch.autograd.gradcheck(
            lambda r, z, c, lv, water=water: pixel_water_paths(r, z, c, WaterSurface(lv, water.n, water.slope)),
            (rays.requires_grad_(), depth.requires_grad_(), CAM.clone().requires_grad_(), level),
            eps=1e-6, atol=1e-7, rtol=1e-6)


# ---- the veil ----------------------------------------------------------------------------------------------
VEIL = torch.tensor([0.05, 0.12, 0.1], dtype=f64)
CB = torch.tensor([0.3, 0.2, 0.25], dtype=f64)


def test_veil_in_linear_light_only_where_there_is_water():
    g = torch.Generator().manual_seed(4)
    image = torch.rand(4, 5, 3, generator=g, dtype=f64)
    alpha = torch.rand(4, 5, 1, generator=g, dtype=f64)
    L = 5 * torch.rand(4, 5, generator=g, dtype=f64)
    L[0] = 0  # a bank row
    out = add_backscatter(image, alpha, L, VEIL, CB)
    want = srgb_to_linear(image) + alpha * VEIL * (1 - torch.exp(-CB * L[..., None]))
    torch.testing.assert_close(srgb_to_linear(out), want, rtol=1e-12, atol=1e-15)
    torch.testing.assert_close(out[0], image[0], rtol=1e-12, atol=1e-15)  # no water, no veil
    deep = add_backscatter(image, torch.ones_like(alpha), torch.full_like(L, 1e4), VEIL, CB)
    torch.testing.assert_close(deep, linear_to_srgb(srgb_to_linear(image) + VEIL))  # B_inf at infinite depth
    assert torch.equal(add_backscatter(image, torch.zeros_like(alpha), L, VEIL, CB), linear_to_srgb(
        srgb_to_linear(image)))  # the background's share is left as it is


def test_veil_gradients_match_finite_differences():
    g = torch.Generator().manual_seed(5)
    args = (0.1 + 0.8 * torch.rand(3, 4, 3, generator=g, dtype=f64), torch.rand(3, 4, 1, generator=g, dtype=f64),
            0.1 + 3 * torch.rand(3, 4, generator=g, dtype=f64), VEIL.clone(), CB.clone())
    assert torch.autograd.gradcheck(add_backscatter, [a.requires_grad_() for a in args], eps=1e-6, atol=1e-7,
                                    rtol=1e-6)

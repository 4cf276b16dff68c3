"""Attenuation along the refracted path (issue 50): the in-water length from physics, its colour factor in
`refract_gaussians`, and the coefficients trained, saved and restored by the trainer."""

import math

import pytest
import torch

from ragsplat_core.refraction import (
    WaterSurface,
    linear_to_srgb,
    plane_frame,
    refract_gaussians,
    srgb_to_linear,
    water_paths,
)

f64 = torch.float64
CAM = torch.tensor([1.0, -2.0, 30.0], dtype=f64)
WATER = WaterSurface(level=0.5, n=1.33)
H = float(CAM[2]) - WATER.level


def point_from_air_angle(theta_a_deg, d, n=WATER.n, azimuth=0.7):
    """True point whose refracted ray leaves the water at air angle theta_a (built forwards by Snell), and the
    water angle theta_w."""
    ta = math.radians(theta_a_deg)
    tw = math.asin(math.sin(ta) / n)
    r = H * math.tan(ta) + d * math.tan(tw)
    p = torch.tensor([[CAM[0] + r * math.cos(azimuth), CAM[1] + r * math.sin(azimuth), WATER.level - d]], dtype=f64)
    return p, tw


def test_nadir_path_is_the_depth():
    p = torch.tensor([[CAM[0], CAM[1], WATER.level - 4.0]], dtype=f64)
    assert float(water_paths(p, CAM, WATER)[0]) == pytest.approx(4.0, rel=0, abs=1e-14)


@pytest.mark.parametrize("theta_a", [5.0, 30.0, 60.0, 85.0])
def test_path_is_depth_over_cos_of_the_snell_angle(theta_a):
    d = 7.0
    p, tw = point_from_air_angle(theta_a, d)
    L = float(water_paths(p, CAM, WATER)[0])
    assert L == pytest.approx(d / math.cos(tw), rel=1e-12)
    # the same length measured as a distance: from the point to where the air ray meets the surface
    s = H * math.tan(math.radians(theta_a))
    hit = CAM[:2] + s * torch.tensor([math.cos(0.7), math.sin(0.7)], dtype=f64)
    leg = torch.cat([p[0, :2] - hit, torch.tensor([d], dtype=f64)])
    assert L == pytest.approx(float(torch.linalg.norm(leg)), rel=1e-12)


def test_n_one_is_the_straight_ray_below_the_level():
    water = WaterSurface(WATER.level, 1.0)
    g = torch.Generator().manual_seed(0)
    p = torch.cat([(torch.rand(50, 2, generator=g, dtype=f64) - 0.5) * 80,
                   WATER.level - 0.01 - 15 * torch.rand(50, 1, generator=g, dtype=f64)], 1)
    u = (WATER.level - p[:, 2]) / (CAM[2] - p[:, 2])  # the fraction of the straight ray below the level
    want = u * torch.linalg.norm(CAM - p, dim=1)
    torch.testing.assert_close(water_paths(p, CAM, water), want, rtol=1e-12, atol=0)


def test_points_above_the_surface_have_no_path():
    p = torch.tensor([[0.0, 0.0, WATER.level], [3.0, 1.0, WATER.level + 2.0], [3.0, 1.0, WATER.level - 1.0]],
                     dtype=f64)
    L = water_paths(p, CAM, WATER)
    assert L[0] == 0 and L[1] == 0 and L[2] > 1.0


def test_tilted_plane_is_the_flat_case_in_its_frame():
    water = WaterSurface(0.3, 1.33, (-0.02, 0.01))
    g = torch.Generator().manual_seed(1)
    p = torch.cat([(torch.rand(40, 2, generator=g, dtype=f64) - 0.5) * 40,
                   -1 - 10 * torch.rand(40, 1, generator=g, dtype=f64)], 1)
    R, p0 = plane_frame(water, p)
    flat = water_paths((p - p0) @ R.T, R @ (CAM - p0), WaterSurface(0.0, 1.33))
    torch.testing.assert_close(water_paths(p, CAM, water), flat, rtol=1e-12, atol=1e-12)
    assert (flat > 0).all()


def test_gradients_match_finite_differences():
    g = torch.Generator().manual_seed(2)
    p = torch.cat([(torch.rand(6, 2, generator=g, dtype=f64) - 0.5) * 50,
                   WATER.level - 0.5 - 10 * torch.rand(6, 1, generator=g, dtype=f64)], 1)
    p[0, :2] = CAM[:2]  # nadir
    for water in (WATER, WaterSurface(0.3, 1.33, (-0.02, 0.01))):
        assert torch.autograd.gradcheck(lambda x, c, water=water: water_paths(x, c, water),
                                        (p.clone().requires_grad_(), CAM.clone().requires_grad_()),
                                        eps=1e-6, atol=1e-7, rtol=1e-6)


# ---- the colour factor in refract_gaussians -------------------------------------------------------------------
def _gaussians(n=30, seed=3):
    g = torch.Generator().manual_seed(seed)
    means = torch.cat([(torch.rand(n, 2, generator=g, dtype=f64) - 0.5) * 30,
                       WATER.level + 1 - 6 * torch.rand(n, 1, generator=g, dtype=f64)], 1)  # some above the level
    scales = 0.05 + 0.1 * torch.rand(n, 3, generator=g, dtype=f64)
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g, dtype=f64), dim=-1)
    return means, scales, quats, 0.2 + 0.7 * torch.rand(n, generator=g, dtype=f64), \
        torch.rand(n, 3, generator=g, dtype=f64)


C = torch.tensor([0.4, 0.1, 0.05], dtype=f64)  # 1/m: a red-absorbing river


@pytest.mark.parametrize("flags", [{"scale": "anisotropic", "color": False}, {"scale": "isotropic", "color": True},
                                   {"position": False, "scale": "none", "opacity": False}])
def test_attenuation_multiplies_submerged_radiance_by_exp_minus_c_l(flags):
    g = _gaussians()
    plain = refract_gaussians(*g, CAM, WATER, **flags)
    out = refract_gaussians(*g, CAM, WATER, **flags, attenuation=C)
    for name in ("means", "scales", "quats", "opacities", "covars", "jacobians"):
        a, b = getattr(plain, name), getattr(out, name)
        assert (a is None and b is None) or torch.equal(a, b), name
    dry = g[0][:, 2] >= WATER.level
    assert dry.any() and (~dry).any()
    assert torch.equal(out.colors[dry], plain.colors[dry])
    factor = torch.exp(-C * water_paths(g[0], CAM, WATER)[:, None])
    torch.testing.assert_close(srgb_to_linear(out.colors), srgb_to_linear(plain.colors) * factor, rtol=1e-12,
                               atol=1e-15)


def test_no_attenuation_is_todays_transform_bit_for_bit():
    g = _gaussians()
    for flags in ({}, {"scale": "anisotropic"}, {"scale": "none"}, {"color": True}):
        a = refract_gaussians(*g, CAM, WATER, **flags)
        b = refract_gaussians(*g, CAM, WATER, **flags, attenuation=None)
        assert all(torch.equal(x, y) for x, y in zip(a, b) if x is not None)


def test_attenuation_alone_at_n_one_and_under_a_tilted_plane():
    g = _gaussians()
    water = WaterSurface(WATER.level, 1.0)
    out = refract_gaussians(*g, CAM, water, attenuation=C)
    assert torch.equal(out.means, g[0]) and torch.equal(out.opacities, g[3])
    want = linear_to_srgb(srgb_to_linear(g[4]) * torch.exp(-C * water_paths(g[0], CAM, water)[:, None]))
    torch.testing.assert_close(out.colors, want, rtol=1e-12, atol=1e-15)
    tilted = WaterSurface(WATER.level, 1.33, (0.01, -0.03))
    plain = refract_gaussians(*g, CAM, tilted, scale="anisotropic")
    out = refract_gaussians(*g, CAM, tilted, scale="anisotropic", attenuation=C)
    factor = torch.exp(-C * water_paths(g[0], CAM, tilted)[:, None])
    torch.testing.assert_close(srgb_to_linear(out.colors), srgb_to_linear(plain.colors) * factor, rtol=1e-12,
                               atol=1e-15)
    assert torch.equal(out.means, plain.means)


def test_gradients_reach_the_coefficients_and_the_gaussians():
    g = [t.clone().requires_grad_() for t in _gaussians(8)]
    c = C.clone().requires_grad_()

    def f(means, colors, c):
        return refract_gaussians(means, g[1], g[2], g[3], colors, CAM, WATER, scale="anisotropic",
                                 attenuation=c).colors

    assert torch.autograd.gradcheck(f, (g[0], g[4], c), eps=1e-6, atol=1e-7, rtol=1e-6)
    f(g[0], g[4], c).sum().backward()
    assert float(c.grad.abs().min()) > 0  # every channel sees submerged Gaussians
    wet = g[0][:, 2] < WATER.level
    assert (g[0].grad[wet, 2] != 0).all()  # a deeper Gaussian is darker: its depth has a colour gradient

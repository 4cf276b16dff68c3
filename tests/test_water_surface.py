"""A sloping water surface (a river's): the tilted plane's transform, tested from physics (Snell's law with
the tilted normal, RA-GS's apparent depth along it, rotation equivariance) and against the horizontal
plane."""

import math

import numpy as np
import pytest
import torch

from ragsplat.dataset.layout import water_json
from ragsplat.refraction import (
    apparent_jacobian,
    apparent_points,
    apparent_points_each,
    covariance,
    opacity_factor,
    refract_gaussians,
)
from ragsplat.water_surface import Profile, WaterSurface

f64 = torch.float64
CAM = torch.tensor([1.0, -2.0, 12.0], dtype=f64)
TILTED = WaterSurface(level=0.5, n=1.33, slope=(-0.01, 0.004))  # 1 % fall along +x, a little across


def below(water, n=300, seed=0, depth=(0.02, 6.0), radius=20.0):
    g = torch.Generator().manual_seed(seed)
    xy = (torch.rand(n, 2, generator=g, dtype=f64) - 0.5) * 2 * radius
    d = depth[0] + torch.rand(n, generator=g, dtype=f64) * (depth[1] - depth[0])
    return torch.cat([xy, (water.height(xy) - d)[:, None]], -1)


def unit_normal(water):
    sx, sy = water.slope
    v = torch.tensor([-sx, -sy, 1.0], dtype=f64)
    return v / v.norm()


def test_horizontal_surface_is_todays_transform_exactly():
    p = below(WaterSurface(0.5, 1.33))
    flat = WaterSurface(0.5, 1.33, slope=(0.0, 0.0))
    assert not flat.tilted and flat == WaterSurface(0.5, 1.33)
    q = refract_gaussians(p, torch.full_like(p, 0.05),
                          torch.tensor([[1.0, 0, 0, 0]], dtype=f64).expand(len(p), 4),
                          torch.full((len(p),), 0.5, dtype=f64), torch.rand(len(p), 3, dtype=f64), CAM, flat,
                          scale="anisotropic")
    r = refract_gaussians(p, torch.full_like(p, 0.05),
                          torch.tensor([[1.0, 0, 0, 0]], dtype=f64).expand(len(p), 4),
                          torch.full((len(p),), 0.5, dtype=f64), torch.rand(len(p), 3, dtype=f64), CAM,
                          WaterSurface(0.5, 1.33), scale="anisotropic")
    assert torch.equal(q.means, r.means) and torch.equal(q.jacobians, r.jacobians)


def test_a_vanishing_tilt_tends_to_the_flat_transform():
    p = below(WaterSurface(0.5, 1.33))
    flat = apparent_points(p, CAM, WaterSurface(0.5, 1.33))
    tiny = apparent_points(p, CAM, WaterSurface(0.5, 1.33, slope=(1e-12, -1e-12)))
    assert torch.allclose(tiny, flat, rtol=0, atol=1e-9)


@pytest.mark.parametrize("theta_a", [0.0, 10.0, 35.0, 60.0])
def test_snell_holds_at_the_tilted_interface_and_the_depth_is_rags_along_the_normal(theta_a):
    """Build the true point forwards: an air ray at theta_a from the tilted normal, bent by Snell's law at the
    surface, followed for a distance under it. The transform must put the apparent point on that air ray, at
    RA-GS's apparent depth d' = d (cos ta / cos tw)^3 / n along the normal (d the true one along it)."""
    water = TILTED
    N = unit_normal(water)
    n = water.n
    # an air direction at theta_a from -N, turned a little about it
    e1 = torch.linalg.cross(N, torch.tensor([0.3, 1.0, 0.0], dtype=f64))
    e1 = e1 / e1.norm()
    ta = math.radians(theta_a)
    air = -math.cos(ta) * N + math.sin(ta) * e1
    t = (water.height(CAM[None, :2])[0]
         - CAM[2]) / (air @ torch.tensor([-water.slope[0], -water.slope[1], 1.0],
                                                                       dtype=f64))
    hit = CAM + t * air  # on the plane: N . (hit - p0) = 0
    assert float(water.depth(hit[None])[0]) == pytest.approx(0, abs=1e-12)
    tw = math.asin(math.sin(ta) / n)
    wet_dir = -math.cos(tw) * N + math.sin(tw) * e1
    d_normal = 2.5
    p = hit + d_normal / math.cos(tw) * wet_dir
    q = apparent_points(p[None], CAM, water)[0]
    # on the air ray through the interface point
    to_q = q - CAM
    assert float(torch.linalg.norm(torch.linalg.cross(to_q, air))) == pytest.approx(0, abs=1e-9)
    # at RA-GS's apparent depth along the normal
    d_app = float(-(q - hit) @ N)
    expected = d_normal * (math.cos(ta) / math.cos(tw)) ** 3 / n
    assert d_app == pytest.approx(expected, rel=1e-10)


def test_equivariant_under_any_rotation_about_the_normal():
    """The transform must not depend on which frame of the plane is used: a tilted world rotated about the
    normal through a point of the surface gives the rotated apparent points."""
    water = TILTED
    N = unit_normal(water)
    p = below(water, n=80)
    phi = 0.9
    K = torch.tensor([[0, -N[2], N[1]], [N[2], 0, -N[0]], [-N[1], N[0], 0]], dtype=f64)
    Rot = torch.eye(3, dtype=f64) + math.sin(phi) * K + (1 - math.cos(phi)) * K @ K  # about N
    o = torch.tensor([3.0, -1.0, 0.0], dtype=f64)
    o[2] = water.height(o[None, :2])[0]  # a point of the surface: the rotated plane is the same plane
    turn = lambda x: (x - o) @ Rot.T + o
    a = turn(apparent_points(p, CAM, water))
    b = apparent_points(turn(p), turn(CAM[None])[0], water)
    assert torch.allclose(a, b, rtol=0, atol=1e-10)


def test_n_one_is_the_pinhole_and_points_above_stay_exactly():
    p = below(TILTED)
    assert torch.allclose(apparent_points(p, CAM, WaterSurface(0.5, 1.0, TILTED.slope)), p, rtol=0,
                          atol=1e-12)
    above = p.clone()
    above[:, 2] = TILTED.height(p[:, :2]) + 0.3
    assert torch.equal(apparent_points(above, CAM, TILTED), above)


def test_tilted_jacobian_matches_differences_and_the_gaussians_use_it():
    p = below(TILTED, n=40)
    J = apparent_jacobian(p, CAM, TILTED)
    eps = 1e-6
    for k in range(3):
        e = torch.zeros(3, dtype=f64)
        e[k] = eps
        col = (apparent_points(p + e, CAM, TILTED) - apparent_points(p - e, CAM, TILTED)) / (2 * eps)
        assert torch.allclose(J[:, :, k], col, rtol=0, atol=1e-7)
    quats = torch.nn.functional.normalize(torch.rand(len(p), 4, dtype=f64), dim=-1)
    scales = torch.rand(len(p), 3, dtype=f64) * 0.1
    out = refract_gaussians(p, scales, quats, torch.full((len(p),), 0.6, dtype=f64),
                            torch.rand(len(p), 3, dtype=f64), CAM, TILTED, scale="anisotropic")
    assert torch.allclose(out.jacobians, J, rtol=0, atol=1e-12)
    assert torch.allclose(out.covars, J @ covariance(quats, scales) @ J.transpose(1, 2), rtol=0, atol=1e-14)
    assert torch.allclose(out.means, apparent_points(p, CAM, TILTED), rtol=0, atol=1e-12)
    assert torch.allclose(out.opacities, 0.6 * opacity_factor(p, TILTED), rtol=0, atol=1e-15)


def test_gradients_reach_level_slope_and_n():
    p = below(TILTED, n=6, depth=(0.5, 4.0))
    level = torch.tensor(0.5, dtype=f64, requires_grad=True)
    slope = torch.tensor([-0.01, 0.004], dtype=f64, requires_grad=True)
    n = torch.tensor(1.33, dtype=f64, requires_grad=True)

    def f(level, slope, n):
        return apparent_points(p, CAM, WaterSurface(level, n, slope))

    assert torch.autograd.gradcheck(f, (level, slope, n), eps=1e-7, atol=1e-6, rtol=1e-5)

    def g(level, slope):
        out = refract_gaussians(p, torch.full_like(p, 0.1),
                                torch.tensor([[1.0, 0, 0, 0]], dtype=f64).expand(6, 4),
                                torch.full((6,), 0.5, dtype=f64), torch.ones(6, 3, dtype=f64), CAM,
                                WaterSurface(level, 1.33, slope), scale="anisotropic")
        return out.means, out.jacobians, out.covars

    assert torch.autograd.gradcheck(g, (level, slope), eps=1e-7, atol=1e-6, rtol=1e-5)


def test_surface_height_depth_shift_and_json():
    w = WaterSurface(2.0, 1.33, [0.01, -0.02])  # a list, as JSON gives it
    assert w.slope == (0.01, -0.02) and hash(w)
    xy = np.array([[10.0, 5.0]])
    assert w.height(xy)[0] == pytest.approx(2.0 + 0.1 - 0.1)
    assert w.depth(np.array([[10.0, 5.0, 1.5]]))[0] == pytest.approx(0.5)
    off = (100.0, 50.0, 3.0)
    s = w.shifted(off)
    assert s.height(xy - np.array(off[:2]))[0] == pytest.approx(w.height(xy)[0] - off[2], abs=1e-12)
    assert WaterSurface(**water_json(w)) == w
    # a flat surface's files as they were
    assert water_json(WaterSurface(0.5, 1.33)) == {"level": 0.5, "n": 1.33}
    with pytest.raises(ValueError, match="slope"):
        WaterSurface(0.0, 1.33, (2.0, 0.0))
    with pytest.raises(ValueError, match="above the water surface"):
        apparent_points(below(w, n=2), torch.tensor([0.0, 0.0, 1.9], dtype=f64),
                        WaterSurface(2.0, 1.33, (0.0, -0.1)))


def test_water_rays_bend_at_the_tilted_normal_and_meet_at_the_true_point():
    """`snell.water_rays` under a tilted surface: the rays of one true point's pixels in several views,
    through the tilted transform, meet at it; the crossing points lie on the surface."""
    from ragsplat.camera import Camera
    from ragsplat.snell import closest_points, water_rays

    water = WaterSurface(level=0.5, n=1.33, slope=(-0.02, 0.01))
    cams = [Camera.look_at([x, y, 4.5], [0.0, 0.0, -1.0], 64, 48, 60.0)
            for x, y in ((0, 0), (2, 0.5), (-1.5, 2))]
    true = np.array([[0.3, -0.2, -1.0], [-0.4, 0.5, -2.5]])
    rays = []
    for cam in cams:
        seen = apparent_points(torch.from_numpy(true), torch.from_numpy(cam.camera_center), water).numpy()
        rays.append(water_rays(cam, cam.project(seen)[0], water))
    origins, dirs = (np.concatenate(r) for r in zip(*rays))
    np.testing.assert_allclose(water.depth(origins), 0, atol=1e-12)
    np.testing.assert_allclose(closest_points(origins, dirs, np.tile([0, 1], 3), 2), true, atol=1e-9)


# A riffle: the surface falls 1 % on average and 6 cm more over 8 m around x = 0 (up to 1.6 % more there).
RIFFLE = WaterSurface(0.0, 1.33, (-0.01, 0.0),
                      Profile((0.0, 0.0), (1.0, 0.0), (-20, -4, 4, 20), (0.03, 0.03, -0.03,
                                                                                                   -0.03)))


def fermat(P, C, water):
    """The interface point of the true light path from P under the surface to the camera C: the point of the
    surface where the optical length |I - C| + n |P - I| is least (Fermat's principle), found by BFGS on its
    exact gradient. It reads only the surface's height and slope from the library, and agrees with a
    derivative-free Nelder-Mead search (this test's tracer until 70dbca0, 15x slower) to 1e-7 m."""
    from scipy.optimize import minimize

    def length(xy):  # the optical length and its gradient in the interface point's x, y
        I = np.array([xy[0], xy[1], float(water.height(np.asarray(xy)[None])[0])])
        g = water.gradient(np.asarray(xy)[None])[0]  # the surface's slope: dI/dxy = [[1, 0, gx], [0, 1, gy]]
        d = (I - C) / np.linalg.norm(I - C) + water.n * (I - P) / np.linalg.norm(P - I)
        return np.linalg.norm(I - C) + water.n * np.linalg.norm(P - I), d[:2] + d[2] * g

    r = minimize(length, P[:2] + (C[:2] - P[:2]) * 0.3, jac=True, method="BFGS", options={"gtol": 1e-12})
    return np.array([*r.x, float(water.height(r.x[None])[0])])


def test_profile_heights_and_gradients():
    xy = np.column_stack([np.linspace(-25, 25, 201), np.full(201, 3.0)])
    z, g = RIFFLE.height(xy), RIFFLE.gradient(xy)
    eps = 1e-6
    dz = (RIFFLE.height(xy + [eps, 0]) - RIFFLE.height(xy - [eps, 0])) / (2 * eps)
    np.testing.assert_allclose(g[:, 0], dz, atol=1e-8)
    np.testing.assert_allclose(g[:, 1], 0.0)
    assert z[0] == pytest.approx(0.25 + 0.03) and z[-1] == pytest.approx(-0.25 - 0.03)  # flat profile beyond
    t = torch.from_numpy(xy)
    np.testing.assert_allclose(RIFFLE.height(t).numpy(), z, atol=1e-15)  # tensors and arrays alike
    np.testing.assert_allclose(RIFFLE.gradient(t).numpy(), g, atol=1e-15)
    assert water_json(RIFFLE)["profile"]["offsets"] == [0.03, 0.03, -0.03, -0.03]
    assert WaterSurface(**water_json(RIFFLE)) == RIFFLE and hash(RIFFLE)
    moved = RIFFLE.shifted((100.0, 50.0, 2.0))
    np.testing.assert_allclose(moved.height(xy - [100.0, 50.0]), z - 2.0, atol=1e-12)


def test_a_flat_profile_is_the_plane():
    p = below(TILTED)
    flat = WaterSurface(0.5, 1.33, TILTED.slope, Profile((0.0, 0.0), (0.6, 0.8), (-30.0, 30.0), (0.0, 0.0)))
    assert torch.allclose(apparent_points(p, CAM, flat), apparent_points(p, CAM, TILTED), rtol=0, atol=1e-12)


def test_curved_surface_against_a_ray_trace():
    """Under the riffle, the tangent plane above each point puts its apparent point on the true light path's
    air ray within 1e-3 rad (0.2 px of a 256 px, 70 degree view; measured 0.09 px at most), several times
    closer than one plane through the mean fall; under a plane the same trace agrees to round-off (the
    tracer's check)."""
    rng = np.random.default_rng(0)
    C = np.array([0.0, 0.0, 4.0])
    mean_plane = WaterSurface(0.0, 1.33, (-0.01, 0.0))
    worst = {"tangent": 0.0, "mean plane": 0.0, "plane check": 0.0}
    for _ in range(40):
        xy = rng.uniform(-8, 8, 2)
        depth = rng.uniform(0.2, 3.0)
        for name, surface, model in (("tangent", RIFFLE, RIFFLE), ("mean plane", RIFFLE, mean_plane),
                                     ("plane check", mean_plane, mean_plane)):
            P = np.array([*xy, float(surface.height(xy[None])[0]) - depth])
            air = fermat(P, C, surface) - C
            q = apparent_points(torch.from_numpy(P[None]), torch.from_numpy(C), model)[0].numpy() - C
            angle = math.acos(min(1.0, float(air @ q / np.linalg.norm(air) / np.linalg.norm(q))))
            worst[name] = max(worst[name], angle)
    assert worst["plane check"] < 1e-6
    assert worst["tangent"] < 1e-3 and worst["tangent"] < worst["mean plane"] / 3


def test_curved_transform_is_consistent_and_differentiable():
    p = below(RIFFLE, n=30, radius=10.0)
    quats = torch.nn.functional.normalize(torch.rand(len(p), 4, dtype=f64), dim=-1)
    scales = torch.rand(len(p), 3, dtype=f64) * 0.1
    out = refract_gaussians(p, scales, quats, torch.full((len(p),), 0.6, dtype=f64),
                            torch.rand(len(p), 3, dtype=f64), CAM, RIFFLE, scale="anisotropic")
    assert torch.allclose(out.means, apparent_points(p, CAM, RIFFLE), rtol=0, atol=1e-12)
    assert torch.allclose(out.jacobians, apparent_jacobian(p, CAM, RIFFLE), rtol=0, atol=1e-12)
    assert torch.allclose(out.opacities, 0.6 * opacity_factor(p, RIFFLE), rtol=0, atol=1e-15)
    each = apparent_points_each(p, CAM.expand(len(p), 3), RIFFLE)
    assert torch.allclose(each, out.means, rtol=0, atol=1e-12)
    q = p[:4].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda q: apparent_points(q, CAM, RIFFLE), (q,), eps=1e-7, atol=1e-6)

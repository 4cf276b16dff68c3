"""Refraction transform, tested from physics (Snell's law, geometry) rather than from its own formulas."""

import logging
import math
import subprocess
import sys

import numpy as np
import pytest
import torch

from ragsplat.refraction import (
    apparent_jacobian,
    apparent_points,
    compiled_refract_gaussians,
    covariance,
    facet_offsets,
    refract_gaussians,
)
from ragsplat.water_surface import WaterSurface

f64 = torch.float64
CAM = torch.tensor([1.0, -2.0, 30.0], dtype=f64)
WATER = WaterSurface(level=0.5, n=1.33)


def random_points(n=200, seed=0, depth=(0.01, 20.0), radius=60.0):
    g = torch.Generator().manual_seed(seed)
    xy = (torch.rand(n, 2, generator=g, dtype=f64) - 0.5) * 2 * radius
    z = WATER.level - (depth[0] + torch.rand(n, generator=g, dtype=f64) * (depth[1] - depth[0]))
    return torch.cat([xy, z[:, None]], -1)


def point_from_air_angle(theta_a_deg, d, H, n, azimuth=0.7, cam=CAM, level=WATER.level):
    """True point whose refracted ray leaves the water at air angle theta_a (built forwards by Snell)."""
    ta = math.radians(theta_a_deg)
    tw = math.asin(math.sin(ta) / n)
    r = H * math.tan(ta) + d * math.tan(tw)
    return torch.tensor([[cam[0] + r * math.cos(azimuth), cam[1] + r * math.sin(azimuth), level - d]],
                        dtype=f64)


def test_normal_incidence_does_not_bend():
    p = torch.tensor([[CAM[0], CAM[1], WATER.level - 4.0]], dtype=f64)
    q = apparent_points(p, CAM, WATER)
    assert q[0, 0] == CAM[0] and q[0, 1] == CAM[1]  # a zero horizontal offset stays exactly zero
    assert float(q[0, 2]) == pytest.approx(WATER.level - 4.0 / WATER.n, rel=0, abs=1e-14)


@pytest.mark.parametrize("theta_a", [5.0, 30.0, 60.0, 85.0])
def test_snell_holds_and_apparent_point_is_on_the_air_ray(theta_a):
    H = float(CAM[2]) - WATER.level
    d = 7.0
    p = point_from_air_angle(theta_a, d, H, WATER.n)
    q = apparent_points(p, CAM, WATER)[0]
    # The air ray from the camera through the apparent point must meet the plane at the radius built above.
    to_q = q - CAM
    t = (WATER.level - CAM[2]) / to_q[2]
    hit = CAM + t * to_q
    s_expected = H * math.tan(math.radians(theta_a))
    assert float(torch.linalg.norm(hit[:2] - CAM[:2])) == pytest.approx(s_expected, rel=1e-12)
    # Snell's law at that interface point, from the two legs' directions.
    air = (hit - CAM) / torch.linalg.norm(hit - CAM)
    wet = (p[0] - hit) / torch.linalg.norm(p[0] - hit)
    sin_a = float(torch.linalg.norm(air[:2]))
    sin_w = float(torch.linalg.norm(wet[:2]))
    assert sin_a == pytest.approx(WATER.n * sin_w, rel=1e-12)
    assert sin_a == pytest.approx(math.sin(math.radians(theta_a)), rel=1e-12)
    # The three legs lie in one vertical plane through the camera nadir (azimuth preserved).
    assert float(torch.atan2(q[1] - CAM[1], q[0] - CAM[0])) == pytest.approx(0.7, abs=1e-12)


def test_paper_closed_form_apparent_position():
    # Eq. 5: r' = r + (n^2 - 1) z tan^3(theta_w), z' = (1/n) (cos ta / cos tw)^3 z (z relative to the level).
    H, d, n = float(CAM[2]) - WATER.level, 3.0, WATER.n
    ta = math.radians(40.0)
    tw = math.asin(math.sin(ta) / n)
    p = point_from_air_angle(40.0, d, H, n)
    q = apparent_points(p, CAM, WATER)[0]
    r = H * math.tan(ta) + d * math.tan(tw)
    r_app = r + (n * n - 1) * (-d) * math.tan(tw) ** 3
    z_app = (math.cos(ta) / math.cos(tw)) ** 3 * (-d) / n
    assert float(torch.linalg.norm(q[:2] - CAM[:2])) == pytest.approx(r_app, rel=1e-12)
    assert float(q[2]) - WATER.level == pytest.approx(z_app, rel=1e-12)


def test_apparent_is_closer_to_nadir_and_shallower():
    p = random_points()
    q = apparent_points(p, CAM, WATER)
    r = torch.linalg.norm(p[:, :2] - CAM[:2], dim=1)
    r_app = torch.linalg.norm(q[:, :2] - CAM[:2], dim=1)
    assert bool((r_app < r).all())
    assert bool(((WATER.level - q[:, 2]) < (WATER.level - p[:, 2])).all())
    assert bool(((WATER.level - q[:, 2]) > 0).all())


def test_n_one_is_exact_identity():
    water = WaterSurface(level=0.5, n=1.0)
    p = random_points()
    # exact: a float n = 1 skips the transform (`is_identity`), nothing is computed
    assert torch.equal(apparent_points(p, CAM, water), p)
    assert torch.equal(apparent_jacobian(p, CAM, water), torch.eye(3, dtype=f64).expand(len(p), 3, 3))
    out = refract_gaussians(p, torch.ones_like(p), torch.tensor([[1.0, 0, 0, 0]]).expand(len(p), 4),
                            torch.full((len(p),), 0.5), torch.rand(len(p), 3), CAM, water, color=True)
    assert torch.equal(out.means, p) and torch.equal(out.opacities, torch.full((len(p),), 0.5))


def test_n_one_as_tensor_is_identity_to_round_off():
    # A calibrated n keeps its gradient path; at n = 1 the formulas themselves collapse to the identity.
    n = torch.tensor(1.0, dtype=f64, requires_grad=True)
    p = random_points()
    q = apparent_points(p, CAM, WaterSurface(level=0.5, n=n))
    torch.testing.assert_close(q, p, rtol=1e-13, atol=1e-12)


def test_above_water_untouched():
    p = torch.tensor([[3.0, 1.0, 0.6], [3.0, 1.0, 0.5], [3.0, 1.0, 0.2]], dtype=f64)  # above, on, below
    q = apparent_points(p, CAM, WATER)
    # exact: only the submerged rows are written (index_put / index_copy), the others are the inputs
    assert torch.equal(q[:2], p[:2]) and not torch.equal(q[2], p[2])
    J = apparent_jacobian(p, CAM, WATER)
    assert torch.equal(J[:2], torch.eye(3, dtype=f64).expand(2, 3, 3))
    out = refract_gaussians(p, torch.ones(3, 3, dtype=f64),
                            torch.tensor([[1.0, 0, 0, 0]], dtype=f64).expand(3, 4),
                            torch.full((3,), 0.8, dtype=f64), torch.ones(3, 3, dtype=f64), CAM, WATER,
                            color=True)
    assert torch.equal(out.means[:2], p[:2]) and torch.equal(out.scales[:2], torch.ones(2, 3, dtype=f64))
    assert torch.equal(out.opacities[:2], torch.full((2,), 0.8, dtype=f64))
    assert float(out.opacities[2]) == pytest.approx(0.8 / 1.33**2)
    assert torch.equal(out.colors[:2], torch.ones(2, 3, dtype=f64))
    white = 1.055 * (1 / 1.33**2) ** (1 / 2.4) - 0.055  # sRGB of white's radiance / n^2
    torch.testing.assert_close(out.colors[2], torch.full((3,), white, dtype=f64))


def test_colour_factor_applies_in_linear_light():
    # sRGB 0.03 lies on the transfer's linear segment: radiance / n^2 is sRGB 0.03 / n^2, not 0.03 n^(-2/2.2)
    # (which is 36 % brighter); mid-grey goes through the power segment.
    c = torch.tensor([[0.03, 0.5, 1.0]], dtype=f64)
    deep = torch.tensor([[0.0, 0.0, -1.0]], dtype=f64)
    out = refract_gaussians(deep, torch.ones(1, 3, dtype=f64), torch.tensor([[1.0, 0, 0, 0]], dtype=f64),
                            torch.ones(1, dtype=f64), c, CAM, WaterSurface(0.5, 1.33), color=True)
    lin = np.where(c.numpy() <= 0.04045, c.numpy() / 12.92, ((c.numpy() + 0.055) / 1.055) ** 2.4) / 1.33**2
    expected = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1 / 2.4) - 0.055)
    np.testing.assert_allclose(out.colors.numpy(), expected, rtol=1e-12)
    assert abs(float(out.colors[0, 0]) - 0.03 / 1.33**2) < 1e-12


@pytest.mark.parametrize("scale", ["isotropic", "anisotropic"])
def test_waterline_is_continuous_in_values_and_gradients(scale):
    """Gaussians moved through the water line: every apparent quantity and its gradient w.r.t. the height
    change smoothly (no jump at the level, none at the blend band's lower edge, finite everywhere)."""
    from ragsplat.refraction import WATERLINE_BAND

    level = WATER.level
    eps = 1e-10
    heights = torch.tensor([level + 0.02, level + eps, level, level - eps, level - WATERLINE_BAND / 2,
                            level - WATERLINE_BAND + eps, level - WATERLINE_BAND - eps, level - 0.5],
                           dtype=f64)

    def apparent(z):  # [N] -> (sum of apparent opacity, scale (or covariance) and colour terms per Gaussian)
        p = torch.stack([torch.full_like(z, 3.0), torch.full_like(z, 1.0), z], 1)
        q = torch.tensor([[0.9, 0.1, 0.3, 0.2]], dtype=f64).expand(len(z), 4)
        out = refract_gaussians(p, torch.full_like(p, 0.05), q, torch.full_like(z, 0.8),
                                torch.full_like(p, 0.5), CAM, WATER, scale=scale, color=True)
        spread = out.covars.diagonal(dim1=1, dim2=2).sum(-1) if scale == "anisotropic" else out.scales.sum(-1)
        return out.opacities, spread, out.colors.sum(-1)

    z = heights.clone().requires_grad_(True)
    for value in apparent(z):
        (grad,) = torch.autograd.grad(value.sum(), z, retain_graph=True)
        v, g = value.detach(), grad
        assert torch.isfinite(v).all() and torch.isfinite(g).all()
        assert abs(float(v[1] - v[3])) < 1e-9 and abs(float(g[1] - g[3])) < 1e-4  # across the level
        assert abs(float(v[5] - v[6])) < 1e-9 and abs(float(g[5] - g[6])) < 1e-4  # across the band's edge
        assert float(v[2] - v[0]) == 0 or abs(float(v[2] - v[0])) < 1e-12  # at the level = above it
        # the band does change them: the test can fail
        assert abs(float(v[4] - v[3])) > 0.02 * abs(float(v[3]))


def test_waterline_band_is_thin_and_exact_below_it():
    from ragsplat.refraction import WATERLINE_BAND, waterline_weight

    d = torch.tensor([-1.0, 0.0, WATERLINE_BAND / 2, WATERLINE_BAND, 1.0], dtype=f64)
    assert waterline_weight(d).tolist() == [0.0, 0.0, 0.5, 1.0, 1.0]  # t in {0, 1/2, 1}: every step exact


def test_camera_not_above_water_raises():
    p = random_points(5)
    for z in (0.5, 0.0):
        with pytest.raises(ValueError, match="not above the water"):
            apparent_points(p, torch.tensor([0.0, 0.0, z], dtype=f64), WATER)


def central_difference_jacobian(p, cam, water, h=1e-6):
    cols = []
    for k in range(3):
        e = torch.zeros(3, dtype=f64)
        e[k] = h
        cols.append((apparent_points(p + e, cam, water) - apparent_points(p - e, cam, water)) / (2 * h))
    return torch.stack(cols, -1)


EXTREME = [  # (label, points, camera) spanning the stiff regimes
    ("typical", random_points(50, seed=1), CAM),
    ("near nadir", torch.tensor([[1.0 + 1e-7, -2.0, -5.0], [1.0, -2.0 + 1e-3, -9.0]], dtype=f64), CAM),
    ("near surface", torch.tensor([[5.0, 3.0, 0.5 - 1e-3], [40.0, 3.0, 0.5 - 1e-2]], dtype=f64), CAM),
    ("grazing", torch.tensor([[900.0, -2.0, -20.0], [600.0, 400.0, -3.0]], dtype=f64), CAM),
    ("low camera", torch.tensor([[20.0, 0.0, -10.0], [0.5, 0.2, -1.0]], dtype=f64),
     torch.tensor([0.0, 0.0, 0.6], dtype=f64)),
    ("deep", torch.tensor([[10.0, 5.0, -99.0], [100.0, 0.0, -80.0]], dtype=f64), CAM),
]


@pytest.mark.parametrize("label,p,cam", EXTREME, ids=[e[0] for e in EXTREME])
def test_jacobian_matches_central_differences(label, p, cam):
    J = apparent_jacobian(p, cam, WATER)
    fd = central_difference_jacobian(p, cam, WATER)
    scale = J.abs().amax(dim=(1, 2), keepdim=True)
    assert float(((J - fd).abs() / scale).max()) < 1e-6


def test_jacobian_matches_paper_eq6_lifted_to_3d():
    H, d, n = float(CAM[2]) - WATER.level, 6.0, WATER.n
    for theta_a in (10.0, 35.0, 70.0):
        p = point_from_air_angle(theta_a, d, H, n, azimuth=0.0)  # radial direction = world x
        ta = math.radians(theta_a)
        tw = math.asin(math.sin(ta) / n)
        z = -d
        r = H * math.tan(ta) + d * math.tan(tw)
        z_app = (math.cos(ta) / math.cos(tw)) ** 3 * z / n
        r_app = r + (n * n - 1) * z * math.tan(tw) ** 3
        sec2 = 1 / math.cos(tw) ** 2
        delta = n * H * math.cos(tw) / math.cos(ta) ** 3 - z * sec2
        bracket = 1 - n * n * math.cos(tw) ** 2 / math.cos(ta) ** 2
        j11 = 1 + 3 * (n * n - 1) * z * math.tan(tw) ** 2 * sec2 / delta
        j12 = (n * n - 1) * math.tan(tw) ** 3 * (1 + 3 * z * sec2 / delta)
        j21 = 3 * z_app * math.tan(tw) / delta * bracket
        j22 = z_app / z + 3 * z_app * math.tan(tw) ** 2 / delta * bracket
        expected = torch.tensor([[j11, 0, j12], [0, r_app / r, 0], [j21, 0, j22]], dtype=f64)
        torch.testing.assert_close(apparent_jacobian(p, CAM, WATER)[0], expected, rtol=1e-10, atol=1e-12)


def test_gradients_finite_at_nadir_and_n_one():
    for n in (1.33, 1.0):
        n_t = torch.tensor(n, dtype=f64, requires_grad=True)
        level = torch.tensor(0.5, dtype=f64, requires_grad=True)
        water = WaterSurface(level=level, n=n_t)
        p = torch.tensor([[1.0, -2.0, -5.0], [1.0, -2.0, 0.5 - 1e-4]], dtype=f64, requires_grad=True)
        scales = torch.full((2, 3), 0.1, dtype=f64, requires_grad=True)
        out = refract_gaussians(p, scales, torch.tensor([[1.0, 0.2, 0, 0]], dtype=f64).expand(2, 4),
                                torch.full((2,), 0.5, dtype=f64), torch.ones(2, 3, dtype=f64), CAM, water)
        (out.means.sum() + out.scales.sum() + out.opacities.sum()).backward()
        for g in (p.grad, scales.grad, n_t.grad, level.grad):
            assert g is not None and bool(torch.isfinite(g).all())


def test_gradcheck_typical_and_extreme():
    for label, p, cam in EXTREME:
        p = p[:2].clone().requires_grad_(True)
        n = torch.tensor(1.33, dtype=f64, requires_grad=True)
        level = torch.tensor(0.5, dtype=f64, requires_grad=True)
        cam_t = cam.clone().requires_grad_(True)

        def f(p, n, level, cam_t):
            return apparent_points(p, cam_t, WaterSurface(level=level, n=n))

        assert torch.autograd.gradcheck(f, (p, n, level, cam_t), eps=1e-7, atol=1e-6, rtol=1e-5), label

        def g(p, n, cam=cam):
            q = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=f64).expand(len(p), 4)
            out = refract_gaussians(p, torch.full_like(p, 0.2), q, torch.full((len(p),), 0.5, dtype=f64),
                                    torch.ones_like(p), cam, WaterSurface(level=0.5, n=n))
            return out.means, out.scales, out.opacities

        assert torch.autograd.gradcheck(g, (p, n), eps=1e-7, atol=1e-6, rtol=1e-5), label


def test_scale_modes_at_nadir_by_hand():
    # At nadir the map is locally diag(1, 1, 1/n): horizontal unchanged, vertical compressed by n.
    n = WATER.n
    p = torch.tensor([[CAM[0], CAM[1], -3.0]], dtype=f64)
    torch.testing.assert_close(apparent_jacobian(p, CAM, WATER)[0],
                               torch.diag(torch.tensor([1, 1, 1 / n], dtype=f64)))
    args = (p, torch.full((1, 3), 0.2, dtype=f64), torch.tensor([[1.0, 0, 0, 0]], dtype=f64),
            torch.full((1,), 0.5, dtype=f64), torch.ones(1, 3, dtype=f64), CAM, WATER)
    none = refract_gaussians(*args, scale="none")
    iso = refract_gaussians(*args, scale="isotropic")
    det = refract_gaussians(*args, scale="determinant")
    ani = refract_gaussians(*args, scale="anisotropic")
    assert torch.equal(none.scales, args[1]) and none.covars is None
    torch.testing.assert_close(iso.scales, torch.full((1, 3), 0.2 * n ** (-1 / 3), dtype=f64))
    torch.testing.assert_close(det.scales, torch.full((1, 3), 0.2 * n ** (-1 / 3), dtype=f64))
    torch.testing.assert_close(ani.covars[0], torch.diag(torch.tensor([0.04, 0.04, 0.04 / n**2], dtype=f64)))
    torch.testing.assert_close(ani.scales, args[1])


def test_scale_modes_off_nadir_match_jacobian():
    p = random_points(20, seed=3)
    J = apparent_jacobian(p, CAM, WATER)
    quats = torch.nn.functional.normalize(torch.randn(20, 4, dtype=f64), dim=-1)
    scales = torch.rand(20, 3, dtype=f64) + 0.1
    args = (p, scales, quats, torch.full((20,), 0.5, dtype=f64), torch.ones(20, 3, dtype=f64), CAM, WATER)
    iso = refract_gaussians(*args, scale="isotropic")
    det = refract_gaussians(*args, scale="determinant")
    ani = refract_gaussians(*args, scale="anisotropic")
    torch.testing.assert_close(iso.scales,
                               scales * torch.linalg.norm(J, dim=1).prod(-1, keepdim=True) ** (1 / 3))
    torch.testing.assert_close(det.scales, scales * torch.linalg.det(J).abs()[:, None] ** (1 / 3))
    torch.testing.assert_close(ani.covars, J @ covariance(quats, scales) @ J.transpose(1, 2))
    torch.testing.assert_close(ani.jacobians, J)  # the surfels' tangent map
    bare = refract_gaussians(*args, scale="anisotropic", covariances=False)  # what surfels ask for
    # bit-identical: the same operations give J and the means whether or not covariances are asked for
    assert (bare.covars is None and torch.equal(bare.jacobians, ani.jacobians)
            and torch.equal(bare.means, ani.means))
    assert iso.jacobians is None and det.jacobians is None
    # The paper's observation: the determinant shrinks more than the geometric mean of axis stretches.
    assert bool((det.scales <= iso.scales + 1e-12).all())


def test_unknown_scale_mode_raises():
    p = random_points(2)
    with pytest.raises(ValueError, match="scale must be"):
        refract_gaussians(p, p, p, p[:, 0], p, CAM, WATER, scale="sphere")


def test_float32_close_to_float64():
    p = random_points(500, seed=5)
    q64 = apparent_points(p, CAM, WATER)
    q32 = apparent_points(p.float(), CAM.float(), WATER)
    dist = torch.linalg.norm(p - CAM, dim=1)
    assert float((torch.linalg.norm(q32.double() - q64, dim=1) / dist).max()) < 2e-6


def test_water_rays_bend_by_snell_and_meet_at_the_true_point():
    """`snell.water_rays`: straight down is not bent, an oblique ray leaves at asin(sin / n); the rays of one
    true point's pixels in several views (through the exact forward transform) meet at it; n = 1 is the
    pinhole."""
    from ragsplat.camera import Camera
    from ragsplat.snell import closest_points, water_rays

    cams = [Camera.look_at([x, y, 4.5], [0.0, 0.0, -1.0], 64, 48, 60.0)
            for x, y in ((0, 0), (2, 0.5), (-1.5, 2))]
    origin, d = water_rays(cams[0], np.array([[32.0, 24.0]]), WATER)  # the principal point: straight down
    np.testing.assert_allclose(d, [[0, 0, -1]], atol=1e-12)
    np.testing.assert_allclose(origin[0, 2], WATER.level)
    _, d = water_rays(cams[1], np.array([[10.0, 30.0]]), WATER)
    air = cams[1].unproject(np.array([[10.0, 30.0]]), np.ones(1)) - cams[1].camera_center
    sin_air = np.linalg.norm(air[0, :2]) / np.linalg.norm(air[0])
    assert np.linalg.norm(d[0, :2]) == pytest.approx(sin_air / WATER.n, rel=1e-12)
    true = np.array([[0.3, -0.2, -1.0], [-0.4, 0.5, -2.5]])
    for water in (WATER, WaterSurface(level=0.5, n=1.0)):
        rays = []
        for cam in cams:
            seen = apparent_points(torch.from_numpy(true), torch.from_numpy(cam.camera_center), water).numpy()
            rays.append(water_rays(cam, cam.project(seen)[0], water))
        origins, dirs = (np.concatenate(r) for r in zip(*rays))
        np.testing.assert_allclose(closest_points(origins, dirs, np.tile([0, 1], 3), 2), true, atol=1e-9)
    # one view, or views along the same line, do not fix a point
    assert np.isnan(closest_points(origins[:1], dirs[:1], np.array([0]), 1)).all()


def test_robust_intersection_is_exact_on_exact_rays_and_ignores_a_ray_that_belongs_elsewhere():
    """`snell.robust_closest_points`: rays bent through the water from a true point meet at it with no
    spread; a zero weight drops a line from `closest_points`; one ray of a track aimed a metre off (a wrong
    match) pulls the least-squares point by centimetres and the robust one by far less."""
    from ragsplat.camera import Camera
    from ragsplat.snell import closest_points, robust_closest_points, water_rays

    rng = np.random.default_rng(3)
    cams = [Camera.look_at([x, y, 4.5], [0.0, 0.0, -1.0], 64, 48, 60.0)
            for x, y in rng.uniform(-1.5, 1.5, (8, 2))]
    true = np.array([[0.3, -0.2, -1.0], [-0.4, 0.5, -2.5], [0.1, 0.1, -1.8]])
    rays = []
    for cam in cams:
        seen = apparent_points(torch.from_numpy(true), torch.from_numpy(cam.camera_center), WATER).numpy()
        rays.append(water_rays(cam, cam.project(seen)[0], WATER))
    origins, dirs = (np.concatenate(r) for r in zip(*rays))
    group = np.tile(np.arange(3), len(cams))
    points, spread = robust_closest_points(origins, dirs, group, 3)
    np.testing.assert_allclose(points, true, atol=1e-9)
    assert (spread < 1e-9).all()
    # a small angular scatter on every ray (the ripples), one ray of the first track sent a metre off
    noisy = dirs + rng.normal(0, 2e-3, dirs.shape)
    wrong = true[0] + [1.0, 0.0, 0.0] - origins[0]
    noisy[0] = wrong
    noisy /= np.linalg.norm(noisy, axis=1, keepdims=True)
    weights = np.ones(len(dirs))
    weights[0] = 0.0
    np.testing.assert_allclose(closest_points(origins, noisy, group, 3, weights=weights)[1:],
                               closest_points(origins[1:], noisy[1:], group[1:], 3)[1:], atol=1e-12)
    plain = closest_points(origins, noisy, group, 3)
    robust, spread = robust_closest_points(origins, noisy, group, 3)
    plain_miss, robust_miss = (np.linalg.norm(p[0] - true[0]) for p in (plain, robust))
    assert plain_miss > 0.05 and robust_miss < plain_miss / 4
    assert spread[0] < 0.02  # the wrong ray weighs little in the track's spread too


@pytest.mark.parametrize("flags", [{"scale": "isotropic", "color": True},  # `full` (+ colour)
                                   {"scale": "anisotropic", "covariances": False},  # `2dgs+full`'s tangents
                                   # and the water's attenuation
                                   {"scale": "anisotropic", "covariances": False,
                                    "attenuation": torch.tensor([0.4, 0.1, 0.05])}])
def test_compiled_transform_matches_eager_in_values_and_gradients(flags):
    # torch.compile fuses the ops and may reorder their arithmetic: the same values to float32 round-off, not
    # bit-equal. Gaussians above the level, in the waterline band and below, seen off nadir.
    g = torch.Generator().manual_seed(3)
    n = 300
    means = random_points(n, seed=3, depth=(-0.5, 4.0), radius=8.0).float()
    means[:20, 2] = WATER.level - torch.rand(20, generator=g) * 0.01  # the waterline band
    inputs = [means, torch.rand(n, 3, generator=g) * 0.05 + 0.01,
              torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1),
              torch.rand(n, generator=g), torch.rand(n, 3, generator=g)]
    cam = torch.tensor([2.0, -1.0, 6.0])
    outs = {}
    # the value-reading helpers are graph breaks (refraction._GRAPH_BREAKS): the first trace logs no dynamo
    # warning of a traced float() or bool()
    warned = _Warnings()
    for name, transform in (("eager", refract_gaussians), ("compiled", compiled_refract_gaussians())):
        leaves = [t.clone().requires_grad_(True) for t in inputs]
        logging.getLogger("torch._dynamo").addHandler(warned)
        try:
            a = transform(*leaves, cam, WATER, **flags)
        finally:
            logging.getLogger("torch._dynamo").removeHandler(warned)
        values = [t for t in (a.means, a.scales, a.opacities, a.colors, a.covars, a.jacobians)
                  if t is not None]
        # a fixed random weighting of every output, so each output's gradient reaches the inputs
        loss = sum((v * torch.randn(v.shape, generator=torch.Generator().manual_seed(k))).sum()
                   for k, v in enumerate(values))
        outs[name] = values + list(torch.autograd.grad(loss, leaves, allow_unused=True))
    for eager, compiled in zip(outs["eager"], outs["compiled"], strict=True):
        if eager is None:
            assert compiled is None
            continue
        torch.testing.assert_close(compiled, eager, rtol=1e-4, atol=1e-5)
    assert warned.messages == []


class _Warnings(logging.Handler):
    def __init__(self):
        super().__init__(logging.WARNING)
        self.messages = []

    def emit(self, record):
        self.messages.append(record.getMessage()[:200])


def test_importing_the_commands_leaves_torch_compile_unloaded():
    # torch._dynamo (torch.compile's tracer, with sympy) costs a command about 3 s of CPU at its start; a
    # compile (compiled_refract_gaussians) or a training's optimiser loads it, an import does not
    code = ("import sys, ragsplat.cli.main, ragsplat.eval.ablation, ragsplat.survey.pipeline; "
            "print('torch._dynamo' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def _tilt(g):  # a facet of one gradient g [2] everywhere: `facet_offsets`' gradient callable
    return lambda xy: torch.as_tensor(g, dtype=xy.dtype).expand(len(xy), 2)


def test_a_flat_facet_moves_nothing_and_air_points_never_move():
    p = random_points(50)
    assert torch.equal(facet_offsets(p, CAM, WATER, _tilt([0.0, 0.0])), torch.zeros(50, 2, dtype=f64))
    above = p.clone()
    above[:, 2] = WATER.level + 0.3
    assert torch.equal(facet_offsets(above, CAM, WATER, _tilt([0.1, -0.2])), torch.zeros(50, 2, dtype=f64))
    # n = 1: a tilted facet bends nothing (round-off)
    moved = facet_offsets(p, CAM, WaterSurface(WATER.level, 1.0), _tilt([0.1, -0.2]))
    assert moved.abs().max() < 1e-12


@pytest.mark.parametrize("slope", [0.02, 0.3])
def test_a_facet_under_a_nadir_camera_bends_the_ray_by_snell(slope):
    # the vertical ray meets a facet rising along +x at incidence a = atan(s), leaves at b = asin(sin a / n)
    # from its normal: it turns a - b from the vertical, towards +x (into the water, along the inward normal)
    d = 1.7
    point = torch.tensor([[CAM[0], CAM[1], WATER.level - d]], dtype=f64)
    a = math.atan(slope)
    b = math.asin(math.sin(a) / WATER.n)
    for g, along in (([slope, 0.0], [1.0, 0.0]), ([0.0, -slope], [0.0, -1.0])):
        moved = facet_offsets(point, CAM, WATER, _tilt(g))[0]
        want = d * math.tan(a - b) * torch.tensor(along, dtype=f64)
        assert torch.allclose(moved, want, rtol=1e-12, atol=1e-14)


def test_the_ray_through_a_tilted_facet_lands_by_snell_at_the_points_depth():
    # Independent of the function's own path: the crossing from `apparent_points` (the apparent point lies
    # on the air ray), the landing from the offset; the bend there obeys sin i = n sin t about the facet's
    # normal, in the plane of the ray and the normal.
    p = random_points(200, depth=(0.1, 5.0), radius=15.0)
    g = torch.Generator().manual_seed(3)
    slopes = (torch.rand(200, 2, generator=g, dtype=f64) - 0.5) * 0.4
    lookup = {}

    def gradient(xy):  # the slope of each point's own facet, by the order the wet points are passed in
        lookup["xy"] = xy
        return slopes[: len(xy)]

    moved = facet_offsets(p, CAM, WATER, gradient)
    app = apparent_points(p, CAM, WATER)
    H = CAM[2] - WATER.level
    cross = CAM + (app - CAM) * (H / (CAM[2] - app[:, 2]))[:, None]  # [N, 3] on the flat surface
    assert torch.allclose(lookup["xy"], cross[:, :2], atol=1e-9)  # the facets are asked for at the crossings
    land = torch.cat([p[:, :2] + moved, p[:, 2:]], -1)
    down = torch.nn.functional.normalize(cross - CAM, dim=-1)
    under = torch.nn.functional.normalize(land - cross, dim=-1)
    normal = torch.nn.functional.normalize(torch.cat([-slopes, torch.ones(200, 1, dtype=f64)], -1), dim=-1)
    sin_i = torch.linalg.cross(down, normal).norm(dim=-1)
    sin_t = torch.linalg.cross(under, normal).norm(dim=-1)
    assert torch.allclose(sin_i, WATER.n * sin_t, atol=1e-9)
    assert ((torch.linalg.cross(down, normal) * under).sum(-1).abs() < 1e-9).all()  # coplanar
    assert ((under * normal).sum(-1) < 0).all()  # into the water


def test_facet_offsets_refuse_a_tilted_surface():
    with pytest.raises(ValueError, match="horizontal"):
        facet_offsets(random_points(3), CAM, WaterSurface(WATER.level, 1.33, (0.01, 0.0)), _tilt([0.0, 0.0]))


def test_views_through_water_count_a_submerged_point_where_the_bent_ray_reaches_it():
    """A nadir camera 10 m above water of index 1.33 with a 90 degree view: its image's edge ray meets the
    surface at 10 m from the axis and bends towards the normal, so 2 m under water it reaches 10 + 2 tan(tw)
    m out, where a straight ray reaches 12 m. A bed point between the two is counted with n = 1 and not
    through the water; a dry point 0.5 m up inside the 9.5 m the edge ray reaches there is counted; a camera
    under the water counts nothing."""
    from ragsplat.camera import Camera
    from ragsplat.refraction import views_through_water

    down = np.diag([1.0, -1.0, -1.0])  # camera x = world x, camera y = world -y, looks down world -z
    cam = Camera.from_fov(64, 64, 90.0, down, -down @ np.array([0.0, 0.0, 10.0]))
    R, C = cam.R[None], cam.camera_center[None]
    K, sizes = np.array([[cam.fx, cam.fy, cam.cx, cam.cy]]), np.array([[cam.width, cam.height]])
    reach = 10.0 + 2.0 * math.tan(math.asin(math.sin(math.radians(45.0)) / 1.33))
    points = np.array([[0.0, 0.0, -2.0], [reach - 0.05, 0.0, -2.0], [reach + 0.05, 0.0, -2.0],
                       [11.5, 0.0, -2.0], [9.3, 0.0, 0.5]])
    water = WaterSurface(level=0.0, n=1.33)
    assert views_through_water(points, R, C, K, sizes, water).tolist() == [1, 1, 0, 0, 1]
    straight = WaterSurface(level=0.0, n=1.0)
    assert views_through_water(points, R, C, K, sizes, straight).tolist() == [1, 1, 1, 1, 1]
    high = WaterSurface(level=20.0, n=1.33)
    assert views_through_water(points, R, C, K, sizes, high).tolist() == [0] * 5
    two = views_through_water(points, np.concatenate([R, R]), np.concatenate([C, C + [30.0, 0, 0]]),
                              np.concatenate([K, K]), np.concatenate([sizes, sizes]), water)
    assert two.tolist() == [1, 1, 0, 0, 1]

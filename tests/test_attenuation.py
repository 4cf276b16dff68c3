"""Attenuation along the refracted path (issue 50): the in-water length from physics, its colour factor in
`refract_gaussians`, and the coefficients trained, saved and restored by the trainer."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import killed_and_resumed, tiny_smoke, water_bed, water_bed_config

from ragsplat import rendering
from ragsplat.cli.main import main
from ragsplat.dataset import Dataset, load_dataset
from ragsplat.errors import ConfigError
from ragsplat.gaussians import SH_C0
from ragsplat.refraction import (
    WATERLINE_BAND,
    linear_to_srgb,
    refract_gaussians,
    srgb_to_linear,
    water_paths,
    waterline_weight,
)
from ragsplat.rendering import rasterize_view, view_gaussians, visible_weights
from ragsplat.runs import load_model
from ragsplat.train import VARIANTS, TrainConfig, Trainer
from ragsplat.train import albedo as albedo_mod
from ragsplat.train.albedo import albedo_trend
from ragsplat.train.config import ATTENUATION_RANGE, DOWNWELLING
from ragsplat.water_surface import Profile, WaterSurface, plane_frame

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
    p = torch.tensor([[CAM[0] + r * math.cos(azimuth), CAM[1] + r * math.sin(azimuth), WATER.level - d]],
                     dtype=f64)
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


def test_curved_surface_is_each_tangent_plane_and_a_flat_profile_the_plane():
    g = torch.Generator().manual_seed(4)
    p = torch.cat([(torch.rand(30, 2, generator=g, dtype=f64) - 0.5) * 40,
                   -0.5 - 5 * torch.rand(30, 1, generator=g, dtype=f64)], 1)
    plane = WaterSurface(0.3, 1.33, (-0.01, 0.0))
    zero = WaterSurface(0.3, 1.33, (-0.01, 0.0), Profile((0.0, 0.0), (1.0, 0.0), (-30.0, 30.0), (0.0, 0.0)))
    torch.testing.assert_close(water_paths(p, CAM, zero), water_paths(p, CAM, plane), rtol=1e-12, atol=0)
    riffle = WaterSurface(0.3, 1.33, (-0.01, 0.0), Profile((0.0, 0.0), (1.0, 0.0), (-20, -4, 4, 20),
                                                           (0.03, 0.03, -0.03, -0.03)))
    L = water_paths(p, CAM, riffle)
    for i in (0, 7, 19):  # the plane tangent to the surface above the point, through that surface point
        xy = p[i:i + 1, :2]
        sx, sy = (float(v) for v in riffle.gradient(xy)[0])
        tangent = WaterSurface(float(riffle.height(xy)[0]) - sx * float(xy[0, 0]) - sy * float(xy[0, 1]),
                               1.33, (sx, sy))
        assert float(L[i]) == pytest.approx(float(water_paths(p[i:i + 1], CAM, tangent)[0]), rel=1e-12)


def test_gradients_match_finite_differences():
    g = torch.Generator().manual_seed(2)
    p = torch.cat([(torch.rand(6, 2, generator=g, dtype=f64) - 0.5) * 50,
                   WATER.level - 0.5 - 10 * torch.rand(6, 1, generator=g, dtype=f64)], 1)
    p[0, :2] = CAM[:2]  # nadir
    for water in (WATER, WaterSurface(0.3, 1.33, (-0.02, 0.01))):
        assert torch.autograd.gradcheck(lambda x, c, water=water: water_paths(x, c, water),
                                        (p.clone().requires_grad_(), CAM.clone().requires_grad_()),
                                        eps=1e-6, atol=1e-7, rtol=1e-6)


# ---- the colour factor in refract_gaussians
# -------------------------------------------------------------------
def _gaussians(n=30, seed=3):
    g = torch.Generator().manual_seed(seed)
    means = torch.cat([(torch.rand(n, 2, generator=g, dtype=f64) - 0.5) * 30,
                       # some above the level
                       WATER.level + 1 - 6 * torch.rand(n, 1, generator=g, dtype=f64)], 1)
    scales = 0.05 + 0.1 * torch.rand(n, 3, generator=g, dtype=f64)
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g, dtype=f64), dim=-1)
    return means, scales, quats, 0.2 + 0.7 * torch.rand(n, generator=g, dtype=f64), \
        torch.rand(n, 3, generator=g, dtype=f64)


C = torch.tensor([0.4, 0.1, 0.05], dtype=f64)  # 1/m: a red-absorbing river


@pytest.mark.parametrize("flags", [{"scale": "anisotropic", "color": False},
                                   {"scale": "isotropic", "color": True},
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


def test_downwelling_adds_the_daylight_s_way_down():
    """With downwelling k the factor is exp(-c (L + k d)): at nadir (L = d) exp(-c (1 + k) d); k = 0 is the
    view's path alone, bit for bit; under a tilted plane d is the depth along its normal."""
    g = _gaussians()
    plain = refract_gaussians(*g, CAM, WATER, attenuation=C)
    assert torch.equal(refract_gaussians(*g, CAM, WATER, attenuation=C, downwelling=0.0).colors, plain.colors)
    out = refract_gaussians(*g, CAM, WATER, attenuation=C, downwelling=1.5)
    depth = (WATER.level - g[0][:, 2]).clamp(min=0)
    torch.testing.assert_close(srgb_to_linear(out.colors),
                               srgb_to_linear(plain.colors) * torch.exp(-1.5 * C * depth[:, None]),
                               rtol=1e-12, atol=1e-15)
    nadir = torch.tensor([[float(CAM[0]), float(CAM[1]), WATER.level - 2.0]], dtype=f64)
    one = [nadir, g[1][:1], g[2][:1], g[3][:1], g[4][:1]]
    seen = refract_gaussians(*one, CAM, WATER, attenuation=C, downwelling=1.5).colors
    torch.testing.assert_close(srgb_to_linear(seen), srgb_to_linear(g[4][:1]) * torch.exp(-C * 2.5 * 2.0),
                               rtol=1e-12, atol=1e-15)
    tilted = WaterSurface(WATER.level, 1.33, (0.01, -0.03))
    a = refract_gaussians(*g, CAM, tilted, attenuation=C)
    b = refract_gaussians(*g, CAM, tilted, attenuation=C, downwelling=1.5)
    normal_depth = tilted.depth(g[0]).clamp(min=0) / math.sqrt(1 + 0.01**2 + 0.03**2)
    torch.testing.assert_close(srgb_to_linear(b.colors),
                               srgb_to_linear(a.colors) * torch.exp(-1.5 * C * normal_depth[:, None]),
                               rtol=1e-10, atol=1e-15)


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


# ---- training ----------------------------------------------------------------------------------------------
VARIANT = "2dgs+full+attenuation"


def _dataset(c):  # `water_bed` through the water's attenuation
    return water_bed(attenuation=torch.tensor(c))


def _cfg(**kw):
    return water_bed_config(**{"variant": VARIANT, **kw})


@pytest.mark.parametrize("truth,up", [((0.6, 0.4, 0.3), True), ((0.02, 0.02, 0.02), False)],
                         ids=["turbid", "clear"])
def test_training_moves_the_coefficients_towards_the_scenes(tmp_path, truth, up):
    """From the bed's own points, 150 steps: every channel leaves the start (0.1 1/m) towards the water the
    images were rendered through. (Recovering c within 25 % is the issue's measurement on `small-field`: on
    this tiny bed the views tell c from the colours too weakly, docs/method.md.)"""
    ds, points = _dataset(truth)
    np.save(tmp_path / "bed.npy", points)
    tr = Trainer(_cfg(iterations=150, init="points", init_points=str(tmp_path / "bed.npy")), ds)
    torch.testing.assert_close(tr.attenuation, torch.full((3,), 0.1))
    tr.train()
    c = tr.attenuation
    assert bool((c > 0.13).all()) if up else bool((c < 0.08).all()), c


def _sloping_bed(c):
    """`water_bed`'s scene on a bed sloping from 0.3 to 1.9 m deep, through water `c` (1/m) with the
    daylight's way down; the start: the bed's points with the colours the images show them in (a track's),
    which hold the water's dimming."""
    from ragsplat.bench.synthetic import bed_scene, render_views, ring_cameras
    from ragsplat.dataset import BedInfo
    from ragsplat.dataset.load import View

    level, c = 0.2, torch.tensor(c)
    scene = bed_scene(300, 1.0, 1.0, seed=0)
    scene["means"][:, 2] = level - (1.1 + 0.8 * scene["means"][:, 0])
    water = WaterSurface(level, 1.33)
    cams = ring_cameras(6, 24, level + 1.5, 2.5, target=(0, 0, level - 1.0))
    views = [View(f"{i:04d}", "train", "nadir", v["camera"], (v["image"] * 255).round().to(torch.uint8),
                  None, "", None, None)
             for i, v in enumerate(render_views(scene, cams, water, attenuation=c, downwelling=DOWNWELLING))]
    depth = water.depth(scene["means"])[:, None]
    seen = linear_to_srgb(srgb_to_linear(scene["colors"]) * torch.exp(-c * (1.2 + DOWNWELLING) * depth))
    return (Dataset(Path("mem"), water, views, BedInfo(depth=1.0, size=2.0)),
            np.concatenate([scene["means"].numpy(), seen.numpy()], 1))


def test_the_colours_trend_with_depth_goes_into_the_attenuation(tmp_path):
    """From tracks' colours, which already hold the water's dimming, the coefficients stay near their start
    unless the colours' trend with depth is moved into them (`detrend_albedo`); then every channel comes
    within 25 % of the water the images were rendered through (300 steps; 14-27 % of it without)."""
    truth = (0.6, 0.4, 0.3)
    ds, points = _sloping_bed(truth)
    np.save(tmp_path / "bed.npy", points)
    found = {}
    for detrend in (False, True):
        tr = Trainer(_cfg(iterations=300, init="points", init_points=str(tmp_path / "bed.npy"),
                          detrend_albedo=detrend, downwelling=DOWNWELLING), ds)
        tr.train()
        found[detrend] = tr.attenuation / torch.tensor(truth)
    assert bool((found[True] > 0.75).all() and (found[True] < 1.25).all()), found
    assert bool((found[False] < 0.5).all()), found


def detrend(tr):  # the transfer as after the trainer's step
    tr.albedo.transfer(tr.splats, tr.water, tr.terms["attenuation"], tr.step)


def test_detrending_keeps_a_nadir_render_and_leaves_no_trend(turbid):
    """One `AlbedoTransfer.transfer`: c rises by -b / (1 + k) per channel, and each submerged colour times the
    nadir dimming exp(-c (1 + k) d) is what it was (to round-off); the colours' trend is then 0 (to round-off,
    as the coefficients stay inside the range); above the water nothing changes."""
    tr = Trainer(_cfg(iterations=1, detrend_albedo=True, downwelling=DOWNWELLING), turbid)
    g = torch.Generator().manual_seed(4)
    with torch.no_grad():  # colours that darken with depth, and Gaussians at several depths
        tr.splats["means"][:, 2] = tr.water.level - 2 * torch.rand(tr.num_gaussians, generator=g)
        tr.splats["means"][:5, 2] = tr.water.level + 0.1
        depth = tr.water.depth(tr.splats["means"])
        tr.splats["sh0"][:, 0] = (linear_to_srgb(0.3 * torch.exp(-0.5 * depth.clamp(min=0))[:, None]
                                                 * torch.tensor([1.0, 0.8, 0.6])) - 0.5) / SH_C0
    before, c0 = tr.splats["sh0"].detach().clone(), tr.attenuation
    detrend(tr)
    k = 1 + DOWNWELLING
    wet = depth > 0
    c1 = tr.attenuation
    torch.testing.assert_close(c1, c0 + 0.5 / k, rtol=1e-4, atol=0)
    lin = srgb_to_linear(SH_C0 * tr.splats["sh0"].detach()[:, 0] + 0.5)
    lin0 = srgb_to_linear(SH_C0 * before[:, 0] + 0.5)
    d = depth[wet][:, None]
    torch.testing.assert_close(lin[wet] * torch.exp(-c1 * k * d), lin0[wet] * torch.exp(-c0 * k * d),
                               rtol=1e-5, atol=1e-7)
    assert torch.equal(tr.splats["sh0"].detach()[~wet], before[~wet])
    weight = torch.sigmoid(tr.splats["opacities"].detach()[wet]) * waterline_weight(depth[wet])
    seen = srgb_to_linear(SH_C0 * tr.splats["sh0"].detach()[wet][:, 0] + 0.5)
    assert float(albedo_trend(seen, depth[wet], weight)[0].abs().max()) < 1e-4


def test_a_faint_haze_at_depth_does_not_count(turbid):
    """Gaussians fainter than the extraction keeps (a haze where the bed is lost in turbid water) are left out
    of the trend: bright ones at depth do not lower c, and their colours are moved as every other's."""
    from ragsplat.surface import ExtractConfig

    def transfer(haze: bool):
        tr = Trainer(_cfg(iterations=1, detrend_albedo=True, downwelling=DOWNWELLING), turbid)
        g = torch.Generator().manual_seed(4)
        with torch.no_grad():
            tr.splats["means"][:, 2] = tr.water.level - 0.1 - 2 * torch.rand(tr.num_gaussians, generator=g)
            depth = tr.water.depth(tr.splats["means"])
            tr.splats["sh0"][:, 0] = (linear_to_srgb(0.3 * torch.exp(-0.5 * depth)[:, None].expand(-1, 3))
                                      - 0.5) / SH_C0
            if haze:  # the deepest tenth: faint and bright
                deep = depth > depth.quantile(0.9)
                tr.splats["sh0"][deep, 0] = (0.9 - 0.5) / SH_C0
                opacity = torch.full_like(depth[deep], ExtractConfig.min_opacity / 2)
                tr.splats["opacities"][deep] = torch.log(opacity / (1 - opacity))
        detrend(tr)
        return tr.attenuation

    torch.testing.assert_close(transfer(True), transfer(False), rtol=0.05, atol=0)
    assert bool((transfer(True) > 0.2).all())


@pytest.mark.parametrize("variant", ["full", "2dgs+full"])
def test_visible_weights_add_up_to_each_pixel_s_alpha(turbid, variant):
    """A pixel's compositing weights add up to its alpha, so the Gaussians' weights summed over the image are
    the alpha map's sum (to round-off); over a mask, its pixels' alpha; none is negative."""
    tr = Trainer(water_bed_config(variant, iterations=1), turbid)
    cam = tr.views[0].camera
    with torch.no_grad():
        g = view_gaussians(tr.splats, tr.centers[0], 0, tr.water, tr.flags, "torch", tr.cfg.surfels)
        alpha = rasterize_view(g, cam, tr.cfg.surfels, torch.zeros(3), "torch")[1][..., 0]  # [H, W]
    w = visible_weights(g, cam, tr.cfg.surfels, "torch")
    assert bool((w >= 0).all()) and float(alpha.sum()) > 10
    torch.testing.assert_close(w.sum(), alpha.sum(), rtol=1e-5, atol=0)
    mask = torch.zeros_like(alpha, dtype=torch.bool)
    mask[: cam.height // 2] = True
    half = visible_weights(g, cam, tr.cfg.surfels, "torch", mask)
    torch.testing.assert_close(half.sum(), alpha[mask].sum(), rtol=1e-5, atol=0)


def test_gaussians_hidden_under_the_bed_do_not_count(turbid):
    """The trend is the visible bed's: opaque Gaussians hidden 20 cm under a skin of wide opaque ones (away
    from its edge), bright and brightening with depth (where a fit weighted by opacity alone found c at
    60-70 % of the water's on the field reach), move the transfer's rise of c by under a tenth (5 %) from
    what the skin alone gives; with every Gaussian counted by its opacity instead, c falls below its start."""
    def transfer(hidden_bright: bool, by_opacity: bool = False):
        tr = Trainer(_cfg(iterations=1, detrend_albedo=True, downwelling=DOWNWELLING), turbid)
        with torch.no_grad():
            x, y = torch.meshgrid(torch.linspace(-0.9, 0.9, 12), torch.linspace(-0.9, 0.9, 12), indexing="ij")
            xy = torch.stack([x.reshape(-1), y.reshape(-1)], 1)  # [144, 2]
            inner = (xy.abs() < 0.8).all(1)  # [144]: 100 under the skin, away from its edge
            depth = 0.3 + 0.8 * (xy[:, 0] + 0.9)  # 0.3 .. 1.74 m, sloping along x
            n, m = len(xy), int(inner.sum())
            tr.splats["means"][:n] = torch.cat([xy, tr.water.level - depth[:, None]], 1)
            tr.splats["means"][n:n + m] = torch.cat([xy[inner], tr.water.level - depth[inner, None] - 0.2], 1)
            tr.splats["means"][n + m:, 2] = tr.water.level + 0.5  # the rest above the water
            tr.splats["scales"][:n, :2] = math.log(0.2)  # wide: they overlap into a skin
            tr.splats["scales"][n:n + m, :2] = math.log(0.04)
            tr.splats["opacities"][:n + m] = math.log(0.99 / 0.01)
            colour = 0.3 * torch.exp(-0.5 * depth)[:, None].expand(-1, 3)
            under = 0.3 * torch.exp(0.5 * depth[inner] + 0.1) if hidden_bright else colour[inner, 0]
            tr.splats["sh0"][:n, 0] = (linear_to_srgb(colour) - 0.5) / SH_C0
            tr.splats["sh0"][n:n + m, 0] = ((linear_to_srgb(under) - 0.5) / SH_C0)[:, None]
            if by_opacity:
                tr.albedo.shares = lambda: torch.sigmoid(tr.splats["opacities"])
            detrend(tr)
        return tr.attenuation - 0.1  # the rise from the start

    skin = transfer(False)
    torch.testing.assert_close(skin, torch.full((3,), 0.5 / (1 + DOWNWELLING)), rtol=1e-2, atol=0)
    torch.testing.assert_close(transfer(True), skin, rtol=0.1, atol=0)
    assert bool((transfer(True, by_opacity=True) < 0).all())


def test_the_transfer_runs_every_step_and_takes_the_weights_every_trend_every(turbid, monkeypatch):
    """The weights are taken on the first step of every `TREND_EVERY` and again once the strategy has replaced
    the Gaussians; the transfer runs after every step."""
    taken, moved = [], []
    monkeypatch.setattr(albedo_mod, "TREND_EVERY", 2)
    tr = Trainer(_cfg(iterations=6, detrend_albedo=True, downwelling=DOWNWELLING), turbid)
    shares, transfer = tr.albedo.shares, tr.albedo.transfer
    monkeypatch.setattr(tr.albedo, "shares", lambda: taken.append(tr.step) or shares())
    monkeypatch.setattr(tr.albedo, "transfer", lambda *a: moved.append(tr.step) or transfer(*a))
    for _ in range(3):
        tr.train_step()
    new = torch.nn.Parameter(tr.splats["means"].detach().clone())  # replaced, as a refinement does
    tr.splats["means"], tr.optimizers["means"].param_groups[0]["params"] = new, [new]
    for _ in range(3):
        tr.train_step()
    assert moved == [1, 2, 3, 4, 5, 6]
    assert taken == [1, 3, 4, 5]


def test_the_trend_is_the_slope_of_log_colour_against_depth():
    depth = torch.linspace(0.1, 3.0, 50, dtype=f64)
    colour = 0.4 * torch.exp(torch.tensor([-0.7, -0.2, 0.1], dtype=f64) * depth[:, None])
    sh0 = ((linear_to_srgb(colour) - 0.5) / SH_C0)[:, None]
    b, spread = albedo_trend(srgb_to_linear(SH_C0 * sh0[:, 0] + 0.5), depth, torch.ones_like(depth))
    torch.testing.assert_close(b, torch.tensor([-0.7, -0.2, 0.1], dtype=f64), rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(spread, depth.std(correction=0).expand(3))
    b, _ = albedo_trend(srgb_to_linear(SH_C0 * sh0[:, 0] + 0.5), torch.full_like(depth, 1.0),
                        torch.ones_like(depth))  # no spread: no trend
    assert torch.equal(b, torch.zeros(3, dtype=f64))


@pytest.fixture(scope="module")
def turbid():
    return _dataset((0.6, 0.4, 0.3))[0]


def test_coefficients_are_trained_and_resumed(turbid, tmp_path):
    cfg = _cfg(iterations=6, checkpoint_every=3)
    a = Trainer(cfg, turbid, tmp_path / "a")
    stats = a.train()
    assert (stats["attenuation"] == [float(c) for c in a.attenuation]
            and not torch.equal(a.attenuation, torch.full((3,), 0.1)))
    meta = json.loads((tmp_path / "a/config.json").read_text())
    assert meta["attenuation"] == [0.1] * 3 and meta["attenuation_final"] == stats["attenuation"]
    assert meta["config"]["water_terms"] == ["attenuation"]
    b, c = killed_and_resumed(cfg, turbid, tmp_path / "b")  # killed after 4 steps: resumes from step 3
    assert c.step == 3 and not torch.equal(c.attenuation, b.attenuation)
    c.train()
    # the same steps from the same state (its Adam moments too)
    assert torch.equal(c.attenuation, a.attenuation)
    assert torch.equal(c.splats["sh0"], a.splats["sh0"])


def test_a_run_with_the_transfer_resumes_as_the_uninterrupted_one(tmp_path, monkeypatch):
    """Killed after 4 steps and resumed from step 3 (a multiple of `TREND_EVERY`, here 3), the run takes the
    weights on the same steps and ends where the uninterrupted one does, bit for bit (the same process)."""
    monkeypatch.setattr(albedo_mod, "TREND_EVERY", 3)
    ds, points = _sloping_bed((0.6, 0.4, 0.3))
    np.save(tmp_path / "bed.npy", points)
    cfg = _cfg(iterations=7, checkpoint_every=3, init="points", init_points=str(tmp_path / "bed.npy"),
               detrend_albedo=True, downwelling=DOWNWELLING)
    a = Trainer(cfg, ds, tmp_path / "a")
    a.train()
    assert not torch.allclose(a.attenuation, torch.full((3,), 0.1), rtol=0.2)  # the transfer moved c
    _, c = killed_and_resumed(cfg, ds, tmp_path / "b")
    c.train()
    assert torch.equal(c.attenuation, a.attenuation)
    assert torch.equal(c.splats["sh0"], a.splats["sh0"])


def test_variants_without_the_term_have_none_and_call_the_transform_as_before(turbid, monkeypatch):
    calls = []
    real = rendering.refract_gaussians
    monkeypatch.setattr(rendering, "refract_gaussians", lambda *a, **k: calls.append(k) or real(*a, **k))
    plain = Trainer(_cfg(variant="2dgs+full", iterations=1), turbid)
    assert "attenuation" not in plain.terms and plain.attenuation is None
    plain.train()
    assert calls == [{**VARIANTS["2dgs+full"], "covariances": False, "check_camera": False}]
    assert plain.stats()["attenuation"] is None
    calls.clear()
    Trainer(_cfg(iterations=1), turbid).train()
    assert set(calls[0]) == {*VARIANTS["2dgs+full"], "covariances", "attenuation", "downwelling",
                            "check_camera"}
    assert (VARIANTS[VARIANT] == VARIANTS["2dgs+full"] and _cfg().surfels
            and _cfg().water_terms == ("attenuation",))
    dry = Dataset(Path("mem"), None, turbid.views, turbid.bed)  # no water, nothing to attenuate
    assert Trainer(_cfg(), dry).terms == {}


def test_coefficients_stay_in_natural_waters_range(turbid):
    tr = Trainer(_cfg(iterations=2, lr_attenuation=10.0), turbid)
    tr.train()
    lo, hi = ATTENUATION_RANGE
    assert bool(((tr.attenuation >= lo * (1 - 1e-6)) & (tr.attenuation <= hi * (1 + 1e-6))).all())
    with pytest.raises(ConfigError, match="attenuation_start"):
        _cfg(attenuation_start=20.0)
    with pytest.raises(ConfigError, match="lr_attenuation"):
        _cfg(lr_attenuation=0.0)


def test_ablation_row_and_renders_of_a_finished_run(evaluable_dataset, tmp_path, monkeypatch):
    """`ragsplat ablation --variants 2dgs+full+attenuation` trains its row, which records the coefficients;
    `ragsplat render` reproduces the trainer's renders through the water from config.json."""
    tiny_smoke(monkeypatch, tmp_path)
    assert main(["ablation", "--data", str(evaluable_dataset), "--out", str(tmp_path / "abl"),
                 "--preset", "smoke", "--variants", VARIANT, "--seeds", "0", "--init", "grid", "--jobs", "1",
                 "--no-download"]) == 0
    run = tmp_path / "abl" / VARIANT / "seed0"
    row = json.loads((run / "row.json").read_text())
    assert len(row["train_stats"]["attenuation"]) == 3
    model, ds = load_model(run, splits=("test",))
    cfg = TrainConfig.from_dict(json.loads((run / "config.json").read_text())["config"])
    trainer = Trainer(cfg, load_dataset(evaluable_dataset), run)  # resumes the finished checkpoint
    assert torch.equal(model.attenuation, trainer.attenuation)
    for interface in (True, False):
        for ours, theirs in zip(model.render(ds.test[0].camera, interface),
                                trainer.render(ds.test[0].camera, interface)):
            assert torch.equal(ours, theirs)


# ---- the SH cap under water (`TrainConfig.wet_sh_degree`) -------------------------------------------------
def _sh_splats(n=40, seed=5):
    """Degree-3 Gaussians with random view dependence, some above the level, some under it, some in the
    water line's blend band."""
    from ragsplat.gaussians import init_points

    g = torch.Generator().manual_seed(seed)
    z = torch.cat([WATER.level + 1 - 3 * torch.rand(n - 2, generator=g, dtype=f64),
                   torch.tensor([WATER.level - WATERLINE_BAND / 2, WATER.level], dtype=f64)])
    points = torch.cat([(torch.rand(n, 2, generator=g, dtype=f64) - 0.5) * 4, z[:, None]], 1)
    splats = init_points(points, torch.rand(n, 3, generator=g, dtype=f64), None, degree=3)
    with torch.no_grad():
        splats["shN"].copy_(0.3 * torch.randn(splats["shN"].shape, generator=g, dtype=f64))
    return splats


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_a_submerged_gaussian_s_colour_stops_at_the_wet_degree(backend):
    from ragsplat.gaussians import colors_for_view

    splats, other = _sh_splats(), torch.tensor([-3.0, 4.0, 20.0], dtype=f64)
    depth = WATER.depth(splats["means"].detach())
    wet, dry = depth >= WATERLINE_BAND, depth <= 0
    band = ~wet & ~dry
    assert wet.any() and dry.any() and band.any()
    full = rendering.view_gaussians(splats, CAM, 3, WATER, None, backend)
    same = rendering.view_gaussians(splats, CAM, 3, WATER, None, backend, wet_degree=3)
    assert torch.equal(full.colors, same.colors)  # 3: no cap, today's colours
    capped = [rendering.view_gaussians(splats, c, 3, WATER, None, backend, wet_degree=0).colors
              for c in (CAM, other)]
    flat = colors_for_view(splats, CAM, 0)
    for colors, centre in zip(capped, (CAM, other)):
        torch.testing.assert_close(colors[wet], flat[wet], rtol=1e-12, atol=1e-14)  # the same from anywhere
        torch.testing.assert_close(colors[dry], colors_for_view(splats, centre, 3)[dry], rtol=1e-12,
                                   atol=1e-14)
    assert not torch.allclose(capped[0][dry], capped[1][dry])  # above the water the view still matters
    w = waterline_weight(depth[band])[:, None]  # in the band: blended as the refraction is
    torch.testing.assert_close(capped[0][band], torch.lerp(full.colors[band], flat[band], w), rtol=1e-12,
                               atol=1e-14)
    # the same cap through the water's transform: only the colours it is given change
    through = rendering.view_gaussians(splats, CAM, 3, WATER, {"scale": "anisotropic"}, backend, wet_degree=0)
    plain = rendering.view_gaussians(splats, CAM, 3, WATER, {"scale": "anisotropic"}, backend)
    assert torch.equal(through.means, plain.means) and torch.equal(through.opacities, plain.opacities)


def test_the_wet_degree_s_gradient_never_reaches_a_submerged_gaussian_s_higher_sh():
    splats = _sh_splats()
    depth = WATER.depth(splats["means"].detach())
    out = rendering.view_gaussians(splats, CAM, 3, WATER, {"scale": "anisotropic"}, "torch", wet_degree=0)
    out.colors.sum().backward()
    grad = splats["shN"].grad.abs().sum((1, 2))
    assert (grad[depth >= WATERLINE_BAND] == 0).all() and (grad[depth <= 0] > 0).all()
    assert (splats["sh0"].grad.abs().sum((1, 2)) > 0).all()


def test_wet_sh_degree_is_a_degree():
    assert TrainConfig(wet_sh_degree=0).wet_sh_degree == 0 and TrainConfig().wet_sh_degree == 3
    with pytest.raises(ConfigError, match="wet_sh_degree"):
        TrainConfig(wet_sh_degree=4)


def test_training_and_a_finished_run_s_renders_use_the_config_s_wet_degree(turbid, monkeypatch):
    from ragsplat.runs import Model

    seen = []
    real = rendering.view_gaussians

    def spy(*a, **k):
        seen.append(a[9] if len(a) > 9 else k.get("wet_degree", 3))
        return real(*a, **k)

    monkeypatch.setattr(rendering, "view_gaussians", spy)
    tr = Trainer(_cfg(iterations=2, sh_degree=3, wet_sh_degree=1), turbid)
    tr.train()
    assert seen and set(seen) == {1}
    seen.clear()
    model = Model({k: v.detach() for k, v in tr.splats.items()}, tr.cfg, tr.flags, turbid.water,
                  torch.device("cpu"), "torch", tr.attenuation)
    model.render(turbid.views[0].camera)
    assert seen == [1]

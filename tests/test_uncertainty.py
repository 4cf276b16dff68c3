"""The per-cell uncertainty's features and model (ragsplat_core/uncertainty.py) from first principles."""

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from ragsplat.camera import Camera
from ragsplat.errors import ConfigError
from ragsplat.refraction import apparent_points
from ragsplat.surface import ExtractConfig, extract_surface, extract_surface_blocks
from ragsplat.uncertainty import (
    GEOMETRY_CAP,
    Z95,
    UncertaintyModel,
    calibrate,
    cell_features,
    conformal_rank,
    fit,
    sigma,
    tvu95,
    view_geometry,
)
from ragsplat.water_surface import WaterSurface

WATER = WaterSurface(0.0, 1.33)


def ring(target, radius, height, count, size=400, fov=60.0):
    """`count` cameras on a circle of `radius` m, `height` m above z = 0, all looking at `target`."""
    return [Camera.look_at((radius * math.cos(a), radius * math.sin(a), height), target, size, size, fov)
            for a in np.linspace(0, 2 * math.pi, count, endpoint=False)]


def grid_of_cameras(height=10.0, spacing=1.0):  # 3 x 3 nadir cameras
    return [Camera.look_at((x, y, height), (x, y, 0.0), 400, 400, 60.0)
            for x in (-spacing, 0, spacing) for y in (-spacing, 0, spacing)]


def sigma_by_differences(point, cameras, water, h=1e-6):
    """The vertical sigma for a unit pixel noise from central differences of the pixel of the true point
    (apparent point, then `Camera.project`): an independent path to the information matrix."""
    info = np.zeros((3, 3))
    for cam in cameras:
        def pixel(p, cam=cam):
            t = torch.tensor(p[None], dtype=torch.float64)
            if water is not None:
                t = apparent_points(t, torch.tensor(cam.camera_center), water)
            return cam.project(t.numpy())[0][0]

        J = np.column_stack([(pixel(point + h * e) - pixel(point - h * e)) / (2 * h) for e in np.eye(3)])
        info += J.T @ J
    return math.sqrt(np.linalg.inv(info)[2, 2])


def test_two_views_at_plus_minus_theta_in_air_give_the_closed_form():
    # a point on both optical axes at distance L: J^T J = (f / L)^2 (I - d d^T); the sum over d = (+-sin, 0,
    # -cos) has zz entry 2 (f / L)^2 sin^2(theta), so sigma_z = L / (f sqrt(2) sin(theta))
    L, point = 10.0, np.array([0.3, -0.2, -2.0])
    for theta in (math.radians(10), math.radians(25), math.radians(40)):
        cams = [Camera.look_at(point + L * np.array([s * math.sin(theta), 0, math.cos(theta)]), point, 300,
                               300, 50.0)
                for s in (1, -1)]
        want = L / (cams[0].fx * math.sqrt(2) * math.sin(theta))
        for water in (None, WaterSurface(0.0, 1.0)):  # air, and water of n = 1
            geo = view_geometry(point[None], cams, water)
            assert geo.views[0] == 2
            assert geo.sigma_z[0] == pytest.approx(want, rel=1e-9)


def test_at_n_1_it_is_a_pinhole_triangulation():
    rng = np.random.default_rng(3)
    cams = [Camera.look_at((*rng.uniform(-3, 3, 2), rng.uniform(6, 12)), (0, 0, -1.5), 320, 240, 70.0)
            for _ in range(6)]
    points = np.column_stack([rng.uniform(-0.5, 0.5, (5, 2)), rng.uniform(-3, -0.5, 5)])
    geo = view_geometry(points, cams, WaterSurface(0.0, 1.0))
    for p, s in zip(points, geo.sigma_z):
        assert s == pytest.approx(sigma_by_differences(p, cams, None), rel=1e-6)


def test_through_the_water_it_matches_differences_of_the_refraction_solve():
    cams = ring((0, 0, -2.0), 3.0, 10.0, 5) + grid_of_cameras()
    points = np.array([[0.1, 0.2, -2.0], [-0.4, 0.3, -0.7], [0.5, -0.5, -4.0]])
    for water in (WATER, WaterSurface(0.1, 1.34, (0.02, -0.01))):  # flat, and a sloping river's surface
        geo = view_geometry(points, cams, water)
        for p, s in zip(points, geo.sigma_z):
            assert s == pytest.approx(sigma_by_differences(p, cams, water), rel=1e-5)


def test_more_views_and_wider_baselines_are_more_precise_and_deeper_is_less():
    point = np.array([[0.0, 0.0, -2.0]])
    few, many = ring(point[0], 2.0, 10.0, 3), ring(point[0], 2.0, 10.0, 12)
    assert view_geometry(point, many, WATER).sigma_z[0] < view_geometry(point, few, WATER).sigma_z[0]
    by_radius = [view_geometry(point, ring(point[0], r, 10.0, 6), WATER).sigma_z[0] for r in (0.5, 1, 2, 4)]
    assert (np.diff(by_radius) < 0).all()
    cams = grid_of_cameras()
    deep = np.array([[0.0, 0.0, -z] for z in (0.5, 1, 2, 4, 8)])
    by_depth = view_geometry(deep, cams, WATER).sigma_z
    assert (np.diff(by_depth) > 0).all()


def test_a_view_that_does_not_see_the_point_does_not_count():
    point = np.array([[0.0, 0.0, -1.0]])
    seeing = grid_of_cameras()
    away = Camera.look_at((0, 0, 10.0), (30.0, 0, 0), 400, 400, 30.0)  # the point is outside its image
    underwater = Camera.look_at((0, 0, -0.5), (0, 0, -1.0), 400, 400, 60.0)  # not in the air: skipped
    a = view_geometry(point, seeing, WATER)
    b = view_geometry(point, seeing + [away, underwater], WATER)
    assert b.views[0] == a.views[0] == 9
    assert b.sigma_z[0] == a.sigma_z[0]
    one = view_geometry(point, seeing[:1], WATER)
    assert one.views[0] == 1 and one.sigma_z[0] == math.inf and math.isnan(one.dz_dlevel[0])
    f = cell_features(point, seeing[:1], WATER)
    assert f.geometry[0] == GEOMETRY_CAP


def retriangulate(point, cameras, observed, water, iterations=8):
    """Gauss-Newton on the reprojection error of the pixels `observed` [V, 2] under `water`, from `point`."""
    p = point.copy()
    for _ in range(iterations):
        J, r = [], []
        for cam, obs in zip(cameras, observed):
            def pixel(q, cam=cam):
                t = apparent_points(torch.tensor(q[None]), torch.tensor(cam.camera_center), water)
                return cam.project(t.numpy())[0][0]
            J.append(np.column_stack([(pixel(p + 1e-6 * e) - pixel(p - 1e-6 * e)) / 2e-6 for e in np.eye(3)]))
            r.append(pixel(p) - obs)
        J, r = np.vstack(J), np.concatenate(r)
        p -= np.linalg.lstsq(J, r, rcond=None)[0]
    return p


def test_a_level_error_moves_the_bed_by_n_minus_1_times_it():
    cams = grid_of_cameras(height=10.0, spacing=1.0)  # near-nadir: the paraxial (n - 1) dL holds
    points = np.array([[0.0, 0.0, -1.0], [0.3, -0.2, -3.0]])
    for n in (1.1, 1.33, 1.5):
        water = WaterSurface(0.0, n)
        geo = view_geometry(points, cams, water)
        assert geo.dz_dlevel == pytest.approx(-(n - 1) * np.ones(2), rel=0.03)  # views up to 8 deg off nadir
        assert geo.dz_dn == pytest.approx(points[:, 2] / n, rel=0.03)  # d(-d)/dn of z = L - n d'
        for p, slope_level, slope_n in zip(points, geo.dz_dlevel, geo.dz_dn):
            observed = [cam.project(apparent_points(torch.tensor(p[None]), torch.tensor(cam.camera_center),
                                                    water).numpy())[0][0] for cam in cams]
            # the bed triangulated under a level 2 cm too high, and an index 0.01 too large, through the solve
            z_level = retriangulate(p, cams, observed, replace(water, level=0.02))[2]
            z_n = retriangulate(p, cams, observed, replace(water, n=n + 0.01))[2]
            assert (z_level - p[2]) / 0.02 == pytest.approx(slope_level, rel=0.01)
            assert (z_n - p[2]) / 0.01 == pytest.approx(slope_n, rel=0.02)


def test_oblique_views_move_the_bed_more_and_the_first_order_slopes_still_hold():
    # views 30-50 degrees off nadir: a level error moves the bed by more than (n - 1) times it
    point = np.array([0.1, 0.0, -1.5])
    cams = ring(point, 4.0, 5.0, 6)
    geo = view_geometry(point[None], cams, WATER)
    observed = [cam.project(apparent_points(torch.tensor(point[None]), torch.tensor(cam.camera_center),
                                            WATER).numpy())[0][0] for cam in cams]
    z_level = retriangulate(point, cams, observed, replace(WATER, level=0.01))[2]
    assert (z_level - point[2]) / 0.01 == pytest.approx(geo.dz_dlevel[0], rel=0.02)
    assert geo.dz_dlevel[0] < -1.2 * (WATER.n - 1)


def test_the_systematic_term_adds_in_quadrature():
    cams = grid_of_cameras()
    points = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -3.0]])
    f = cell_features(points, cams, WATER, sigma_level=0.05, sigma_n=0.01)
    want = np.hypot(0.33 * 0.05, points[:, 2] / 1.33 * 0.01)
    assert f.systematic == pytest.approx(want, rel=0.03)
    model = UncertaintyModel(("one",), (0.02,))
    assert tvu95(model, f) == pytest.approx(Z95 * np.hypot(0.02, f.systematic))
    assert tvu95(model, f.matrix(model.features)) == pytest.approx(Z95 * 0.02 * np.ones(2))


def test_the_extraction_records_its_cells_without_changing_the_grid():
    rng = np.random.default_rng(0)
    n = 400
    xy = np.stack(np.meshgrid(np.linspace(0, 1, 20), np.linspace(0, 1, 20)), -1).reshape(-1, 2)
    means = np.column_stack([xy, -1 + 0.05 * np.sin(3 * xy[:, 0])])
    scales = np.column_stack([np.full((n, 2), 0.04), np.full(n, 0.003)])
    quats = np.tile([1.0, 0, 0, 0], (n, 1))
    keep = rng.random(n) > 0.04  # a few missing Gaussians leave holes to fill
    g = (means[keep], scales[keep], quats[keep], np.ones(keep.sum()))
    region = {"xmin": 0.0, "xmax": 1.0, "ymin": 0.0, "ymax": 1.0}
    cfg = ExtractConfig(n_samples=40_000, max_scale_gsd=math.inf, cell=0.05, despike_min_neighbours=10**6)
    plain, stats = extract_surface(*g, cfg, region, (0.0, 0.0))
    grid, with_cells = extract_surface(*g, cfg, region, (0.0, 0.0), cells=True)
    np.testing.assert_array_equal(grid, plain)
    assert {k: v for k, v in with_cells.items() if k != "cells"} == stats
    cells = with_cells["cells"]
    assert (cells["filled"].sum() == stats["grid_filled"]
            and not cells["filled"][:len(grid) - stats["grid_filled"]].any())
    assert (cells["samples"][~cells["filled"]] > 0).all()
    known = np.isfinite(cells["spread"])
    assert np.median(cells["spread"][known]) < 0.01  # thin discs: millimetres of height spread
    blocks, by_block = extract_surface_blocks(*g, cfg, 8, (0.0, 0.0), region, cells=True)
    np.testing.assert_array_equal(blocks, extract_surface_blocks(*g, cfg, 8, (0.0, 0.0), region)[0])
    assert by_block["blocks"] > 1 and all(len(v) == len(blocks) for v in by_block["cells"].values())
    f = cell_features(grid, grid_of_cameras(3.0, 0.5), WATER, cells)
    assert np.isfinite(f.spread).all() and (f.filled == cells["filled"]).all()
    assert f.depth == pytest.approx(-grid[:, 2])


def draw(rng, n):
    """Features [n, 5] like a bed's: a constant, geometry (m/px), depth (m), spread (m), filled."""
    return np.column_stack([np.ones(n), rng.uniform(0.005, 0.05, n), rng.uniform(0.1, 4, n),
                            rng.exponential(0.01, n), rng.random(n) < 0.1])


TRUE_W = np.array([0.01, 0.8, 0.004, 1.5, 0.06])


def fisher_se(F, w):
    """Standard errors of v = w^2 from the Gaussian NLL's Fisher information, 1/2 sum f_k^2 f_l^2 / var^2."""
    var = F**2 @ w**2
    info = 0.5 * (F**2 / var[:, None]).T @ (F**2 / var[:, None])
    return np.sqrt(np.diag(np.linalg.inv(info)))


def test_fit_recovers_heteroscedastic_weights_and_the_conformal_step_covers_95_percent():
    rng = np.random.default_rng(11)
    F = draw(rng, 200_000)
    e = rng.normal(0, np.sqrt(F**2 @ TRUE_W**2))
    model = fit(F, e, seeds=(1, 2), commit="abc")
    v = np.square(model.weights)
    se = fisher_se(F, TRUE_W)
    assert np.all(np.abs(v - TRUE_W**2) < 4 * se), (v, TRUE_W**2, se)
    assert model.fit_seeds == (1, 2) and model.scale == 1.0
    Fc = draw(rng, 50_000)
    model = calibrate(model, Fc, rng.normal(0, np.sqrt(Fc**2 @ TRUE_W**2)), seeds=(3,))
    assert model.calibration_seeds == (3,) and model.scale == pytest.approx(1.0, abs=0.03)
    Ft = draw(rng, 200_000)
    et = rng.normal(0, np.sqrt(Ft**2 @ TRUE_W**2))
    assert 0.94 <= np.mean(np.abs(et) <= tvu95(model, Ft)) <= 0.96
    assert sigma(model, Ft) == pytest.approx(tvu95(model, Ft) / Z95)


def test_the_conformal_step_corrects_a_model_that_is_too_narrow():
    rng = np.random.default_rng(5)
    F = draw(rng, 100_000)
    e = rng.normal(0, np.sqrt(F**2 @ TRUE_W**2))
    half = UncertaintyModel(("one", "geometry", "depth", "spread", "filled"), tuple(TRUE_W / 2))
    model = calibrate(half, F, e)
    assert model.scale == pytest.approx(2.0, rel=0.03)
    Ft = draw(rng, 100_000)
    assert 0.94 <= np.mean(np.abs(rng.normal(0, np.sqrt(Ft**2 @ TRUE_W**2))) <= tvu95(model, Ft)) <= 0.96


def test_conformal_rank_has_the_n_plus_1_correction():
    assert conformal_rank(19, 0.95) == 19
    assert conformal_rank(99, 0.95) == 95
    assert conformal_rank(100, 0.95) == 96
    with pytest.raises(ConfigError):
        calibrate(UncertaintyModel(("one",), (1.0,)), np.ones((18, 1)), np.ones(18))
    # 19 scores 1..19: the 19th, the largest
    model = calibrate(UncertaintyModel(("one",), (1.0 / Z95,)), np.ones((19, 1)), np.arange(1, 20.0))
    assert model.scale == pytest.approx(19.0)


def test_the_model_round_trips_through_json_and_refuses_nonsense():
    model = UncertaintyModel(("one", "depth"), (0.01, 0.003), 1.2, 0.95, (1, 2), (3,), "deadbeef",
                             {"fit_cells": 9})
    assert UncertaintyModel.from_json(model.to_json()) == model
    with pytest.raises(ConfigError):
        UncertaintyModel(("one",), (0.1, 0.2))
    with pytest.raises(ConfigError):
        UncertaintyModel.from_json('{"features": ["one"]}')
    with pytest.raises(ConfigError):
        cell_features(np.zeros((2, 3)) - 1, grid_of_cameras(), WATER).matrix(("nonsense",))

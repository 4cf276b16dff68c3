"""The water surface from the edge points a surveyor measures (`survey.water.fit_edge`)."""

import numpy as np
import pytest

from ragsplat.errors import DatasetError
from ragsplat.survey.water import fit_edge, profile


def banks(slope=(-0.01, 0.0), level=100.0, noise=0.01, count=15, seed=0, length=40.0, width=7.0):
    """Points on both banks of a reach along x (a slight bend), z on the plane plus RTK noise."""
    rng = np.random.default_rng(seed)
    x = np.concatenate([np.linspace(-length / 2, length / 2, count)] * 2) + 500.0
    y = np.concatenate([np.full(count, -width / 2), np.full(count, width / 2)]) + 0.5 * np.sin(x / 5) + 200.0
    z = level + slope[0] * x + slope[1] * y + rng.normal(0, noise, len(x))
    return np.column_stack([x, y, z])


def test_a_sloping_surface_is_found_with_its_fall():
    pts = banks(slope=(-0.01, 0.002))
    fit = fit_edge(pts)
    assert fit.kind == "plane"
    assert fit.slope[0] == pytest.approx(-0.01, abs=6e-4) and fit.slope[1] == pytest.approx(0.002, abs=3e-3)
    height = fit.level + fit.slope[0] * pts[:, 0] + fit.slope[1] * pts[:, 1]
    truth = 100.0 - 0.01 * pts[:, 0] + 0.002 * pts[:, 1]
    assert np.abs(height - truth).max() < 0.01  # within the noise everywhere along the reach
    assert fit.report()["inliers"] == len(pts)


def test_flat_water_stays_one_level():
    fit = fit_edge(banks(slope=(0.0, 0.0)))
    assert fit.kind == "level" and fit.slope == (0.0, 0.0)
    assert fit.level == pytest.approx(100.0, abs=0.01)


def test_a_wrong_point_is_left_out():
    pts = banks()
    pts[3, 2] += 0.5  # a rod on a stone, not on the water's edge
    fit = fit_edge(pts)
    assert not fit.inliers[3] and fit.inliers.sum() == len(pts) - 1
    assert fit.slope[0] == pytest.approx(-0.01, abs=6e-4)


def test_one_bank_gives_the_fall_along_it():
    pts = banks()[:15]  # a line: no cross slope can be told
    fit = fit_edge(pts)
    assert fit.kind == "plane" and fit.slope[0] == pytest.approx(-0.01, abs=1e-3)


def test_too_few_points_refused():
    with pytest.raises(DatasetError, match="at least 3"):
        fit_edge(np.zeros((2, 3)))


def test_profile_says_where_points_lie_along_the_reach():
    edge = banks()
    pts = np.column_stack([np.linspace(480, 520, 50), np.full(50, 200.0), np.zeros(50)])
    height = np.where(pts[:, 0] < 500, 1.0, -1.0)  # the first half under the surface, the rest above
    bins = profile(pts, height, edge[:, :2], bins=2)
    assert bins[0]["below"] > 0 and bins[0]["above"] == 0 and bins[1]["above"] > 0 and bins[1]["below"] == 0


def test_a_riffle_is_a_profile_and_a_plane_stays_a_plane():
    """A surface that falls 1 % over pools and steps down 8 cm more at a riffle: the points support a profile;
    its heights are right along the whole reach (within the noise), where the best plane is 2-3 cm off."""
    rng = np.random.default_rng(3)
    x = np.concatenate([np.linspace(-40, 40, 25)] * 2)
    y = np.concatenate([np.full(25, -4.0), np.full(25, 4.0)])
    step = -0.04 * np.tanh(x / 4)  # the riffle at x = 0
    z = 50.0 - 0.01 * x + step + rng.normal(0, 0.005, len(x))
    fit = fit_edge(np.column_stack([x, y, z]))
    assert fit.kind == "profile" and fit.profile is not None
    from ragsplat.refraction import WaterSurface

    surface = WaterSurface(fit.level, 1.33, fit.slope, fit.profile)
    xs = np.column_stack([np.linspace(-35, 35, 71), np.zeros(71)])
    truth = 50.0 - 0.01 * xs[:, 0] - 0.04 * np.tanh(xs[:, 0] / 4)
    assert np.abs(surface.height(xs) - truth).max() < 0.02
    plane = WaterSurface(fit.level, 1.33, fit.slope)
    assert np.abs(plane.height(xs) - truth).max() > 0.02
    assert fit_edge(banks()).kind == "plane"  # a straight fall stays a plane

"""The water surface from the edge points a surveyor measures (`survey.water.fit_edge`), and its level from
the shoreline in a pinhole model's points (`survey.water.shoreline_level`)."""

import numpy as np
import pytest

from ragsplat.errors import DatasetError
from ragsplat.survey.water import fit_edge, profile, shoreline_level


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
    from ragsplat.water_surface import WaterSurface

    surface = WaterSurface(fit.level, 1.33, fit.slope, fit.profile)
    xs = np.column_stack([np.linspace(-35, 35, 71), np.zeros(71)])
    truth = 50.0 - 0.01 * xs[:, 0] - 0.04 * np.tanh(xs[:, 0] / 4)
    assert np.abs(surface.height(xs) - truth).max() < 0.02
    plane = WaterSurface(fit.level, 1.33, fit.slope)
    assert np.abs(plane.height(xs) - truth).max() > 0.02
    assert fit_edge(banks()).kind == "plane"  # a straight fall stays a plane


def shore(level=0.3, slope=0.15, raised=1.33, noise=0.02, count=6000, seed=2):
    """A pinhole model's points over a lake shore: a beach rising in y (wavy along x) into dry land, a flat
    floor 1 m down, the ground under water raised to `level` + depth / `raised`, plus SfM noise."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-20, 20, (count, 2))
    z = np.maximum(-0.1 + slope * xy[:, 1] + 0.1 * np.sin(xy[:, 0] / 6), -1.0)
    return np.column_stack([xy, np.where(z < level, level + (z - level) / raised, z) + rng.normal(0, noise,
                                                                                                   count)])


@pytest.mark.parametrize("raised", [1.33, 1.5, 1.65])
def test_the_shoreline_gives_the_level_where_the_ground_bends(raised):
    # oblique rays raise the ground more than nadir's 1 / n: the bend still starts at the level
    found = shoreline_level(shore(raised=raised), 1.33, 0.15, 0.4)
    assert found is not None and found.straddling >= 300
    assert abs(found.level - 0.3) < 0.035 and abs(found.level - 0.3) < 4 * found.sigma + 0.005
    assert found.sigma < 0.02


def test_a_gentle_beach_in_noise_gives_an_honest_spread():
    found = shoreline_level(shore(slope=0.05), 1.33, 0.15, 0.4)
    assert found is None or found.sigma > 0.05  # never a sure level from a bend the noise hides


@pytest.mark.parametrize("kind", ["flat bed", "dry slope"])
def test_ground_that_does_not_bend_at_the_water_gives_no_shoreline(kind):
    rng = np.random.default_rng(0)
    xy = rng.uniform(-20, 20, (6000, 2))
    z = np.full(6000, -0.5) if kind == "flat bed" else 0.15 * xy[:, 1]
    found = shoreline_level(np.column_stack([xy, z + rng.normal(0, 0.02, 6000)]), 1.33, 0.3, 0.4)
    assert found is None or found.sigma > 0.05


def test_a_poorly_determined_level_is_taken_from_a_surer_shoreline():
    from types import SimpleNamespace

    from ragsplat.survey.stages.water import LEVEL_WARN, _by_shoreline, level_sigma
    from ragsplat.water_surface import WaterSurface

    points = shore()
    calls = []

    def adjusted(free, level):
        calls.append((free, level))
        return SimpleNamespace(water=WaterSurface(level, 1.33))

    def estimate(sigma):
        return {"free": ["level"], "relative_level": False, "sigma_m": {"level": sigma},
                "sigma_given_cameras_m": {"level": sigma}}

    sure = estimate(0.005)
    adj = SimpleNamespace(water=WaterSurface(0.2, 1.33))
    assert _by_shoreline(points, 1.33, adj, sure, adjusted)[1].level == 0.2 and not calls
    assert "shoreline" not in sure  # a determined level is not looked for at the shore
    poor = estimate(0.1)
    _, water, est = _by_shoreline(points, 1.33, adj, poor, adjusted)
    assert calls == [((), water.level)] and abs(water.level - 0.3) < 0.035
    assert est["by"] == "shoreline" and est["adjustment"] == {"level": 0.2, "sigma_m": 0.1}
    assert level_sigma(est)[0] == est["shoreline"]["sigma_m"] < LEVEL_WARN
    flat = np.column_stack([points[:, :2], np.full(len(points), -0.5)])
    calls.clear()
    kept = _by_shoreline(flat, 1.33, adj, estimate(0.1), adjusted)
    assert kept[1].level == 0.2 and not calls and kept[2]["shoreline"] is None

"""Where a bed gains or loses (`tools.density`): the views that see a submerged point through the water (the
refracted field of view, narrower under water than the straight one), the relief of a bump on a plane, and
binned summaries that partition the cells."""

import math

import numpy as np
import pytest

from ragsplat.camera import Camera
from ragsplat.water_surface import WaterSurface
from tools.density import BINS, breakdown, in_bin, relief, summary, views_seeing

N, H, D = 1.33, 10.0, 2.0  # index, camera height over the level, depth of the test points


def test_views_seeing_uses_the_refracted_field_of_view():
    cam = Camera.look_at([0.0, 0.0, H], [0.0, 0.0, 0.0], 64, 64, 60.0)
    t_w = math.asin(math.sin(math.radians(30)) / N)
    seen_edge = H * math.tan(math.radians(30)) + D * math.tan(t_w)  # the last ray, bent at the surface
    straight_edge = (H + D) * math.tan(math.radians(30))
    assert seen_edge < straight_edge - 0.3
    xs = [0.0, seen_edge - 0.05, seen_edge + 0.05, straight_edge - 0.05, -(seen_edge - 0.05)]
    points = np.array([[x, 0.0, -D] for x in xs])
    got = views_seeing(points, [cam], WaterSurface(0.0, N))
    np.testing.assert_array_equal(got, [1, 1, 0, 0, 1])
    # n = 1: the pinhole, whose edge is the straight one; two cameras count twice
    got = views_seeing(points, [cam, cam], WaterSurface(0.0, 1.0))
    np.testing.assert_array_equal(got, [2, 2, 2, 2, 2])


def test_relief_is_zero_on_a_plane_and_the_height_of_a_bump():
    x, y = np.meshgrid(np.arange(-1, 1.0001, 0.05), np.arange(-1, 1.0001, 0.05))
    plane = np.column_stack([x.ravel(), y.ravel(), 0.1 * x.ravel() - 0.05 * y.ravel() - 1.0])
    inner = (np.abs(plane[:, 0]) < 0.65) & (np.abs(plane[:, 1]) < 0.65)  # whole discs: a symmetric median
    np.testing.assert_allclose(relief(plane)[inner], 0.0, atol=1e-12)
    bump = plane.copy()
    top = np.flatnonzero((np.abs(bump[:, 0]) < 1e-9) & (np.abs(bump[:, 1]) < 1e-9))
    bump[top, 2] += 0.2
    assert relief(bump)[top] == pytest.approx(0.2 + relief(plane)[top], abs=1e-12)


def test_breakdown_partitions_the_cells_and_summarises_each_bin():
    rng = np.random.default_rng(0)
    n = 500
    keys = {"tracks": rng.integers(0, 20, n), "views": rng.integers(0, 90, n),
            "relief": rng.uniform(-3, 9, n)}
    dz = rng.normal(0, 0.03, n)
    dz[::7] = np.nan  # cells left out
    out = breakdown({"dem": dz}, keys)
    for key, rows in out.items():
        assert sum(r["cells"] for r in rows) == n, key  # every cell in exactly one bin
        assert [r["bin"] for r in rows] == list(BINS[key])
    rows = out["views"]
    m = in_bin(keys["views"], *BINS["views"][1], closed=True)
    assert rows[1]["dem"] == summary(dz[m])
    s = summary(np.array([0.01, -0.02, 0.05, np.nan]))
    # the hole is a miss: 2 of the 4 cells within 3 cm (not 2 of the 3 covered), and a quarter of holes leaves
    # no p95; median and bias are over the covered cells
    assert s["cover"] == 0.75 and s["good"] == pytest.approx(2 / 4) and s["p95_cm"] is None
    assert s["bias_cm"] == pytest.approx(100 * 0.04 / 3) and s["median_cm"] == pytest.approx(2.0)
    e = np.r_[np.linspace(0.0, 0.099, 100), np.nan]  # one hole in 101: the p95 is still among the errors
    assert summary(e)["p95_cm"] == pytest.approx(100 * np.percentile(np.r_[e[:100], 1e9], 95))

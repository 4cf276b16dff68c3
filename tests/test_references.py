"""The field's reference methods from first principles: Dietrich's multi-camera correction (nadir gives
depth x n; two symmetric cameras, whose straight rays meet right above the true point, give the true depth;
the angle filter), the TIN DEM (a plane exactly, a paraboloid to the linear interpolation's error; nothing
outside the hull), the tracks' outlier filter (an injected outlier removed, the rest kept), and the start's
fill of the tracks' gaps (in a hole only, on the filtered TIN)."""

import numpy as np
import pytest
import torch

from ragsplat.eval.references import dietrich
from ragsplat.refraction import apparent_points
from ragsplat.tracks import fill_gaps, gap_nodes, tin, track_filter
from ragsplat.water_surface import WaterSurface

N = 1.33


def test_dietrich_at_nadir_is_depth_times_n():
    app = np.array([[1.0, 2.0, -0.6], [0.0, 0.0, 0.5]])  # a submerged point and a dry one
    got = dietrich(app, np.array([[1.0, 2.0, 30.0]]), np.array([0, 1]), np.array([0, 0]),
                   WaterSurface(0.0, N))
    np.testing.assert_allclose(got, [[1.0, 2.0, -0.6 * N], [0.0, 0.0, 0.5]], atol=1e-12)


@pytest.mark.parametrize("offset", [3.0, 12.0, 25.0])
def test_dietrich_recovers_a_point_seen_by_two_symmetric_cameras(offset):
    # the light paths to X bend at the water; their straight air rays meet right above X (symmetry), where
    # Dietrich's assumption holds, so each camera's rule gives the true depth
    water, X, H = WaterSurface(0.0, N), np.array([0.0, 0.0, -2.0]), 20.0
    centres = np.array([[-offset, 0.0, H], [offset, 0.0, H]])
    crossing = []
    for c in centres:
        a = apparent_points(torch.tensor(X[None]), torch.tensor(c), water)[0].numpy()  # on the air ray
        d = a - c
        crossing.append(c + d * (-c[0] / d[0]))  # the air ray at x = 0
    assert crossing[0] == pytest.approx(crossing[1], abs=1e-9)
    got = dietrich(np.array([crossing[0]]), centres, np.array([0, 0]), np.array([0, 1]), water)
    np.testing.assert_allclose(got[0], X, atol=1e-9)
    straight = crossing[0][2] * N  # depth x n, the nadir rule, is wrong off nadir (0.4 % at 8.5 deg)
    assert abs(straight - X[2]) > 0.002 * abs(X[2])


def test_dietrich_angle_filter_and_reduction():
    app = np.array([[0.0, 0.0, -1.0]])
    centres = np.array([[0.0, 0.0, 10.0], [10.0, 0.0, 10.0]])  # nadir, and 45 degrees away
    point, camera = np.array([0, 0]), np.array([0, 1])
    both = dietrich(app, centres, point, camera, WaterSurface(0.0, N), reduce=np.mean)[0, 2]
    nadir = dietrich(app, centres, point, camera, WaterSurface(0.0, N), max_angle_deg=35)[0, 2]
    assert nadir == pytest.approx(-N) and both < nadir  # the oblique view's rule gives a deeper point
    assert np.isnan(dietrich(app, centres[1:], np.array([0]), np.array([0]), WaterSurface(0.0, N),
                             max_angle_deg=35)[0, 2])


def test_tin_recovers_a_plane_and_a_paraboloid_inside_the_hull():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-5, 5, size=(800, 2))
    nodes = np.stack(np.meshgrid(np.arange(-6, 6.01, 0.25), np.arange(-6, 6.01, 0.25)), -1).reshape(-1, 2)
    plane = tin(np.column_stack([xy, 0.3 * xy[:, 0] - 0.2 * xy[:, 1] + 1.0]), nodes)
    np.testing.assert_allclose(plane[:, 2], 0.3 * plane[:, 0] - 0.2 * plane[:, 1] + 1.0, atol=1e-9)
    assert np.abs(plane[:, :2]).max() <= 5.0 and len(plane) < len(nodes)  # nothing outside the hull
    bowl = tin(np.column_stack([xy, 0.05 * (xy**2).sum(1)]), nodes)
    err = bowl[:, 2] - 0.05 * (bowl[:, :2] ** 2).sum(1)
    assert err.min() >= -1e-9 and np.median(err) < 0.01  # linear interpolation of a convex surface: above it


def test_track_filter_removes_an_injected_outlier_and_keeps_the_rest():
    rng = np.random.default_rng(1)
    xy = rng.uniform(0, 10, size=(2000, 2))
    pts = np.column_stack([xy, np.sin(xy[:, 0] / 3) + rng.normal(0, 0.02, len(xy))])
    pts[7, 2] += 1.5
    keep = track_filter(pts)
    assert not keep[7] and keep.sum() == len(pts) - 1


def test_fill_gaps_fills_a_hole_from_the_filtered_tin_and_nowhere_else():
    rng = np.random.default_rng(2)
    xy = rng.uniform(-3, 3, size=(4000, 2))
    xy = xy[np.hypot(*xy.T) > 1.0]  # a round hole of radius 1 m, as deep bed with no tracks
    z = 0.2 * xy[:, 0] - 0.1 * xy[:, 1] - 1.0  # a sloping plane
    pts = np.column_stack([xy, z, np.tile([0.2, 0.4, 0.6], (len(xy), 1))])
    pts[np.argmin(np.hypot(*(xy - [1.1, 0.0]).T)), 2] += 2.0  # a gross outlier on the hole's rim
    fill = fill_gaps(pts, 0.2)
    assert fill.shape[1] == 6 and len(fill) > 0
    near = np.hypot(*fill[:, :2].T)
    assert near.max() < 1.0 + 1e-9  # only in the hole: elsewhere every node has a point within 0.2 m
    assert len(fill) >= 0.6 * np.pi / 0.2**2  # most of its ~78 nodes (those over 0.2 m from the rim's points)
    np.testing.assert_allclose(fill[:, :2] / 0.2, np.round(fill[:, :2] / 0.2), atol=1e-9)  # on the grid
    # the TIN of the filtered points: the plane to round-off, the outlier left out
    np.testing.assert_allclose(fill[:, 2], 0.2 * fill[:, 0] - 0.1 * fill[:, 1] - 1.0, atol=1e-9)
    np.testing.assert_allclose(fill[:, 3:], np.tile([0.2, 0.4, 0.6], (len(fill), 1)))  # the nearest colour
    assert fill_gaps(pts[:, :3], 0.2).shape == (len(fill), 3)
    dense = fill_gaps(pts, 5.0)  # no node is 5 m from every point inside the hull
    assert dense.shape == (0, 6)
    with pytest.raises(ValueError, match="spacing"):
        fill_gaps(pts, 0.0)


def test_gap_nodes_in_chunks_are_the_whole_grids_gaps():
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(3)
    xy = rng.uniform(-2.05, 3.1, size=(300, 2))
    tree = cKDTree(xy)
    lo, hi = xy.min(0), xy.max(0)
    xs, ys = (np.arange(np.floor(a / 0.2), np.ceil(b / 0.2) + 1) * 0.2 for a, b in zip(lo, hi))
    nodes = np.stack(np.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)  # the whole grid at once
    want = nodes[tree.query(nodes)[0] > 0.2]
    assert 0 < len(want) < len(nodes)
    # a column per chunk (twice), three columns, all at once
    for chunk in (1, len(ys), 3 * len(ys) + 1, 10**6):
        np.testing.assert_array_equal(gap_nodes(tree, lo, hi, 0.2, chunk), want)


def test_gridded_applies_the_outlier_filter_it_is_given():
    from ragsplat.eval.references import gridded

    x, y = np.meshgrid(np.linspace(0, 4, 21), np.linspace(0, 4, 21), indexing="ij")
    pts = np.column_stack([x.ravel(), y.ravel(), -1.0 - 0.1 * x.ravel()])
    pts[220, 2] += 2.0  # one track 2 m too high at the centre
    nodes = pts[:, :2]
    kept = gridded(pts, nodes, {"radius": 1.0, "tol": 0.3, "min_neighbours": 8})
    raw = gridded(pts, nodes, None)
    assert np.abs(kept[:, 2] - (-1.0 - 0.1 * kept[:, 0])).max() < 1e-9  # the plane again, the spike gone
    # unfiltered: the spike stays
    assert raw[np.argmax(raw[:, 2])][2] == pytest.approx(-1.0 - 0.1 * 2.0 + 2.0)


def test_tune_references_rule_prefers_1pct_within_half_a_point_at_3pct():
    from tools.tune_references import choose

    rows = [{"f1_1pct": 0.70, "f1_3pct": 0.960}, {"f1_1pct": 0.72, "f1_3pct": 0.956},
            {"f1_1pct": 0.80, "f1_3pct": 0.950}]
    assert choose(rows) == 1  # the third is more than 0.5 point below the best F1@3%
    assert choose(rows[:1]) == 0

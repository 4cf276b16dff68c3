import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from ragsplat.errors import ConfigError
from ragsplat.gaussians import quat_to_rotmat
from ragsplat.scoring import geometry_metrics
from ragsplat.surface import (
    ExtractConfig,
    despike,
    extract_surface,
    grid_median,
    largest_remainder,
    plane_filter,
    sample_gaussians,
)


def plane_grid(nx, ny, step, z=0.0):
    x, y = np.meshgrid(np.arange(nx) * step, np.arange(ny) * step, indexing="ij")
    return np.column_stack([x.ravel(), y.ravel(), np.full(x.size, z)])


def test_largest_remainder_hand_cases():
    # quotas 3.5, 2.1, 1.4: floors 3, 2, 1 leave one, which goes to the largest remainder (0.5)
    assert largest_remainder([0.5, 0.3, 0.2], 7).tolist() == [4, 2, 1]
    assert largest_remainder([1, 1, 1], 10).tolist() == [4, 3, 3]  # tie: lower index first
    c = largest_remainder(np.random.default_rng(0).random(1000), 12345)
    assert c.sum() == 12345 and (c >= 0).all()
    assert largest_remainder([0, 0], 5).tolist() == [0, 0]


def test_metrics_plane_shifted_5cm():
    gt = plane_grid(20, 20, 0.05)
    pred = gt + [0, 0, 0.05]
    m = geometry_metrics(pred, gt)
    assert m["accuracy"] == pytest.approx(0.05) and m["completeness"] == pytest.approx(0.05)
    assert m["chamfer"] == pytest.approx(0.05)
    for t in ("0.1", "0.3"):
        assert m[f"precision@{t}"] == 1.0 and m[f"recall@{t}"] == 1.0 and m[f"f1@{t}"] == 1.0


def test_metrics_strict_threshold():
    # dyadic spacing so every distance is exact: a shift equal to the threshold does not count
    gt = plane_grid(8, 8, 0.0625)
    m = geometry_metrics(gt + [0, 0, 0.25], gt, thresholds=(0.125, 0.25, 0.5))
    assert m["precision@0.25"] == 0.0 and m["recall@0.25"] == 0.0 and m["f1@0.25"] == 0.0
    assert m["f1@0.125"] == 0.0 and m["f1@0.5"] == 1.0


def test_metrics_half_coverage_hand_values():
    # GT 10 x 10 at 1/16 m; the prediction covers the first 5 columns exactly. Missing columns lie
    # 1, 2, 3, 4, 5 steps (0.0625 .. 0.3125 m) from the last predicted column.
    step = 0.0625
    gt = plane_grid(10, 10, step)
    pred = plane_grid(5, 10, step)
    m = geometry_metrics(pred, gt, thresholds=(0.125, 0.25))
    assert m["accuracy"] == 0.0
    assert m["completeness"] == pytest.approx(10 * step * (1 + 2 + 3 + 4 + 5) / 100)
    assert m["chamfer"] == pytest.approx(m["completeness"] / 2)
    assert m["precision@0.125"] == 1.0
    assert m["recall@0.125"] == pytest.approx(0.6)  # 50 covered + the 1-step column; 2 steps = 0.125 fails <
    assert m["f1@0.125"] == pytest.approx(2 * 0.6 / 1.6)
    assert m["recall@0.25"] == pytest.approx(0.8)  # 50 + columns at 1, 2, 3 steps (0.1875 < 0.25)


def test_metrics_empty_prediction():
    m = geometry_metrics(np.zeros((0, 3)), plane_grid(3, 3, 0.05))
    assert m["chamfer"] is None and m["f1@0.1"] == 0.0


def test_sampling_counts_truncation_and_culling():
    means = np.array([[0, 0, 0], [5, 0, 0], [10, 0, 0.0]])
    scales = np.array([[0.1, 0.1, 0.1], [0.2, 0.1, 0.1], [1.0, 1.0, 1.0]])
    quats = np.array([[1, 0, 0, 0], [0.9, 0.1, 0.3, 0.2], [1, 0, 0, 0.0]])
    opac = np.array([0.9, 0.9, 0.01])  # the huge third one is culled by opacity
    cfg = ExtractConfig(n_samples=3001, sigma_cut=2.0, min_opacity=0.1, max_scale_gsd=math.inf)
    pts, keep = sample_gaussians(torch.tensor(means), torch.tensor(scales), torch.tensor(quats),
                                 torch.tensor(opac), cfg)
    assert keep.tolist() == [True, True, False] and len(pts) == 3001
    near0 = np.linalg.norm(pts - means[0], axis=1) < 1
    assert near0.sum() == 1000  # volumes 1 : 2 -> 1000.33 / 2000.67 -> 1000 / 2001
    rot = quat_to_rotmat(torch.tensor(quats[1:2]))[0].numpy()
    local = (pts[~near0] - means[1]) @ rot / scales[1]  # back to standard-normal coordinates
    r = np.linalg.norm(local, axis=1)
    assert r.max() <= 2.0 and r.max() > 1.9  # truncated at 2 sigma, and the cut is reached
    np.testing.assert_allclose(local.mean(0), 0, atol=0.1)


def test_plane_filter_drops_floaters_and_isolated():
    rng = np.random.default_rng(0)
    bed = np.column_stack([rng.random((4000, 2)) * 2, 0.002 * rng.standard_normal(4000)])
    floaters = np.column_stack([rng.random((20, 2)) * 2, np.full(20, 0.05)])
    lonely = np.array([[5.0, 5.0, 0.0]])
    pts = np.vstack([bed, floaters, lonely])
    keep = plane_filter(pts, ExtractConfig(filter_radius=0.1, filter_k=2.0))
    assert keep[:4000].mean() > 0.9
    assert not keep[4000:].any()


def test_plane_filter_kernel_matches_numpy_twin():
    # a bumpy, noisy bed with floaters, sparse patches (few neighbours) and isolated points: every branch
    rng = np.random.default_rng(1)
    xy = rng.random((6000, 2)) * 3
    bed = np.column_stack([xy, 0.1 * np.sin(3 * xy[:, 0]) * np.cos(2 * xy[:, 1])
                           + 0.004 * rng.standard_normal(6000)])
    sparse = np.column_stack([5 + rng.random((40, 2)) * 0.3, 0.02 * rng.standard_normal(40)])
    floaters = np.column_stack([rng.random((60, 2)) * 3, rng.uniform(0.02, 0.2, 60)])
    pts = rng.permutation(np.vstack([bed, sparse, floaters, [[9.0, 9.0, 0.0], [0.0, -9.0, 0.0]]]))
    cfg = ExtractConfig(filter_radius=0.1, filter_k=2.0)
    fast, twin = plane_filter(pts, cfg, chunk=2500), plane_filter(pts, cfg, chunk=2500, fast=False)
    # booleans from float64 fits (numba vs numpy, ~1e-13 apart): every point is >= 1e-4 (relative) from its
    # threshold here (measured), so the two agree exactly
    np.testing.assert_array_equal(fast, twin)
    assert 0.5 < fast.mean() < 1  # both outcomes occur
    # isolated points tested too
    lax = ExtractConfig(filter_radius=0.1, filter_k=2.0, filter_min_neighbours=0)
    np.testing.assert_array_equal(plane_filter(pts, lax, chunk=2500),
                                  plane_filter(pts, lax, chunk=2500, fast=False))


def test_grid_median_ignores_one_floater():
    pts = np.array([[0.01, 0.01, 0.0], [0.02, 0.03, 0.1], [0.04, 0.02, 10.0], [0.08, 0.01, -1.0]])
    g = grid_median(pts, 0.05, origin=(-0.025, -0.025))  # nodes at odd multiples of 2.5 cm
    np.testing.assert_allclose(g, [[0.025, 0.025, 0.1], [0.075, 0.025, -1.0]])
    # with nodes on multiples of 5 cm the cells are centred on them: the first three points split
    g = grid_median(pts, 0.05, origin=(0.0, 0.0))
    np.testing.assert_allclose(g, [[0.0, 0.0, 0.0], [0.0, 0.05, 0.1], [0.05, 0.0, 10.0], [0.1, 0.0, -1.0]])


def undulating_bed(step=0.05):  # 1 m of relief over a 3 m wavelength, as the rough bed
    x, y = np.meshgrid(np.arange(-3, 3, step), np.arange(-2, 2, step), indexing="ij")
    return np.column_stack([x.ravel(), y.ravel(), 0.5 * np.cos(2 * np.pi * x.ravel() / 3) - 1.5])


def test_despike_drops_a_floater_patch_and_keeps_the_relief():
    bed = undulating_bed()
    assert despike(bed, 0.05, 1.0, 0.3).all()  # the default: every cell of the relief stays
    patch = (np.abs(bed[:, 0] - 1.0) < 0.2) & (np.abs(bed[:, 1] + 0.5) < 0.2)  # 64 cells, 0.4 m wide
    for dz in (2.0, -0.6):  # floaters above, a hole below
        spiked = bed + np.where(patch, dz, 0.0)[:, None] * [0, 0, 1]
        keep = despike(spiked, 0.05, 1.0, 0.3)
        # booleans: the patch is 0.6 m or more off, the tolerance 0.3
        np.testing.assert_array_equal(keep, ~patch)
    # too tight a tolerance takes the crests and troughs of real relief: a test that can fail
    assert not despike(bed, 0.05, 1.0, 0.05).all()
    assert despike(spiked, 0.05, 1.0, np.inf).all()  # off


def test_despike_tiles_give_the_same_cells():
    # tiles of 16 cells (the disc is 20 cells wide) against one tile holding the whole bed; a far floater
    # alone in its tile, 5 km away, has no neighbours and is kept (the point filter's job), and costs no
    # memory
    bed = undulating_bed()
    rng = np.random.default_rng(0)
    spiked = bed + (rng.random(len(bed)) < 0.02)[:, None] * [0, 0, 1.0]
    far = np.vstack([spiked, [[5000.0, 5000.0, 3.0]]])
    whole, tiled = despike(far, 0.05, 1.0, 0.3, block=256), despike(far, 0.05, 1.0, 0.3, block=16)
    # medians select values: the same neighbours, the same verdicts
    np.testing.assert_array_equal(tiled, whole)
    assert tiled[-1] and 0 < (~tiled).sum() < len(bed)


def test_despike_matches_a_cell_by_cell_reference():
    # rough relief with spikes and holes of every size, even and odd neighbour counts, edges
    rng = np.random.default_rng(3)
    bed = undulating_bed(0.1)
    bed = bed[rng.random(len(bed)) < 0.8]  # holes: counts vary
    bed[:, 2] += rng.normal(0, 0.05, len(bed)) + (rng.random(len(bed)) < 0.05) * rng.normal(0, 1.0, len(bed))
    tree = cKDTree(bed[:, :2])
    ref = np.ones(len(bed), dtype=bool)
    for g, near in enumerate(tree.query_ball_point(bed[:, :2], 0.5 + 1e-6)):
        others = [k for k in near if k != g]
        if len(others) >= 8:
            ref[g] = abs(bed[g, 2] - np.median(bed[others, 2])) <= 0.3
    keep = despike(bed, 0.1, 0.5, 0.3, block=16, chunk=100)
    # a median selects (or halves a sum of two) values: exact both ways
    np.testing.assert_array_equal(keep, ref)
    assert 0 < (~keep).sum() < 0.2 * len(bed)


def test_despike_needs_enough_neighbours():
    lone = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.0, 0.05, 5.0]])  # 2 neighbours each: no verdict
    assert despike(lone, 0.05, 1.0, 0.3).all()
    assert not despike(lone, 0.05, 1.0, 0.3, min_neighbours=2).all()
    # a coarse DEM: 1 m cells have 4 neighbours within 1 m, fewer than the default 8
    coarse = plane_grid(5, 5, 1.0)
    coarse[12, 2] = 3.0
    assert despike(coarse, 1.0, 1.0, 0.3).all() and not despike(coarse, 1.0, 1.0, 0.3, min_neighbours=4)[12]


def test_extraction_recovers_a_flat_bed():
    # flat discs tiling the plane z = -1, small opaque floaters half a metre above it (their samples are
    # outvoted by the bed in every cell's median) and one huge faint blob that culling must remove
    step = 0.05
    bed = plane_grid(40, 40, step, z=-1.0)
    n = len(bed)
    fl = np.column_stack([np.random.default_rng(1).random((5, 2)) * 2, np.full(5, -0.5)])
    means = np.vstack([bed, fl, [[1.0, 1.0, -0.7]]])
    scales = np.vstack([np.tile([0.03, 0.03, 0.003], (n, 1)), np.tile([0.01, 0.01, 0.01], (5, 1)),
                        [[1.0, 1.0, 1.0]]])
    quats = np.tile([1.0, 0, 0, 0], (n + 6, 1))
    opac = np.append(np.full(n + 5, 0.8), 0.05)
    region = {"xmin": 0.2, "xmax": 1.7, "ymin": 0.2, "ymax": 1.7}
    cfg = ExtractConfig(n_samples=40_000, gsd=0.025)  # the default size cull: sigma <= 6 x 2.5 cm
    grid, stats = extract_surface(means, scales, quats, opac, cfg, region)
    assert stats["samples"] == 40_000 and stats["gaussians_sampled"] == n + 5 and stats["grid_spikes"] == 0
    assert stats["config"]["n_samples"] == 40_000
    gt = plane_grid(31, 31, step, z=-1.0) + [0.2, 0.2, 0]
    m = geometry_metrics(grid, gt)
    assert m["chamfer"] < 0.005 and m["f1@0.1"] == 1.0
    assert np.abs(grid[:, 2] + 1).max() < 0.01  # no cell took a floater's height


def test_extraction_despikes_a_floater_patch():
    # the bed z = -1 with a 0.3 m square gap, and there a patch of small opaque discs 1.5 m higher: each of
    # its cells has only floater samples, so the point filter and the medians keep them; despiking drops them
    step = 0.05
    bed = plane_grid(40, 40, step, z=-1.0)
    gap = (np.abs(bed[:, 0] - 1.0) < 0.15) & (np.abs(bed[:, 1] - 1.0) < 0.15)
    means = np.vstack([bed[~gap], bed[gap] + [0, 0, 1.5]])
    n = len(means)
    scales, quats, opac = (np.tile([0.03, 0.03, 0.003], (n, 1)), np.tile([1.0, 0, 0, 0], (n, 1)),
                           np.full(n, 0.9))
    region = {"xmin": 0.2, "xmax": 1.7, "ymin": 0.2, "ymax": 1.7}
    cfg = ExtractConfig(n_samples=40_000, gsd=0.025, fill_gap_cells=0.0)  # the despiked cells stay empty
    kept, _ = extract_surface(means, scales, quats, opac, replace(cfg, despike_tol=math.inf), region)
    assert (kept[:, 2] > 0).sum() >= 20  # the patch is in the grid without despiking
    grid, stats = extract_surface(means, scales, quats, opac, cfg, region)
    assert stats["grid_spikes"] >= 20 and np.abs(grid[:, 2] + 1).max() < 0.01
    assert len(grid) == len(kept) - stats["grid_spikes"]
    filled, fstats = extract_surface(means, scales, quats, opac, replace(cfg, fill_gap_cells=1.0), region)
    assert fstats["grid_filled"] > 0 and np.abs(filled[:, 2] + 1).max() < 0.01  # the hole's rim, at the bed


def test_wide_gaussians_are_not_sampled():
    # small thin discs tiling the plane z = -1 and one opaque disc (sigma 0.5 m = 10 cells) 30 cm above them,
    # tilted by 10 degrees: by volume it takes most samples and wins the median of many cells it covers;
    # with the cull the grid is the bed again
    step = 0.05
    bed = plane_grid(40, 40, step, z=-1.0)
    n = len(bed)
    means = np.vstack([bed, [[1.0, 1.0, -0.7]]])
    scales = np.vstack([np.tile([0.03, 0.03, 0.0003], (n, 1)), [[0.5, 0.5, 0.003]]])
    tilt = math.radians(10)
    quats = np.vstack([np.tile([1.0, 0, 0, 0], (n, 1)), [[math.cos(tilt / 2), math.sin(tilt / 2), 0, 0]]])
    opac = np.full(n + 1, 0.9)
    region = {"xmin": 0.2, "xmax": 1.7, "ymin": 0.2, "ymax": 1.7}
    wide = ExtractConfig(n_samples=40_000, max_scale_gsd=math.inf)
    grid, stats = extract_surface(means, scales, quats, opac, wide, region)
    assert stats["gaussians_sampled"] == n + 1 and (grid[:, 2] > -0.9).sum() > 50
    cfg = ExtractConfig(n_samples=40_000, max_scale_gsd=4.0, gsd=0.025)  # sigma <= 10 cm
    grid, stats = extract_surface(means, scales, quats, opac, cfg, region)
    assert stats["gaussians_sampled"] == n and np.abs(grid[:, 2] + 1).max() < 0.01
    with pytest.raises(ConfigError, match="ground sample distance"):  # a size cull with nothing to scale it
        extract_surface(means, scales, quats, opac, replace(cfg, gsd=None), region)


def test_the_size_cull_is_six_pixels_or_the_relief_whichever_is_smaller_but_three_pixels_at_least():
    """6 ground sample distances on `small` (2.33 cm: 14 cm, the relief's limit lies just above it), the
    relief's 14 cm on the long reach (4.66 cm: 3 pixels), 3 pixels where 14 cm would be fewer (smoke, 7 cm);
    an explicit smaller K stands, inf lifts either limit."""
    from ragsplat.surface import max_scale

    def cull(gsd, **kw):
        return max_scale(ExtractConfig(gsd=gsd, **kw))

    assert cull(0.023286) == pytest.approx(6 * 0.023286, rel=1e-12)
    assert cull(0.046572) == pytest.approx(0.14, rel=1e-12)
    assert cull(0.07) == pytest.approx(0.21, rel=1e-12)
    assert cull(0.046572, max_scale_gsd=2.0) == pytest.approx(2 * 0.046572, rel=1e-12)
    assert cull(0.046572, max_scale_m=math.inf) == pytest.approx(6 * 0.046572, rel=1e-12)
    assert cull(0.046572, max_scale_gsd=math.inf) == math.inf


def test_fill_holes_recovers_a_plane_and_leaves_wide_gaps():
    # A plane on a 5 cm lattice with one-cell holes and a hole 5 cells wide: filling 1 cell gives back the
    # plane's exact height in the small holes and leaves the wide one empty; 0 changes nothing.
    from ragsplat.surface import fill_holes

    cell, origin = 0.05, (0.1, -0.2)
    i, j = np.meshgrid(np.arange(40), np.arange(30), indexing="ij")
    xy = np.column_stack([i.ravel(), j.ravel()]) * cell + origin
    full = np.column_stack([xy, 0.3 * xy[:, 0] - 0.2 * xy[:, 1] + 1.0])
    small = ((i % 7 == 3) & (j % 5 == 2)).ravel()  # isolated one-cell holes
    wide = ((i >= 20) & (i < 25) & (j >= 10) & (j < 15)).ravel()
    grid = full[~small & ~wide]
    assert fill_holes(grid, cell, origin, 0.0) is grid
    filled = fill_holes(grid, cell, origin, 1.0)
    assert np.array_equal(filled[:len(grid)], grid)  # the measured cells first, unchanged
    new = filled[len(grid):]
    # the wide hole's cells next to measured ones
    rim = wide & ~((i > 20) & (i < 24) & (j > 10) & (j < 14)).ravel()
    cells = lambda p: set(map(tuple, np.round((p[:, :2] - origin) / cell).astype(int)))
    assert cells(new) == cells(full[small | rim])  # the wide hole's inner 3 x 3 stays empty
    np.testing.assert_allclose(new[:, 2], 0.3 * new[:, 0] - 0.2 * new[:, 1] + 1.0, atol=1e-12)
    line = full[((j == 4) & (i % 3 != 1)).ravel()]  # one row with gaps: no hull to interpolate in
    assert fill_holes(line, cell, origin, 1.0) is line

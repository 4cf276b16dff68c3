"""The river reach: a channel whose geometry must be recovered from the images. Checked on the heightfield:
a waterline exists, banks rise above the water, depths span 0 to the spec's maximum, the floor continues the
border cross-section, the scene is seeded, and trivial answers (flat planes) score badly against it."""

import numpy as np
import pytest

from ragsplat.datagen import flight
from ragsplat.datagen.assets import scene_geometry
from ragsplat.datagen.bed import ground_truth, make_bed, waterline
from ragsplat.datagen.build import null_models
from ragsplat.datagen.spec import preset


@pytest.fixture(scope="module")
def smoke():
    spec = preset("smoke")
    return spec, make_bed(spec)


def wet_grid(spec, bed):
    wet, banks = ground_truth(spec, bed, flight.eval_region(spec), 0.05)
    assert (wet[:, 2] < spec.level).all() and (banks[:, 2] >= spec.level).all()
    return np.concatenate([wet, banks]), wet


def test_channel_banks_and_depth_range(smoke):
    spec, bed = smoke
    r, h = spec.reach, bed.mesh_heights - spec.level
    assert h.min() == pytest.approx(-r.max_depth, abs=0.02)  # the deepest pool
    assert h.max() > r.bank_height  # banks (and the land on them) stand above the water
    across = h[:, h.shape[1] // 2]  # one cross-section, from y = -size/2 to +size/2
    assert across[0] > 0 and across[-1] > 0 and across.min() < -0.3 * r.max_depth  # bank, channel, bank
    grid, wet = wet_grid(spec, bed)
    depth = spec.level - wet[:, 2]
    assert depth.min() < 0.05 and depth.max() > 0.9 * r.max_depth  # 0 at the waterline .. the pools
    assert 0.5 < len(wet) / len(grid) < 1.0  # the evaluated area is mostly, not only, water


def test_waterline_runs_along_both_banks(smoke):
    spec, bed = smoke
    lines = sorted(waterline(bed, spec.level), key=len, reverse=True)
    span = bed.extent
    for line in lines[:2]:  # the two banks: polylines across the whole reach
        assert np.ptp(line[:, 0]) > 0.9 * span
    assert lines[0][:, 1].mean() * lines[1][:, 1].mean() < 0  # one on each side of the channel


def test_floor_continues_the_border_cross_section(smoke):
    spec, bed = smoke
    geo = scene_geometry(spec, bed)
    fv = geo["floor_verts"]
    # every floor vertex lies on the border cross-section or on the land beyond it
    k = bed.mesh_heights.shape[0]
    ys = bed.x0 + np.arange(k) * bed.cell
    expect = np.interp(fv[:, 1], ys, bed.profile[:: bed.stride], left=bed.z0, right=bed.z0)
    np.testing.assert_allclose(fv[:, 2], expect, atol=1e-12)
    # and the bed mesh meets it: the outermost mesh columns are the cross-section
    np.testing.assert_allclose(bed.mesh_heights[:, 0], bed.profile[:: bed.stride], atol=1e-12)
    np.testing.assert_allclose(bed.mesh_heights[:, -1], bed.profile[:: bed.stride], atol=1e-12)
    tri = fv[geo["floor_tris"]]
    normal_z = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])[:, 2]
    assert np.all(normal_z > 0)  # counter-clockwise from above, like the bed


def test_same_seed_same_reach(smoke):
    spec, bed = smoke
    again = make_bed(spec)
    assert np.array_equal(again.heights, bed.heights) and np.array_equal(again.albedo, bed.albedo)
    assert not np.allclose(make_bed(preset("smoke", seed=1)).heights, bed.heights)


@pytest.mark.parametrize("name, seed", [("smoke", s) for s in range(4)] + [("small", 0), ("small", 1)])
def test_flat_planes_score_badly(name, seed):
    """The benchmark's target: a plane at the median bed height scores F1 < 40 % at 3 % of the maximum
    depth."""
    spec = preset(name, seed=seed)
    _, wet = wet_grid(spec, make_bed(spec))
    scores = null_models(spec, wet)
    assert scores["thresholds_m"]["3%"] == pytest.approx(0.03 * spec.reach.max_depth)
    for plane in ("median_plane", "mean_depth_plane"):
        assert scores[plane]["f1_3%"] < 0.40, scores[plane]
        assert scores[plane]["f1_1%"] < scores[plane]["f1_3%"] < scores[plane]["f1_30cm"]

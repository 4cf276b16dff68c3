"""End to end at smoke scale under a sloping water surface (`smoke-slope`, 1 %): the dataset carries the
surface in transforms.json and scene.json and loads with it; the rendered dry depth unprojects onto the
sheared bed; the survey's water-edge points lie on the surface and water_level.txt is one level at their
mean; the ripples of a sloping river ride on its mean surface."""

import json
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from ragsplat.camera import Camera
from ragsplat.cli.main import main
from ragsplat.dataset import layout, load_dataset

pytestmark = pytest.mark.blender

SLOPE = (-0.01, 0.0)


@pytest.fixture(scope="module")
def smoke_slope(tmp_path_factory):
    out = tmp_path_factory.mktemp("data") / "smoke-slope"
    assert main(["generate", "--preset", "smoke-slope", "--out", str(out), "--quiet"]) == 0
    return out


def test_the_dataset_carries_and_loads_the_sloping_surface(smoke_slope):
    tf = json.loads((smoke_slope / layout.TRANSFORMS).read_text())
    scene = json.loads((smoke_slope / layout.SCENE).read_text())
    assert tf["water"] == scene["water"] == {"level": 0.0, "n": 1.33, "slope": list(SLOPE)}
    assert scene["spec"]["water"]["slope"] == list(SLOPE)
    data = load_dataset(smoke_slope, load_dry=False, ground_truth=True)
    truth = data.ground_truth
    assert data.water.slope == SLOPE and truth.water.slope == SLOPE
    depth = truth.water.depth(truth.grid)
    assert depth.min() > 0 and 0.9 * truth.max_depth < depth.max() < truth.max_depth  # as in smoke
    assert (truth.water.depth(truth.banks) <= 0).all()
    assert scene["null_models"]["median_plane"]["f1_3%"] < 0.4


def test_dry_depth_unprojects_onto_the_sheared_bed(smoke_slope):
    tf = json.loads((smoke_slope / layout.TRANSFORMS).read_text())
    surface = layout.Surface.load(smoke_slope / layout.GT_SURFACE)
    edge = surface.x0 + (surface.heights.shape[0] - 1) * surface.cell
    worst, count = 0.0, 0
    for f in tf["frames"]:
        cam = Camera.from_c2w_gl(f["transform_matrix"], tf["w"], tf["h"],
                                 intrinsics=(tf["fl_x"], tf["fl_y"], tf["cx"], tf["cy"]))
        depth = layout.read_depth(smoke_slope / f["gt_depth_file_path"]).astype(np.float64)
        j, i = np.nonzero(depth < layout.NO_HIT)
        pts = cam.unproject(np.stack([i + 0.5, j + 0.5], -1), depth[j, i])
        on_bed = np.all((pts[:, :2] > surface.x0 + 0.1) & (pts[:, :2] < edge - 0.1), axis=1)
        err = np.abs(pts[on_bed, 2] - surface.height_at(pts[on_bed, :2]))
        worst, count = max(worst, err.max()), count + on_bed.sum()
    print(f"\ndry depth -> sheared bed: {count} pixels, max vertical error {worst * 1e6:.1f} um")
    assert count > 10000 and worst < 0.01


def test_the_survey_measures_the_edge_on_the_surface(smoke_slope):
    edge = layout.read_points(smoke_slope / layout.SURVEY_EDGE)
    assert 20 <= len(edge) <= 40 and (edge[:, 1] < 0).sum() == (edge[:, 1] > 0).sum()  # both banks
    height = edge[:, :2] @ SLOPE  # the true surface (level 0) under each point
    assert np.abs(edge[:, 2] - height).max() < 0.04  # 1 cm noise
    assert np.ptp(height) > 0.04  # the edge falls along the reach
    level = float((smoke_slope / layout.SURVEY_LEVEL).read_text())
    assert level == pytest.approx(height.mean(), abs=0.04)  # one level at the mean


def test_ripples_ride_on_the_sloping_mean_surface():
    from ragsplat.blender_scenes.render import _ripple
    from ragsplat.datagen.conditions import ripple_height
    from ragsplat.datagen.job import Ripples

    rng = np.random.default_rng(0)
    verts = np.column_stack([rng.uniform(-5, 5, (50, 2)), np.zeros(50)])
    geo = {"water_verts": verts, "water_weight": rng.uniform(0, 1, 50)}
    ripples = Ripples(k=rng.normal(0, 10, (4, 2)).tolist(), amplitude=[0.004, 0.002, 0.001, 0.003], level=0.2)
    phases = rng.uniform(0, 6, 4).tolist()
    got = {}
    water = SimpleNamespace(data=SimpleNamespace(
        vertices=SimpleNamespace(foreach_set=lambda key, co: got.update({key: np.reshape(co, (-1, 3))})),
        update=lambda: None))
    ripple = geo["water_weight"] * ripple_height(verts[:, :2], np.array(ripples.k),
                                                 np.array(ripples.amplitude), np.array(phases))
    _ripple(water, geo, ripples, phases)
    np.testing.assert_allclose(got["co"][:, 2], 0.2 + ripple, atol=1e-6)  # flat: as before
    _ripple(water, geo, replace(ripples, slope=(-0.01, 0.02)), phases)
    np.testing.assert_allclose(got["co"][:, 2], 0.2 + verts[:, :2] @ [-0.01, 0.02] + ripple, atol=1e-6)

"""A sloping water surface (a river falling downstream): the generator shears the whole flat scene with it,
so depths, what is wet and the waterline are the flat preset's; the flat presets' files stay as they were;
the survey's water-edge points lie on the surface along both banks. numpy only, no rendering."""

import argparse
import hashlib
import json
import math

import numpy as np
import pytest

from ragsplat.cli import generate as cli
from ragsplat.datagen import flight
from ragsplat.datagen.assets import write_bed_assets
from ragsplat.datagen.bed import make_bed, world_waterline
from ragsplat.datagen.build import null_models, render_job
from ragsplat.datagen.spec import PRESETS, SceneSpec, preset, validate, with_slope
from ragsplat.datagen.survey import EDGE_POINTS, SurveyNoise, _write_edge, edge_points
from ragsplat.dataset import layout
from ragsplat.errors import SpecError

# sha256 (16 hex) of json.dumps(preset.to_dict()) before the slope existed: spec.json is the first file of a
# dataset and the spec check of every rerun, so these presets' datasets stay byte-identical.
FLAT_SPECS = {"smoke": "5076738637e72b3d", "small": "685c689220fed1ac", "paper-reach": "7a40b8531e978198",
              "smoke-bed": "8fccd103c5e9e20c", "small-bed": "6c79400057b3bafb", "paper": "877b835a4fc0fb83",
              "small-field": "03447082bb91b749", "smoke-field": "3e0e93ccc3bbe197"}


def test_flat_presets_spec_json_is_unchanged_and_has_no_slope():
    for name, digest in FLAT_SPECS.items():
        d = preset(name).to_dict()
        assert "slope" not in d["water"], name
        assert hashlib.sha256(json.dumps(d).encode()).hexdigest()[:16] == digest, name


@pytest.mark.parametrize("name", list(PRESETS))
def test_spec_round_trips_through_json(name):
    spec = preset(name)
    assert SceneSpec.from_dict(json.loads(json.dumps(spec.to_dict()))) == spec


def test_slope_presets_are_their_flat_twins_falling_one_percent():
    for name, flat in (("small-slope", "small"), ("smoke-slope", "smoke")):
        spec = preset(name)
        assert spec.water.slope == (-0.01, 0.0) and spec.to_dict()["water"]["slope"] == (-0.01, 0.0)
        assert spec == with_slope(preset(flat), 0.01, name)
        validate(spec)


@pytest.mark.parametrize("slope", [(math.nan, 0.0), (0.0, math.inf), (-0.5, 0.0), (0.08, 0.08)])
def test_validate_refuses_a_bad_slope_in_one_line(slope):
    spec = preset("smoke-slope")
    with pytest.raises(SpecError, match="water slope") as err:
        d = spec.to_dict()
        validate(SceneSpec.from_dict({**d, "water": {**d["water"], "slope": slope}}))
    assert "\n" not in str(err.value)


def test_validate_refuses_a_surface_that_rises_towards_the_cameras():
    spec = with_slope(preset("smoke"), 0.1)  # 10 %: 0.85 m over the smoke bed's half diagonal
    validate(spec)
    low = SceneSpec.from_dict({**spec.to_dict(), "flight": {**spec.to_dict()["flight"], "altitude": 1.5}})
    with pytest.raises(SpecError, match="flight altitude"):
        validate(low)


def test_cli_water_slope_sets_the_spec(monkeypatch, tmp_path):
    seen = []

    def generate(spec, out, shard, progress):
        seen.append(spec)
        return {"damaged": [], "rendered": 0, "skipped": 0, "complete": True}

    monkeypatch.setattr("ragsplat.datagen.build.generate", generate)
    parser = argparse.ArgumentParser()
    cli.add_arguments(parser)
    for extra, slope in (([], (0.0, 0.0)), (["--water-slope", "0.005"], (-0.005, 0.0))):
        args = parser.parse_args(["--preset", "smoke", "--out", str(tmp_path / "d"), "--quiet", *extra])
        assert cli.run(args) == 0
        assert seen[-1].water.slope == slope and seen[-1].preset == "smoke"
    assert "slope" not in seen[0].to_dict()["water"]  # --water-slope left out: the flat preset as it is


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """The bed assets (geometry, ground truth) of smoke and smoke-slope, as `generate` writes them."""
    out = {}
    for name in ("smoke", "smoke-slope"):
        root = tmp_path_factory.mktemp(name)
        (root / "scene").mkdir()
        (root / "gt").mkdir()
        write_bed_assets(preset(name), root)
        out[name] = root
    return out


def test_the_scene_is_sheared_so_depths_and_wet_stay_the_flat_presets(built):
    flat, slope = built["smoke"], built["smoke-slope"]
    water = preset("smoke-slope").water
    sx, sy = water.slope
    for name in (layout.GT_GRID, layout.GT_BANKS):  # the wet grid and the banks: the same nodes
        a, b = np.load(flat / name), np.load(slope / name)
        assert a.shape == b.shape and np.array_equal(a[:, :2], b[:, :2])
        np.testing.assert_allclose(b[:, 2], a[:, 2] + sx * a[:, 0] + sy * a[:, 1], rtol=0, atol=1e-12)
        depth = water.height(b[:, :2]) - b[:, 2]
        np.testing.assert_allclose(depth, 0.0 - a[:, 2], rtol=0, atol=1e-12)  # the flat preset's, below z = 0
    wet, banks = np.load(slope / layout.GT_GRID), np.load(slope / layout.GT_BANKS)
    assert (wet[:, 2] < water.height(wet[:, :2])).all() and (banks[:, 2] >= water.height(banks[:, :2])).all()
    assert np.ptp(water.height(wet[:, :2])) > 0.04  # the surface falls 5 cm over the evaluated stretch
    # every mesh Blender renders, the water's included, falls with the surface; uv and triangles stay
    ga, gb = np.load(flat / "scene" / "geometry.npz"), np.load(slope / "scene" / "geometry.npz")
    assert set(ga.files) == set(gb.files)
    for key in ga.files:
        if key.endswith("_verts"):
            v = ga[key]
            np.testing.assert_allclose(gb[key][:, :2], v[:, :2], rtol=0, atol=0)
            sheared = v[:, 2] + sx * v[:, 0] + sy * v[:, 1]
            np.testing.assert_allclose(gb[key][:, 2], sheared, rtol=0, atol=1e-9)
        else:
            assert np.array_equal(ga[key], gb[key]), key
    # the exact bed surface: sheared at its vertices, and so between them (each triangle onto one)
    sa, sb = layout.Surface.load(flat / layout.GT_SURFACE), layout.Surface.load(slope / layout.GT_SURFACE)
    xy = np.random.default_rng(0).uniform(-5, 5, (500, 2))
    np.testing.assert_allclose(sb.height_at(xy), sa.height_at(xy) + xy @ [sx, sy], rtol=0, atol=1e-12)


def test_the_waterline_lies_on_the_sloping_surface(built):
    spec = preset("smoke-slope")
    lines = json.loads((built["smoke-slope"] / layout.GT_WATERLINE).read_text())["geometry"]["coordinates"]
    flat = json.loads((built["smoke"] / layout.GT_WATERLINE).read_text())["geometry"]["coordinates"]
    assert [np.asarray(a)[:, :2].tolist() for a in lines] == flat  # the same line, now with its heights
    surface = layout.Surface.load(built["smoke-slope"] / layout.GT_SURFACE)
    for line in map(np.asarray, lines):
        assert line.shape[1] == 3
        np.testing.assert_allclose(line[:, 2], spec.water.height(line[:, :2]), atol=1e-6)
        np.testing.assert_allclose(surface.height_at(line[:, :2]), line[:, 2], atol=1e-5)  # the bed meets it


def test_null_models_use_the_depth_below_the_surface(built):
    a = null_models(preset("smoke"), np.load(built["smoke"] / layout.GT_GRID))
    b = null_models(preset("smoke-slope"), np.load(built["smoke-slope"] / layout.GT_GRID))
    assert a["max_depth_m"] == b["max_depth_m"] and a["thresholds_m"] == b["thresholds_m"]
    for plane in ("median_plane", "mean_depth_plane"):
        assert b[plane]["z"] == pytest.approx(a[plane]["z"], abs=1e-9)  # its height at the origin
        for key, value in a[plane].items():  # the same answer, parallel to the surface: the same scores
            assert b[plane][key] == pytest.approx(value, abs=0.01), key


def test_water_edge_points_lie_on_the_surface_along_both_banks(built, tmp_path):
    spec = preset("smoke-slope")
    region = flight.eval_region(spec)
    xy = edge_points(world_waterline(spec, make_bed(spec)), region["xmin"], region["xmax"])
    assert len(xy) == 2 * EDGE_POINTS and 10 <= EDGE_POINTS <= 20
    surface = layout.Surface.load(built["smoke-slope"] / layout.GT_SURFACE)
    truth = spec.water.height(xy)
    np.testing.assert_allclose(surface.height_at(xy), truth, atol=1e-9)  # where the bed meets the water
    for bank, side in ((xy[:EDGE_POINTS], -1), (xy[EDGE_POINTS:], 1)):
        assert (np.sign(bank[:, 1]) == side).all()  # one bank each side of the channel
        assert np.ptp(bank[:, 0]) > 0.8 * (region["xmax"] - region["xmin"])  # along the whole reach
        assert (bank[:, 0] >= region["xmin"]).all() and (bank[:, 0] <= region["xmax"]).all()
    noise = SurveyNoise()
    _write_edge(tmp_path, np.column_stack([xy, truth]), spec.seed, noise)
    text = (tmp_path / layout.SURVEY_EDGE).read_bytes()
    assert text.startswith(b"x,y,z\n")
    points = layout.read_points(tmp_path / layout.SURVEY_EDGE)
    np.testing.assert_allclose(points[:, :2], xy, atol=5e-4)
    residual = points[:, 2] - truth
    assert np.abs(residual).max() < 4 * noise.level and 0.4 * noise.level < residual.std() < 2 * noise.level
    _write_edge(tmp_path, np.column_stack([xy, truth]), spec.seed, noise)
    assert (tmp_path / layout.SURVEY_EDGE).read_bytes() == text  # seeded: the same file again


def test_ripples_ride_on_the_sloping_mean_surface_and_flat_jobs_stay_as_they_were(tmp_path):
    field = preset("smoke-field")
    job = render_job(field, tmp_path, flight.plan(field)[0].camera, [])
    assert job.ripples.slope is None
    sloping = with_slope(field, 0.01)
    job = render_job(sloping, tmp_path, flight.plan(sloping)[0].camera, [])
    assert job.ripples.slope == (-0.01, 0.0) and job.ripples.level == 0.0

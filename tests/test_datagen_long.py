"""River scale (issue 49): the `long` reach flown as a survey flies it (nadir strips, obliques at stations
along the reach) and its CI twin `smoke-long`. The flight plan checked by the independent tracer of
test_datagen_flight; the older presets' spec.json stay as they were. numpy only, no rendering."""

import hashlib
import json
import math
from dataclasses import replace

import numpy as np
import pytest
from test_datagen_flight import trace_to_bed

from ragsplat.datagen import flight
from ragsplat.datagen.bed import make_bed, world_waterline
from ragsplat.datagen.spec import PRESETS, SceneSpec, SpecError, preset, validate
from ragsplat.datagen.survey import EDGE_POINTS, edge_count, edge_points, flight_lines

LONG = ("long", "smoke-long")


def obliques(spec, split):
    return [p for p in flight.plan(spec) if p.kind.startswith("oblique") and p.split == split]


def azimuth(pose) -> float:
    """The direction (deg) from where the view looks to the camera, as `flight._oblique` takes it."""
    forward = pose.camera.R[2]
    return round(math.degrees(math.atan2(-forward[1], -forward[0])) % 360, 6)


@pytest.mark.parametrize("name", LONG)
def test_strip_obliques_aim_at_the_bed_below_their_stations(name):
    spec = preset(name)
    f = spec.flight
    nadir_x = flight.nadir_positions(spec)[:, 0]
    stations = flight.stations(spec)
    np.testing.assert_allclose(stations[:, 0], np.linspace(min(nadir_x), max(nadir_x), f.stations),
                               atol=1e-12)
    assert not stations[:, 1].any()  # on the reach's axis, from the first nadir column to the last
    for split, aims in (("train", stations), ("test", (stations[1:] + stations[:-1]) / 2)):
        count = np.zeros(len(aims), int)
        for p in obliques(spec, split):
            cam = p.camera
            tilt = math.degrees(math.acos(-cam.R[2] @ [0, 0, 1]))
            assert tilt == pytest.approx(float(p.kind.removeprefix("oblique")), abs=1e-9)
            assert cam.camera_center[2] == pytest.approx(spec.level + f.altitude)  # the nadirs' altitude
            assert cam.R[1] @ [0, 0, 1] < 0  # image up leans towards world up
            axis = np.array([[cam.cx, cam.cy]])  # the principal point
            rough = trace_to_bed(cam, axis, spec.level, spec.n, spec.level - spec.bed.depth)[0]
            k = np.linalg.norm(aims - rough[:2], axis=1).argmin()
            # through the water at its height above the aim point (the surface falls along x)
            surface = spec.water.height(aims[k])
            hit = trace_to_bed(cam, axis, surface, spec.n, surface - spec.bed.depth)[0]
            np.testing.assert_allclose(hit, [*aims[k], surface - spec.bed.depth], atol=1e-9)
            count[k] += 1
        per = len(f.tilts) * (round(360 / f.azimuth_step) if split == "train" else 1)
        assert count.tolist() == [per] * len(aims), split


def test_held_out_obliques_turn_through_the_held_out_azimuths_between_training_ones():
    spec = preset("long")
    f = spec.flight
    # looking down, up and across the river at every station; the held-out views between those azimuths
    assert {azimuth(p) for p in obliques(spec, "train")} == {0.0, 90.0, 180.0, 270.0}
    test = obliques(spec, "test")
    held = [azimuth(p) for p in test[: f.stations - 1]]  # the first tilt's, station by station
    assert held == [(45.0 + 90 * k) % 360 for k in range(f.stations - 1)]
    train = np.array([p.camera.camera_center for p in flight.plan(spec) if p.split == "train"])
    for p in flight.plan(spec):
        if p.split == "test":
            assert np.linalg.norm(train - p.camera.camera_center, axis=1).min() > 0.5


def test_long_is_a_river_reach_flown_as_a_survey():
    spec = preset("long")
    validate(spec)
    poses = flight.plan(spec)
    train = [p for p in poses if p.split == "train"]
    assert len(train) >= 300 and len(poses) - len(train) >= 0.2 * len(train)
    rows, cols = spec.flight.grid
    assert sum(p.kind == "nadir" for p in train) == rows * cols and rows >= 3
    assert 12 <= spec.flight.altitude <= 20
    fx = spec.flight.width / 2 / math.tan(math.radians(spec.flight.fov_deg / 2))
    assert 0.03 <= spec.flight.altitude / fx <= flight.gsd(spec) <= 0.05  # at the water line and on the bed
    r = flight.eval_region(spec)
    assert r["xmax"] - r["xmin"] >= 100 and r["xmax"] < spec.bed.size / 2 - spec.bed.taper
    reach = spec.reach
    assert (r["xmax"] - r["xmin"]) / reach.pool_spacing >= 5  # pools and riffles along it
    assert r["ymax"] > reach.width / 2 + reach.meander + reach.bar_width  # both banks in the evaluated region
    assert 0.002 <= -spec.water.slope[0] <= 0.005 and spec.water.slope[1] == 0  # a river's fall, downstream
    assert not spec.render.lens
    lines = flight_lines(train)  # consumer GPS: a bias for each nadir strip and each oblique pass
    assert len(set(lines.tolist())) == rows + len(spec.flight.tilts)


@pytest.mark.parametrize("name", LONG)
def test_every_point_of_the_evaluated_reach_is_seen_by_nadirs(name):
    spec = preset(name)
    r = flight.eval_region(spec)
    xs = np.linspace(r["xmin"], r["xmax"], 401)
    ys = np.linspace(r["ymin"], r["ymax"], 41)
    xy = np.stack(np.meshgrid(xs, ys), -1).reshape(-1, 2)
    seen = flight.nadir_views_covering(spec, xy)
    assert seen.min() >= 1
    # away from the strips' two ends, 85 % forward overlap: six nadirs or more (at the edges, of one strip)
    inner = np.abs(xy[:, 0]) <= flight.nadir_positions(spec)[:, 0].max() - flight.footprint(spec)[0] / 2
    assert inner.mean() > 0.3 and seen[inner].min() >= 6


def test_smoke_long_spreads_its_photos_along_the_reach():
    spec = preset("smoke-long")
    validate(spec)
    train = [p for p in flight.plan(spec) if p.split == "train"]
    assert 20 <= len(train) <= 100 and spec.flight.width == 64
    r = flight.eval_region(spec)
    assert r["xmax"] - r["xmin"] >= 3 * flight.footprint(spec)[0]  # three tiles of a survey, or more
    # the photos looking at each third of the reach: a third of them or so, nadirs and obliques
    x = np.array([p.camera.camera_center[0] + (p.camera.camera_center[2] - spec.level) * -p.camera.R[2][0]
                  / -p.camera.R[2][2] for p in train])  # where each optical axis meets the water
    third = np.digitize(x, np.linspace(r["xmin"], r["xmax"], 4)[1:-1])
    counts = np.bincount(third, minlength=3)
    assert counts.min() >= 0.25 * len(train), counts
    for k in range(3):
        assert {p.kind for p, t in zip(train, third) if t == k} == {"nadir", "oblique20", "oblique40"}
    assert spec.flight.pattern == preset("long").flight.pattern and not spec.render.lens


@pytest.mark.parametrize("name", LONG)
def test_spec_round_trips_and_older_presets_spec_json_are_unchanged(name):
    spec = preset(name, seed=3)
    d = json.loads(json.dumps(spec.to_dict()))
    assert d["flight"]["pattern"] == "strips" and d["render"]["lens"] is False
    assert SceneSpec.from_dict(d) == spec
    # the presets made before: none of the new keys, spec.json byte for byte (the flat ones:
    # test_datagen_slope.FLAT_SPECS)
    for older in PRESETS:
        if preset(older).flight.pattern == "rings":
            d = preset(older).to_dict()
            assert not {"pattern", "stations", "side_overlap", "height", "camera"} & set(d["flight"]) \
                and "lens" not in d["render"], older
    digests = {"small-slope": "14c53fe6a1840d20", "smoke-slope": "9590c3fa031b2e0d"}
    for older, digest in digests.items():
        assert hashlib.sha256(json.dumps(preset(older).to_dict()).encode()).hexdigest()[:16] == digest, older


@pytest.mark.parametrize("change, message", [
    (lambda f: replace(f, stations=1), "at least 2"),
    (lambda f: replace(f, grid=(2, 1)), "at least 2"),
    (lambda f: replace(f, pattern="rings"), "strips pattern"),
    (lambda f: replace(f, pattern="zigzag"), "'rings', 'strips' or 'mapping'"),
    (lambda f: replace(f, grid=(2, 30)), "evaluated region"),
])
def test_bad_strip_plans_are_one_line_errors(change, message):
    """validate refuses a bad plan's parameters; the plan itself one whose evaluated region leaves the bed."""
    spec = replace(preset("smoke-long"), flight=change(preset("smoke-long").flight))
    with pytest.raises(SpecError, match=message) as err:
        validate(spec)
        flight.plan(spec)
    assert "\n" not in str(err.value)


def test_edge_points_along_the_whole_long_reach():
    r = flight.eval_region(preset("small"))
    assert edge_count(r["xmax"] - r["xmin"]) == EDGE_POINTS  # small's survey as it was
    r = flight.eval_region(preset("long"))
    assert edge_count(r["xmax"] - r["xmin"]) == math.ceil((r["xmax"] - r["xmin"]) / 2)  # one every 2 m
    spec = preset("smoke-long")
    r = flight.eval_region(spec)
    length = r["xmax"] - r["xmin"]
    xy = edge_points(world_waterline(spec, make_bed(spec)), r["xmin"], r["xmax"], edge_count(length))
    for bank in np.split(xy, 2):  # each bank from one end of the evaluated reach to the other
        assert np.ptp(bank[:, 0]) > 0.85 * (r["xmax"] - r["xmin"])

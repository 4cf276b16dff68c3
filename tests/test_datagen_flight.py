"""Flight plan: overlap on the bed (through the water), tilt, aim and counts, checked by an independent
tracer."""

import math
from dataclasses import replace

import numpy as np
import pytest

from ragsplat.datagen import flight
from ragsplat.datagen.spec import PRESETS, SceneSpec, SpecError, preset, validate


def trace_to_bed(cam, pixels, level, n, bed_z):
    """Independent vector-Snell tracer: pixels [N, 2] -> points [N, 3] where their rays meet z = bed_z."""
    d = np.stack([(pixels[:, 0] - cam.cx) / cam.fx, (pixels[:, 1] - cam.cy) / cam.fy,
                  np.ones(len(pixels))], -1)
    d = d @ cam.R  # camera -> world directions
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    c = cam.camera_center
    p = c + ((level - c[2]) / d[:, 2])[:, None] * d
    eta, cosi = 1.0 / n, -d[:, 2]
    k = 1.0 - eta**2 * (1.0 - cosi**2)
    t = eta * d + (eta * cosi - np.sqrt(k))[:, None] * np.array([0.0, 0.0, 1.0])
    return p + ((bed_z - p[:, 2]) / t[:, 2])[:, None] * t


@pytest.mark.parametrize("name", ["smoke", "small", "paper-reach", "small-bed", "paper", "long",
                                  "smoke-long"])
def test_nadir_overlap_on_the_bed_through_water(name):
    spec = preset(name)
    validate(spec)
    poses = [p for p in flight.plan(spec) if p.kind == "nadir" and p.split == "train"]
    cam = poses[0].camera
    w, bed_z = cam.width, spec.level - spec.bed.depth
    # Image edges along the centre row (u = 0 and u = W) and the centre column (v = 0 and v = W).
    edge = np.array([[0.0, w / 2], [w, w / 2], [w / 2, 0.0], [w / 2, w]])
    hits = trace_to_bed(cam, edge, spec.level, spec.n, bed_z)
    side_x, side_y = hits[1, 0] - hits[0, 0], hits[2, 1] - hits[3, 1]  # image up is world +y
    assert (side_x, side_y) == pytest.approx(flight.footprint(spec), rel=1e-9)
    assert side_x == pytest.approx(side_y, rel=1e-12)  # square photos
    step = flight.spacing(spec)[0]
    if spec.flight.grid[1] > 1:
        centres = np.array([p.camera.camera_center for p in poses])
        assert np.diff(np.unique(centres[:, 0].round(9))) == pytest.approx(step)
    assert 1 - step / side_x == pytest.approx(spec.flight.overlap, abs=1e-9)
    # The dry footprint is wider: ignoring refraction would overstate the overlap (by 3.7 % for long's bed
    # 1.5 m under 12 m of air, 9.5 % for small's).
    dry = trace_to_bed(cam, edge, spec.level, 1.0, bed_z)
    assert dry[1, 0] - dry[0, 0] > side_x * 1.03


@pytest.mark.parametrize("name", ["smoke", "paper-reach", "paper"])
def test_obliques_tilt_and_refracted_axis_hits_scene_centre(name):
    spec = preset(name)
    centre = np.array([0.0, 0.0, spec.level - spec.bed.depth])
    obliques = [p for p in flight.plan(spec) if p.kind.startswith("oblique")]
    assert {p.kind for p in obliques} == {f"oblique{t:g}" for t in spec.flight.tilts}
    for p in obliques:
        cam = p.camera
        tilt = math.degrees(math.acos(-cam.R[2] @ [0, 0, 1]))
        assert tilt == pytest.approx(float(p.kind.removeprefix("oblique")), abs=1e-9)
        assert cam.camera_center[2] == pytest.approx(spec.level + spec.flight.altitude)
        hit = trace_to_bed(cam, np.array([[cam.cx, cam.cy]]), spec.level, spec.n, centre[2])[0]
        np.testing.assert_allclose(hit, centre, atol=1e-9)
        # Image up leans towards world up: the top image row looks further away than the bottom row.
        assert cam.R[1] @ [0, 0, 1] < 0


def test_dry_scene_aims_straight_at_the_centre():
    spec = replace(preset("smoke-bed"), water=None)
    for p in flight.plan(spec):
        if p.kind.startswith("oblique"):
            uv, _ = p.camera.project(np.array([[0.0, 0.0, -spec.bed.depth]]))
            np.testing.assert_allclose(uv[0], [p.camera.cx, p.camera.cy], atol=1e-9)


def test_counts_and_held_out_poses_differ_from_training():
    spec = preset("paper")
    poses = flight.plan(spec)
    train = [p for p in poses if p.split == "train"]
    rows, cols = spec.flight.grid
    assert len(train) == rows * cols + len(spec.flight.tilts) * 36  # 16 + 72 = 88: "about 90"
    assert 85 <= len(train) <= 95
    test = [p for p in poses if p.split == "test"]
    assert len(test) == (rows - 1) * (cols - 1) + len(spec.flight.tilts) * 6
    assert [p.name for p in poses] == [f"{i:04d}" for i in range(len(poses))]
    train_c = np.array([p.camera.camera_center for p in train])
    for p in test:
        assert np.linalg.norm(train_c - p.camera.camera_center, axis=1).min() > 0.1
    # Test ring views sit at +5 deg from training azimuths.
    az = {round(math.degrees(math.atan2(*p.camera.camera_center[1::-1])) % 360, 6)
          for p in test if p.kind == "oblique20"}
    assert az == {5.0 + 60 * k for k in range(6)}


def test_eval_region_is_seen_by_many_nadirs():
    spec = preset("paper")
    r = flight.eval_region(spec)
    corners = np.array([[r["xmin"], r["ymin"]], [r["xmax"], r["ymax"]], [0.0, 0.0]])
    seen = flight.nadir_views_covering(spec, corners)
    assert seen[2] == 16 and seen.min() == 9  # centre: all 16 nadirs; corners: a 3 x 3 block of them
    assert r["xmax"] < spec.bed.size / 2 - spec.bed.taper


@pytest.mark.parametrize("name", ["small", "small-bed"])
def test_gsd_matches_the_traced_pixel_size(name):
    spec = preset(name)
    cam = flight.plan(spec)[len(flight.nadir_positions(spec)) // 2].camera  # the centre nadir
    c = cam.cx
    hits = trace_to_bed(cam, np.array([[c - 0.5, c], [c + 0.5, c]]), spec.level, spec.n, -spec.bed.depth)
    assert hits[1, 0] - hits[0, 0] == pytest.approx(flight.gsd(spec), rel=1e-4)


@pytest.mark.parametrize("change, message", [
    (lambda s: replace(s, flight=replace(s.flight, altitude=-1.0)), "camera under water"),
    (lambda s: replace(s, flight=replace(s.flight, overlap=0.0)), "zero overlap"),
    (lambda s: replace(s, flight=replace(s.flight, tilts=(60.0,))), "below the horizon"),
    (lambda s: replace(s, bed=replace(s.bed, depth=0.2)), "reaches the water"),
    (lambda s: replace(s, reach=preset("small").reach), "does not fit"),
    (lambda s: replace(s, reach=replace(preset("smoke").reach, bank_height=0.1)), "bar_height < bank_height"),
])
def test_bad_specs_are_one_line_errors(change, message):
    with pytest.raises(SpecError, match=message) as err:
        validate(change(preset("smoke-bed")))
    assert "\n" not in str(err.value)


def test_unknown_preset_and_spec_round_trip():
    with pytest.raises(SpecError, match="unknown preset"):
        preset("huge")
    spec = preset("small", seed=7)
    assert SceneSpec.from_dict(spec.to_dict()) == spec
    bed = preset("small-bed", seed=7)
    assert SceneSpec.from_dict(bed.to_dict()) == bed
    dry = replace(spec, water=None)
    assert SceneSpec.from_dict(dry.to_dict()) == dry


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_preset_validates_and_plans(name):
    """Each preset passes validate and its flight plan's region check (`flight.check_region`)."""
    spec = preset(name)
    validate(spec)
    assert len(flight.plan(spec)) > 0

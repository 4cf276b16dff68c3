"""The flight people fly and the lake shore it flies over: the `mapping` lawnmower (rows flown back and forth,
the image's top ahead, its width across the line, a consumer camera's field of view at fewer pixels) and the
`ShoreSpec` ground (a beach sloping into water that levels out, land rising beyond the waterline)."""

import math
from dataclasses import replace

import numpy as np
import pytest

from ragsplat.datagen import flight
from ragsplat.datagen.bed import ground_truth, make_bed, waterline
from ragsplat.datagen.spec import CAMERAS, SceneSpec, ShoreSpec, SpecError, preset, validate
from ragsplat.datagen.survey import GeoOrigin, edge_points, flight_lines, gimbal_angles
from ragsplat.dataset import exif

MAPPING = ["lake-mapping", "river-mapping", "smoke-lake-mapping", "smoke-river-mapping"]


def train_nadirs(spec):
    return [p for p in flight.plan(spec) if p.kind == "nadir" and p.split == "train"]


@pytest.mark.parametrize("name", MAPPING)
def test_mapping_flies_rows_back_and_forth_with_the_image_top_ahead(name):
    spec = preset(name)
    rows, cols = spec.flight.grid
    poses = train_nadirs(spec)
    assert len(poses) == rows * cols and all(p.kind == "nadir" for p in flight.plan(spec))  # no obliques
    centres = np.array([p.camera.camera_center for p in poses]).reshape(rows, cols, 3)
    sx, sy = flight.spacing(spec)
    for row in range(rows):
        ahead = 1.0 if row % 2 == 0 else -1.0  # the lawnmower turns at each row's end
        np.testing.assert_allclose(np.diff(centres[row, :, 0]), ahead * sx, rtol=1e-9)
        for p in poses[row * cols:(row + 1) * cols]:
            up, right = -p.camera.R[1], p.camera.R[0]  # the image's top and right in the world
            np.testing.assert_allclose(up, [ahead, 0.0, 0.0], atol=1e-12)
            np.testing.assert_allclose(np.abs(right), [0.0, 1.0, 0.0], atol=1e-12)  # the width across
    np.testing.assert_allclose(np.diff(centres[:, 0, 1]), sy, rtol=1e-9)
    assert (flight_lines(poses) == np.repeat(np.arange(rows), cols)).all()  # a flight line a row
    assert spec.flight.width > spec.flight.image_height  # a 4:3 photo, its long side across the line


@pytest.mark.parametrize("name", MAPPING)
def test_mapping_overlaps_forward_and_side_on_the_bed(name):
    """The footprint traced through the water from the image's edges: its side along the line (the image's
    height) and across it (the width) give the forward and the side overlap at the grid's spacing."""
    from test_datagen_flight import trace_to_bed

    spec = preset(name)
    cam = train_nadirs(spec)[0].camera
    w, h = cam.width, cam.height
    edge = np.array([[0.0, h / 2], [w, h / 2], [w / 2, 0.0], [w / 2, h]])
    hits = trace_to_bed(cam, edge, spec.level, spec.n, spec.level - spec.bed.depth)
    across, along = abs(hits[1, 1] - hits[0, 1]), abs(hits[2, 0] - hits[3, 0])
    assert (along, across) == pytest.approx(flight.footprint(spec), rel=1e-9)
    sx, sy = flight.spacing(spec)
    assert 1 - sx / along == pytest.approx(spec.flight.overlap, abs=1e-9)
    assert 1 - sy / across == pytest.approx(spec.flight.side_overlap, abs=1e-9)
    assert spec.flight.overlap == 0.8 and spec.flight.side_overlap == 0.7  # a planning app's defaults


def test_the_camera_is_a_phantom_3s_at_fewer_pixels():
    spec = preset("lake-mapping")
    model = CAMERAS[spec.flight.camera]
    # 2 atan(6.17 / 2 / 3.61): the FC300S's 81 degrees across its 4:3 photo
    assert model.fov_deg == pytest.approx(81.03, abs=0.01)
    cam = train_nadirs(spec)[0].camera
    assert cam.fov_x_deg == pytest.approx(model.fov_deg, abs=1e-9) and cam.width / cam.height == 4 / 3
    record = model.record(spec.flight.width)
    assert record["gsd_scale"] == pytest.approx(4000 / 1200)
    # at 40 m over the bed 1 m down: 5.8 cm a pixel, 3.3 times the real camera's 1.7 cm
    assert flight.gsd(spec) == pytest.approx(0.058, abs=0.001)
    with pytest.raises(SpecError, match="not that camera's"):
        validate(replace(spec, flight=replace(spec.flight, height=1200)))
    with pytest.raises(SpecError, match="unknown camera"):
        validate(replace(spec, flight=replace(spec.flight, camera="FC9999")))


def test_mapping_obliques_are_taken_from_the_grid_points():
    spec = preset("smoke-lake-mapping")
    spec = replace(spec, flight=replace(spec.flight, tilts=(20.0,), azimuth_step=90.0))
    validate(spec)
    grid = flight.nadir_positions(spec)
    obliques = [p for p in flight.plan(spec) if p.kind == "oblique20" and p.split == "train"]
    assert len(obliques) == 4 * len(grid)
    for p in obliques:
        c = p.camera.camera_center
        assert np.linalg.norm(grid - c[:2], axis=1).min() < 1e-9  # flat water: exactly above a grid point
        assert math.degrees(math.acos(-p.camera.R[2] @ [0, 0, 1])) == pytest.approx(20.0, abs=1e-9)
    held = [p for p in flight.plan(spec) if p.kind == "oblique20" and p.split == "test"]
    assert len(held) == len(flight.nadir_positions(spec, between=True))


def test_the_gimbal_heading_turns_with_each_flight_line():
    """DJI's GimbalYawDegree of a nadir is its image's top: east (+x) on the first line, west on the next
    (true north differs from the UTM grid's by the meridian convergence, about a degree here)."""
    spec = preset("smoke-lake-mapping")
    origin = GeoOrigin()
    crs = f"EPSG:{exif.utm_epsg(origin.lat, origin.lon)}"
    shift = np.array([*exif.to_metric(origin.lat, origin.lon, origin.height, crs)[0][:2], origin.height])
    poses = train_nadirs(spec)
    yaw, pitch, _ = gimbal_angles([p.camera for p in poses], shift, crs).T
    cols = spec.flight.grid[1]
    assert np.abs(yaw[:cols] - 90).max() < 2 and np.abs(np.abs(yaw[cols:]) - 90).max() < 2
    assert (yaw[cols:] < 0).all() and np.allclose(pitch, -90)


def test_the_shore_slopes_into_water_that_levels_out():
    spec = preset("smoke-lake-mapping")
    shore = spec.reach
    bed = make_bed(spec)
    x = bed.x0 + np.arange(bed.heights.shape[1]) * bed.texel
    # the border cross-section (no bends, no relief): the slopes at the waterline and the levels far away
    y = x  # the same texel grid along y
    profile = bed.profile - spec.level
    at = np.searchsorted(y, shore.shoreline)
    assert profile[at - 1] < 0 <= profile[at]
    step = 2 * bed.texel
    assert (profile[at - 1] - profile[at - 3]) / step == pytest.approx(shore.beach_slope, rel=0.05)
    assert (profile[at + 2] - profile[at]) / step == pytest.approx(shore.land_slope, rel=0.05)
    assert -shore.depth <= profile[0] < -0.94 * shore.depth  # the lake's floor, 16 m out
    assert 0.9 * shore.land_height < profile[-1] <= shore.land_height  # the land, 10 m in
    # one waterline across the scene, within the bends' amplitude of the shoreline
    lines = sorted(waterline(bed, spec.level), key=lambda line: -np.ptp(line[:, 0]))
    assert np.ptp(lines[0][:, 0]) > 0.9 * spec.bed.size
    inner = np.abs(lines[0][:, 0]) < spec.bed.size / 2 - spec.bed.taper
    assert np.abs(lines[0][inner, 1] - shore.shoreline).max() <= shore.wander + 0.3
    # the ground truth splits into the bed under the water and the dry beach
    wet, dry = ground_truth(spec, bed, flight.eval_region(spec), 0.1)
    assert len(wet) > len(dry) > 0 and wet[:, 2].min() > spec.level - shore.depth - 0.4
    # a lake shore's edge points: along its one bank
    r = flight.eval_region(spec)
    edge = edge_points(waterline(bed, spec.level), r["xmin"], r["xmax"], 10)
    assert edge.shape == (10, 2) and np.abs(edge[:, 1] - shore.shoreline).max() <= shore.wander + 0.3


def test_a_shore_spec_round_trips_and_bad_ones_are_one_line_errors():
    spec = preset("lake-mapping", seed=3)
    assert SceneSpec.from_dict(spec.to_dict()) == spec
    assert isinstance(SceneSpec.from_dict(spec.to_dict()).reach, ShoreSpec)
    for change, message in [({"depth": 0.0}, "must be > 0"), ({"sand_height": 2.0}, "sand_height < land"),
                            ({"shoreline": 70.0}, "does not lie in")]:
        with pytest.raises(SpecError, match=message) as err:
            validate(replace(spec, reach=replace(spec.reach, **change)))
        assert "\n" not in str(err.value)

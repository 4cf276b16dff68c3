"""A survey split into tiles (`survey.tiles`): the footprints from physics, the layout's partition of the
plane, the merge's one cell per tile and its seams, and `ragsplat survey --tile-size` end to end, in this
process and as Dask tasks on a local cluster whose worker is killed mid-task."""

import contextlib
import io
import json
import math
import re
import shutil

import numpy as np
import pytest
from conftest import kill_a_worker
from test_survey import args, finished, survey  # noqa: F401 (fixtures)

from ragsplat.camera import Camera
from ragsplat.cli.main import main
from ragsplat.survey import tiles
from ragsplat.survey.stages.training import seen_area
from ragsplat.water_surface import WaterSurface


def test_a_nadir_footprint_is_the_field_of_view_at_the_water():
    """A nadir camera h above the water sees h tan(fov / 2) either side; an oblique one's box lies ahead of
    it; on a sloping surface the height is the surface's below the camera."""
    cams = [Camera.look_at([1.0, 2.0, 5.0], [1.0, 2.0, 0.0], 200, 100, 60.0),
            Camera.look_at([0.0, 0.0, 5.0], [5.0, 0.0, 0.0], 200, 100, 60.0, up=(0.0, 0.0, 1.0))]
    R = np.stack([c.R for c in cams])
    C = np.stack([c.camera_center for c in cams])
    K = np.array([[c.fx, c.fy, c.cx, c.cy] for c in cams])
    sizes = np.array([[200, 100]] * 2, float)
    water = WaterSurface(1.0, 1.33)  # 4 m below the cameras
    box = tiles.footprints(R, C, K, sizes, water)
    half_x, half_y = 4.0 * 100 / cams[0].fx, 4.0 * 50 / cams[0].fy
    np.testing.assert_allclose(box[0], [1 - half_x, 2 - half_y, 1 + half_x, 2 + half_y], atol=1e-9)
    assert box[1][0] > 0 and box[1][2] > 4.0 and box[1][2] <= tiles.MAX_REACH * 4.0 + 1e-9
    sloping = tiles.footprints(R[:1], C[:1], K[:1], sizes[:1], WaterSurface(1.0, 1.33, (0.1, 0.0)))
    h = 5.0 - (1.0 + 0.1 * 1.0)  # the surface's height below the camera
    np.testing.assert_allclose(sloping[0, 2] - sloping[0, 0], 2 * h * 100 / cams[0].fx, atol=1e-9)


def test_the_tiles_partition_the_plane_and_hold_the_photos_that_see_them():
    rng = np.random.default_rng(0)
    centres = np.column_stack([np.linspace(0, 100, 60), rng.uniform(-5, 5, 60)])
    boxes = np.column_stack([centres - 8.0, centres + 8.0])  # 16 m footprints along a 100 m reach
    names = [f"{k:03d}.jpg" for k in range(60)]
    one = tiles.plan([0, -10], [100, 10], boxes, names, 120.0, 5.0)
    assert len(one) == 1 and one[0].photos == tuple(names) and not np.isfinite(one[0].core).any()
    plan = tiles.plan([0, -10], [100, 10], boxes, names, 40.0, 4.0)
    assert [t.grid for t in plan] == [(0, 0), (1, 0), (2, 0)]
    points = rng.uniform([-50, -50], [150, 50], (10_000, 2))
    owners = np.stack([tiles.inside(points, t.core) for t in plan])
    assert (owners.sum(0) == 1).all()  # every point of the plane in exactly one core, the far field included
    middle = plan[1]
    assert middle.core[0] == pytest.approx(100 / 3) and middle.outer[0] == pytest.approx(100 / 3 - 4)
    for t in plan:  # a photo joins when a tenth of its footprint lies in the outer box
        share = tiles._share_inside(boxes, [max(v, -1e9) if k < 2 else min(v, 1e9)
                                            for k, v in enumerate(t.outer)])
        assert set(t.photos) == {n for n, s in zip(names, share) if s >= tiles.MIN_SEEN}
    assert set().union(*(t.photos for t in plan)) == set(names)


def consumer_flight(lines=(-12.0, 12.0), photos=9):
    """A consumer drone's nadir flight as the real one that broke the ground-only plan: lines of `photos`
    photos 10.5 m apart, 40 m up, a DJI FC300S at 4000 x 2250 (3.61 mm on 6.17 mm: fx 2 340 px, a GSD of
    1.71 cm): their names, footprints (68 x 38 m) and the points' box (about 86 x 119 m)."""
    fx, height = 3.61 / 6.17 * 4000, 40.0
    centres = np.array([(x, 10.5 * k) for x in lines for k in range(photos)])
    half = height * np.array([2000, 1125]) / fx
    names = [f"DJI_{k:04d}.JPG" for k in range(len(centres))]
    return names, np.column_stack([centres - half, centres + half]), centres.min(0) - 0.9 * half, \
        centres.max(0) + 0.9 * half, height / fx


def test_tiles_are_planned_by_photos_as_well_as_ground():
    """18 photos of a consumer flight at 1.71 cm cut by ground alone (1 500 GSD) make 20 tiles of 2-10
    photos; planned by photos too, the grid is coarser until every tile holds `MIN_TILE_PHOTOS`, and still
    partitions the plane; a tile no photo sees is left out."""
    names, boxes, lo, hi, gsd = consumer_flight()
    size = 1500 * gsd
    by_ground = tiles.plan(lo, hi, boxes, names, size, 0.1 * size, min_photos=1)
    assert len(by_ground) == 20 and min(len(t.photos) for t in by_ground) == 2
    plan = tiles.plan(lo, hi, boxes, names, size, 0.1 * size)
    assert len(plan) > 1 and all(len(t.photos) >= tiles.MIN_TILE_PHOTOS for t in plan)
    assert [t.index for t in plan] == list(range(len(plan)))
    points = np.random.default_rng(0).uniform(lo - 50, hi + 50, (10_000, 2))
    assert (np.stack([tiles.inside(points, t.core) for t in plan]).sum(0) == 1).all()
    assert set().union(*(t.photos for t in plan)) == set(names)
    one_line = consumer_flight(lines=(-12.0,), photos=12)  # a line of 12: no cut leaves 12 either side
    assert len(tiles.plan(*one_line[2:4], one_line[1], one_line[0], size, 0.1 * size)) == 1
    # an L: the corner far from both legs is seen by no photo, and left out
    legs = np.array([(10.0 * k, 0.0) for k in range(10)] + [(0.0, 10.0 * k) for k in range(1, 10)])
    boxes = np.column_stack([legs - 4.0, legs + 4.0])
    plan = tiles.plan([-4, -4], [94, 94], boxes, [str(k) for k in range(19)], 50.0, 2.0, min_photos=1)
    assert [t.grid for t in plan] == [(0, 0), (1, 0), (0, 1)]


def test_a_survey_that_one_worker_trains_is_one_tile(survey, finished, monkeypatch):  # noqa: F811
    """Without --tile-size, 18 photos are one tile however small `TILE_GSD` makes a tile's ground; with it,
    the size is obeyed."""
    from dataclasses import replace

    from ragsplat.survey.stages import tiled
    from ragsplat.survey.stages.base import SurveyConfig
    from ragsplat.water_surface import WaterSurface

    out = finished[0]
    lo, hi = np.array(json.loads((out / "water.json").read_text())["extent_m"])
    cfg = SurveyConfig(images=survey / "images", out=out)
    monkeypatch.setattr(tiled, "TILE_GSD", 10)  # about 20 cm: a grid of 30 x 30 by ground
    water = WaterSurface(0.0, 1.33)
    assert len(tiled.plan_tiles(cfg, out / "model", water, lo, hi)[0]) == 1
    assert len(tiled.plan_tiles(replace(cfg, tile_size=3.0), out / "model", water, lo, hi)[0]) == 4
    monkeypatch.setattr(tiled, "ONE_TILE_PHOTOS", 17)
    assert len(tiled.plan_tiles(cfg, out / "model", water, lo, hi)[0]) > 1


def test_the_merge_takes_each_cell_from_its_core_and_measures_the_overlap():
    boxes = np.array([[0.0, 0.0, 1.0, 1.0], [1.0, 0.0, 2.0, 1.0]])  # a photo over each half
    plan = tiles.plan([0, 0], [2, 1], boxes, ["a", "b"], 1.0, 0.25, min_photos=1)  # two tiles split at x = 1
    step = 0.05
    xs = np.arange(-10, 50) * step
    left = np.array([(x, 0.5, 0.0) for x in xs if x < 1.25 + 1e-9])
    right = np.array([(x, 0.5, 0.01) for x in xs if x > 0.75 - 1e-9])  # 1 cm higher
    grid, owner, report = tiles.merge([left, right], plan, step)
    assert len(grid) == len(xs) and len(np.unique(np.round(grid[:, 0] / step))) == len(xs)
    np.testing.assert_array_equal(owner, (grid[:, 0] >= 1.0).astype(int))
    assert grid[owner == 1, 2].min() == 0.01 and grid[owner == 0, 2].max() == 0.0 and report["filled"] == 0
    (pair,) = report["overlap"]
    assert pair["tiles"] == [0, 1] and pair["cells"] == 11
    assert pair["median_m"] == pytest.approx(-0.01) and pair["rms_m"] == pytest.approx(0.01)
    holed = left[np.abs(left[:, 0] - 0.5) > 1e-9]  # the left tile left x = 0.5 empty: nobody made it
    # the right tile left x = 1.1: the left one's is used
    right_hole = right[np.abs(right[:, 0] - 1.1) > 1e-9]
    grid, owner, report = tiles.merge([holed, right_hole], plan, step)
    assert len(grid) == len(xs) - 1 and report["filled"] == 1
    assert owner[np.isclose(grid[:, 0], 1.1)].tolist() == [0]


@pytest.fixture(scope="module")
def tiled(survey, finished, tmp_path_factory):  # noqa: F811
    """The synthetic survey again from the finished run's poses, in tiles of 3 m (2 x 2 over its 5.8 m)
    trained here one after another, and what it printed."""
    out = tmp_path_factory.mktemp("tiled") / "run"
    _reuse_poses(finished[0], out)
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        assert main(args(survey, out, "--tile-size", "3", "--jobs", "1")) == 0, err.getvalue()
    return out, err.getvalue()


def _reuse_poses(run, out):
    """A run folder with `run`'s stages up to the water (its poses), so that only the training is new."""
    out.mkdir(parents=True)
    for name in ("sfm", "model"):
        shutil.copytree(run / name, out / name)
    for name in (".ragsplat", "stages.json", "georef.json", "water.json"):
        shutil.copy(run / name, out / name)


def test_a_tiled_survey_gives_one_cell_per_tile_and_seams_that_agree(survey, finished, tiled):  # noqa: F811
    out, err = tiled
    report = json.loads((out / "tiles.json").read_text())
    assert len(report["tiles"]) == 4 and "4 tiles of at most 3.0 m" in err
    assert all(t["photos"] >= 3 and t["run"]["worker_peak_gib"] > 0 for t in report["tiles"])
    import laspy

    las = laspy.read(out / "bed.laz")
    xy = np.column_stack([las.x, las.y])
    assert len(np.unique(np.round(xy / 0.05), axis=0)) == len(xy)  # no cell twice
    assert len(xy) == sum(report["cells"].values())
    single = laspy.read(finished[0] / "bed.laz")
    ours = {tuple(k): z for k, z in zip(np.round(xy / 0.05).astype(int), las.z)}
    theirs = {tuple(k): z for k, z in zip(np.round(np.column_stack([single.x, single.y]) / 0.05).astype(int),
                                          single.z)}
    # the tiles cover what one training covers, every tile its share; the smoke trainings' cover is blobs
    # whose count differs between machines and thread counts (docs/lab/history.md, the tiled survey's cover)
    assert len(ours) > 0.7 * len(theirs)
    assert min(report["cells"].values()) > 0.5 * len(ours) / len(report["cells"])
    # each seam's overlap agrees as well as two trainings of the whole survey (tiled and not) agree
    common = ours.keys() & theirs.keys()
    dz = np.array([ours[k] - theirs[k] for k in common])
    spread = math.sqrt(np.mean(dz**2))
    assert report["overlap"] and all(p["rms_m"] < 2 * spread + 0.01 for p in report["overlap"])
    # the tiles' orthophotos merged on the merged DEM's lattice, drawn over its cells
    import rasterio

    from ragsplat.dataset.layout import NODATA

    with rasterio.open(out / "dem.tif") as dem, rasterio.open(out / "ortho_bed.tif") as ortho:
        assert ortho.crs == dem.crs and ortho.res == dem.res
        cols, rows = ~ortho.transform * (dem.transform.c, dem.transform.f)
        assert abs(cols - round(cols)) < 1e-6 and abs(rows - round(rows)) < 1e-6  # one lattice
        covered = dem.read(1) != NODATA
        r0, c0 = round(rows), round(cols)
        alpha = ortho.read(4)[r0:r0 + dem.height, c0:c0 + dem.width]
        assert alpha.shape == covered.shape and (alpha[covered] > 0).mean() > 0.9


def test_a_tile_s_gaussian_budget_is_for_the_ground_its_photos_see(tiled):
    # a tile's photos see past its core on every side: its budget is for the box of its own points (the same
    # density as a survey of one tile), which together cover more than the survey's box
    out, _ = tiled
    folders = sorted((out / "tiles").iterdir())
    seen = [seen_area(folder / "data") for folder in folders]
    for folder, area in zip(folders, seen, strict=True):
        logged = re.search(r"Gaussians for (\d+) m\^2", (folder / "log.txt").read_text()).group(1)
        assert logged == f"{area:.0f}"
    lo, hi = np.array(json.loads((out / "water.json").read_text())["extent_m"])
    assert len(seen) == 4 and sum(seen) > 1.2 * np.prod(hi - lo)


def test_tiles_on_dask_workers_one_killed_give_the_same_products(survey, tiled, tmp_path):  # noqa: F811
    """`--jobs 2` for real (a local cluster of two worker processes): a SIGKILL of a worker training a tile
    does not end the command: Dask runs the tile again on a worker, which resumes from its checkpoint; the
    merged products are those of the tiles trained one after another in one process (to round-off: one
    thread per worker there, two here)."""
    import sys

    import laspy

    out = tmp_path / "run"
    _reuse_poses(tiled[0], out)
    argv = [sys.executable, "-m", "ragsplat.cli.main",
            *args(survey, out, "--tile-size", "3", "--jobs", "2")]

    def victim():  # a tile a worker is training: its pid in the log's first line
        for log in out.glob("tiles/*/log.txt"):
            lines = log.read_text().splitlines()
            if len(lines) > 2 and "step" in lines[-1]:
                return int(lines[0].rsplit(" ", 1)[1]), log

    log, err, status = kill_a_worker(argv, victim)
    assert status == 0, err
    workers = {line for line in log.read_text().splitlines() if "worker process" in line}
    assert len(workers) == 2, log.read_text()  # the tile began again on another worker
    ours, theirs = laspy.read(out / "bed.laz"), laspy.read(tiled[0] / "bed.laz")
    assert len(ours.x) == len(theirs.x)
    np.testing.assert_allclose(np.column_stack([ours.x, ours.y]), np.column_stack([theirs.x, theirs.y]))
    np.testing.assert_allclose(ours.z, theirs.z, atol=0.002)


def test_a_rerun_with_other_culls_extracts_again_without_training_again(survey, tiled, tmp_path):  # noqa: F811
    """The culls (`--max-scale-gsd`, ...) reach every tile's extraction and are recorded: a rerun of a
    finished tiled survey, copied to another folder, with a tighter cull trains nothing again, and its DEM
    keeps fewer cells."""
    import laspy

    out = tmp_path / "run"
    shutil.copytree(tiled[0], out)
    before = {p: p.stat().st_mtime_ns for p in out.glob("tiles/*/train/point_cloud.ply")}
    assert len(before) == 4
    assert main(args(survey, out, "--tile-size", "3", "--jobs", "1", "--max-scale-gsd", "3")) == 0
    assert {p: p.stat().st_mtime_ns for p in before} == before  # no tile trained again
    assert all(log.read_text().count("iterations from the") == 1 for log in out.glob("tiles/*/log.txt"))
    assert json.loads((out / "survey.json").read_text())["culls"] == {"max_scale_gsd": 3.0}
    report = json.loads((out / "tiles.json").read_text())
    assert 0 < sum(report["cells"].values()) < 0.9 * len(laspy.read(tiled[0] / "bed.laz").x)


def test_a_survey_s_tiles_get_a_worker_each_until_they_fill_two_rounds():
    """Without --jobs: fewer tiles than two per `JOBS` worker each get a worker (3 tiles on 2 cores share
    them instead of leaving one idle in a second round); more go to `JOBS` workers; --jobs is obeyed."""
    from ragsplat.cli.main import command
    from ragsplat.train.defaults import JOBS, tile_workers

    assert [tile_workers(k) for k in range(1, 2 * JOBS)] == list(range(1, 2 * JOBS))
    assert all(tile_workers(k) == JOBS for k in range(2 * JOBS, 6 * JOBS))
    given = ["photos", "--positions", "p.csv", "--water-level", "0", "--out", "run"]
    assert command("survey", given)[1].jobs is None
    assert command("survey", [*given, "--jobs", "3"])[1].jobs == 3


def test_seam_distance_counts_only_edges_between_tiles():
    """tools.seams: a point's distance is to its own core's finite edges; the survey's open outside is no
    seam."""
    from tools.seams import border_distance

    cores = [[None, None, 10.0, None], [10.0, None, None, None]]  # two tiles split at x = 10
    xy = np.array([[9.0, -50.0], [10.5, 3.0], [-100.0, 0.0], [40.0, 1e6]])
    np.testing.assert_allclose(border_distance(xy, cores), [1.0, 0.5, 110.0, 30.0])


def test_a_survey_trains_at_most_at_its_scene_scale(survey, finished, tmp_path, monkeypatch):  # noqa: F811
    """3DGS's scene scale (the cameras' extent) grows with a tile's length; a survey caps it at
    `SCENE_SCALE_GSD` ground sample distances, and `tools.retrain` trains as the survey does. Here the cap is
    lowered below the synthetic survey's extent so that it applies; a smaller survey keeps its extent."""
    from ragsplat.dataset.load import load_dataset
    from ragsplat.survey.stages import training
    from ragsplat.train.config import TrainConfig
    from tools import retrain

    ds = load_dataset(finished[0] / "data", splits=("train",), load_dry=False)
    extent, gsd = ds.camera_extent(), ds.gsd
    assert json.loads((finished[0] / "train" / "config.json").read_text())["config"]["scene_scale"] is None
    below = TrainConfig(scene_scale=None)
    monkeypatch.setattr(training, "SCENE_SCALE_GSD", 1.01 * extent / gsd)
    assert training.at_survey_scale(below, extent, gsd) is below
    monkeypatch.setattr(training, "SCENE_SCALE_GSD", 0.5 * extent / gsd)
    assert training.at_survey_scale(below, extent, gsd).scene_scale == pytest.approx(0.5 * extent)
    given = TrainConfig(scene_scale=7.0)
    assert training.at_survey_scale(given, extent, gsd) is given

    out = tmp_path / "run"
    _reuse_poses(finished[0], out)
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        assert main(args(survey, out)) == 0, err.getvalue()
    cfg = json.loads((out / "train" / "config.json").read_text())
    assert cfg["config"]["scene_scale"] == cfg["scene_scale"] == pytest.approx(0.5 * extent, rel=1e-6)
    assert f"scene scale {0.5 * extent:.1f} m" in err.getvalue()
    budget = re.search(r"at most (\d+) Gaussians for", err.getvalue()).group(1)
    again = tmp_path / "again"
    assert retrain.main([str(out / "data"), str(again), "--budget", budget, "--preset", "smoke"]) == 0
    assert json.loads((again / "config.json").read_text())["scene_scale"] == cfg["scene_scale"]


def test_a_tile_that_cannot_train_is_left_out_with_a_line(survey, tiled, tmp_path, monkeypatch,  # noqa: F811
                                                          capsys):
    """A tile whose training raises (a tile of one photo: pycolmap's "Need at least two images") is left out
    with one line naming it and its log; the other tiles' products are made, tiles.json records the failure,
    and a rerun tries that tile again. Every tile failing is one error."""
    from ragsplat.survey.stages import tiled as stage

    out = tmp_path / "run"
    shutil.copytree(tiled[0], out)
    (out / "dem.tif").unlink()
    trained = stage.train_tile

    def one_fails(job):
        if job.folder.endswith("/1"):
            raise ValueError("Need at least two images for triangulation")
        return trained(job)

    monkeypatch.setattr(stage, "train_tile", one_fails)
    assert main(args(survey, out, "--tile-size", "3", "--jobs", "1")) == 0
    err = capsys.readouterr().err
    assert "tile 1 (17 photos) left out: ValueError: Need at least two images" in err
    assert "from 3 tiles" in err and (out / "dem.tif").stat().st_size > 0
    report = json.loads((out / "tiles.json").read_text())
    assert "Need at least two" in report["tiles"][1]["run"]["failed"] and "1" not in report["cells"]
    monkeypatch.setattr(stage, "train_tile", trained)
    assert main(args(survey, out, "--tile-size", "3", "--jobs", "1")) == 0  # tried again: all four
    assert "from 4 tiles" in capsys.readouterr().err
    monkeypatch.setattr(stage, "train_tile", lambda job: one_fails(replace_folder(job)))
    (out / "dem.tif").unlink()
    assert main(args(survey, out, "--tile-size", "3", "--jobs", "1")) == 2
    assert "every tile failed" in capsys.readouterr().err


def replace_folder(job):  # the job as tile 1's: its training fails
    from dataclasses import replace

    return replace(job, folder=job.folder.rsplit("/", 1)[0] + "/1")

"""A river's sloping water surface in the evaluation (issue 47), from physics: depths are below the surface's
height above each point, for the scoring (the depth bands, the banks, the scale-free thresholds), for the
references (depth x n; Dietrich with pyBathySfM's per-point water surface elevation, exact to round-off on
the true point where the rule's assumption holds, 13-27 cm off with one level) and for a depth file read as a
bed; and `ragsplat ablation --one-level`, which gives the method and every reference one flat level at the
mean of the surveyed edge points while the scoring keeps the true surface."""

import argparse
import json
import shutil
from dataclasses import replace

import numpy as np
import pytest
import torch
from test_eval_ablation import FakeRunner

from ragsplat.cli import ablation as cli
from ragsplat.cli.main import main
from ragsplat.dataset import layout
from ragsplat.dataset.load import GroundTruth, load_dataset
from ragsplat.errors import ConfigError, DatasetError
from ragsplat.eval.ablation import EDGE_POINTS, TrainEval, one_level_water, run_ablation
from ragsplat.eval.evaluate import score_grid
from ragsplat.eval.references import depth_times_n, dietrich, dietrich_grid
from ragsplat.eval.score_file import read_bed
from ragsplat.export import Bed, Georef, write_dem
from ragsplat.refraction import apparent_points
from ragsplat.water_surface import WaterSurface

N = 1.33
SLOPE = (-0.05, 0.02)  # steeper than a river's 0.1-1 %, so that a wrong level shows at a few metres


def nadir_view(X: np.ndarray, water: WaterSurface, height: float = 20.0) -> tuple[np.ndarray, np.ndarray]:
    """(the apparent point of X [3] seen by a camera `height` m above it through `water`, the camera
    centre)."""
    centre = np.array([X[0], X[1], float(water.height(X[:2])) + height])
    return apparent_points(torch.tensor(X[None]), torch.tensor(centre), water)[0].numpy(), centre


@pytest.mark.parametrize("slope", [(-0.01, 0.005), SLOPE])
def test_depth_x_n_and_dietrich_at_nadir_recover_the_depth_below_the_surface_above_the_point(slope):
    # 1.5 m below a tilted surface, 30 m from where its height is `level`: the nadir view's apparent depth is
    # the depth / n below the surface there (to the tilt's second order), not below the level
    water = WaterSurface(0.2, N, slope)
    x, y = 30.0, -10.0
    X = np.array([x, y, float(water.height(np.array([x, y]))) - 1.5])
    app, centre = nadir_view(X, water)
    assert water.depth(app) == pytest.approx(1.5 / N, rel=2 * np.hypot(*slope) ** 2)
    one = (np.array([0]), np.array([0]))
    for got in (depth_times_n(app[None], water)[0], dietrich(app[None], centre[None], *one, water)[0]):
        assert got[2] == pytest.approx(X[2], abs=0.5 * 1.5 * np.hypot(*slope) ** 2)  # 0.08 mm at 1 %
    level = WaterSurface(0.2, N)  # one level: every depth off by (n - 1) x the surface's rise over the level
    wrong = (N - 1) * (float(water.height(X[:2])) - 0.2)
    assert abs(wrong) > 0.1
    for got in (depth_times_n(app[None], level)[0], dietrich(app[None], centre[None], *one, level)[0]):
        assert got[2] - X[2] == pytest.approx(wrong, rel=0.01)


@pytest.mark.parametrize("offset", [3.0, 12.0, 25.0])
def test_dietrich_recovers_a_point_seen_by_two_cameras_across_a_sloping_river(offset):
    # the surface falls along x; cameras mirrored across y = 0 see X on y = 0, where their air rays meet (the
    # mirror symmetry holds under the tilt): there each camera's rule, with the surface's height above that
    # point, gives X's height; one level at the origin's height gives it 13-27 cm too deep
    water, x0 = WaterSurface(0.3, N, (-0.02, 0.0)), 20.0
    h = float(water.height(np.array([x0, 0.0])))
    X = np.array([x0, 0.0, h - 2.0])
    centres = np.array([[x0, -offset, h + 20.0], [x0, offset, h + 20.0]])
    crossing = []
    for c in centres:
        d = apparent_points(torch.tensor(X[None]), torch.tensor(c), water)[0].numpy() - c
        crossing.append(c + d * (-c[1] / d[1]))  # the air ray at y = 0
    np.testing.assert_allclose(crossing[0], crossing[1], atol=1e-9)
    obs = (np.array([0, 0]), np.array([0, 1]))
    got = dietrich(np.array([crossing[0]]), centres, *obs, water)[0]
    assert got[2] == pytest.approx(X[2], abs=1e-4)
    flat = dietrich(np.array([crossing[0]]), centres, *obs, WaterSurface(0.3, N))[0]
    assert flat[2] - X[2] < -0.13


def test_depth_x_n_leaves_ground_above_the_sloping_surface_as_it_is():
    water = WaterSurface(0.0, N, (-0.1, 0.0))  # 1 m lower at x = 10
    pts = np.array([[10.0, 0.0, -0.5],  # above the surface there (-1 m), below the level at the origin: dry
                    [10.0, 0.0, -1.5],  # 0.5 m under the surface there
                    [0.0, 0.0, 0.2]])  # a bank at the origin
    np.testing.assert_allclose(depth_times_n(pts, water), [[10.0, 0.0, -0.5], [10.0, 0.0, -1.0 - 0.5 * N],
                                                           [0.0, 0.0, 0.2]], atol=1e-12)


def sloping_truth(water: WaterSurface, depth: float = 1.0, max_depth: float = 1.2):
    """A bed `depth` below `water` everywhere on 40 x 10 nodes 5 cm apart (2 m along x), and one bank node on
    the next row above the surface there but below the level at the origin."""
    x, y = np.meshgrid(np.arange(40) * 0.05, np.arange(10) * 0.05, indexing="ij")
    xy = np.column_stack([x.ravel(), y.ravel()])
    bed = np.column_stack([xy, water.height(xy) - depth])
    bank = np.array([[1.95, 0.5, float(water.height(np.array([1.95, 0.5]))) + 0.05]])
    assert bank[0, 2] < water.level  # dry only below the sloping surface
    region = {"xmin": 0.0, "xmax": 1.95, "ymin": 0.0, "ymax": 0.5}
    return GroundTruth(bed, region, max_depth, water, banks=bank)


def test_survey_figures_take_depths_below_the_sloping_surface():
    # every wet cell 0.98 m below the surface: all in the middle third of 1.5 m (0.5-1.0 m), which one level
    # would spread over two bands; the bank node above the surface stays a bank
    water = WaterSurface(0.0, N, SLOPE)
    truth = sloping_truth(water, depth=0.98, max_depth=1.5)
    s = score_grid(truth.nodes + [0, 0, 0.02], truth)["survey"]
    assert (s["shallow"]["n"], s["middle"]["n"], s["deep"]["n"]) == (0, 400, 0) and s["wet"]["n"] == 400
    assert s["banks"]["n"] == 1 and s["banks"]["bias"] == pytest.approx(0.02) and s["coverage"] == 1.0
    assert s["wet"]["bias"] == pytest.approx(0.02)
    flat = score_grid(truth.nodes + [0, 0, 0.02], replace(truth, water=WaterSurface(0.0, N)))["survey"]
    assert flat["deep"]["n"] > 0 and flat["banks"]["n"] == 0  # what a level would have measured


@pytest.fixture(scope="module")
def sloping_dataset(evaluable_dataset, tmp_path_factory):
    """The evaluable dataset under a surface sloping `SLOPE` (its level 0 at the origin: +-3 cm over the
    region), as transforms.json records it."""
    root = tmp_path_factory.mktemp("slope") / "data"
    shutil.copytree(evaluable_dataset, root)
    meta = json.loads((root / layout.TRANSFORMS).read_text())
    meta["water"] = layout.water_json(WaterSurface(0.0, N, SLOPE))
    (root / layout.TRANSFORMS).write_text(json.dumps(meta))
    return root


def test_the_thresholds_of_a_sloping_dataset_are_percent_of_its_depth_below_the_surface(sloping_dataset):
    truth = load_dataset(sloping_dataset, splits=(), ground_truth=True).ground_truth
    below = float(truth.water.depth(truth.grid).max())
    assert truth.water.slope == SLOPE and truth.max_depth == pytest.approx(below)
    assert abs(below - float((0.0 - truth.grid[:, 2]).max())) > 0.01  # below the level alone: cm off
    named = score_grid(truth.grid, truth)["thresholds_m"]
    assert named["1%"] == pytest.approx(0.01 * below) and named["3%"] == pytest.approx(0.03 * below)


def test_a_depth_band_under_a_sloping_surface_is_a_bed_below_it(sloping_dataset, tmp_path):
    # `ragsplat export --dem` writes band 2 as the depth below the sloping surface; read back as depths, the
    # bed heights are the surface's height at each node - depth: the elevation band's scores exactly
    truth = load_dataset(sloping_dataset, splits=(), ground_truth=True).ground_truth
    UP = 0.02
    write_dem(tmp_path / "bed.tif", Bed(truth.grid + [0, 0, UP], 0.05, truth.water, Georef()))
    grid, record = read_bed(tmp_path / "bed.tif", truth, Georef(), band=2, depth=True)
    assert record["values"] == "depth" and len(grid) == len(truth.grid)
    order = np.lexsort(grid[:, :2].T), np.lexsort(truth.grid[:, :2].T)
    np.testing.assert_allclose(grid[order[0]], truth.grid[order[1]] + [0, 0, UP], atol=1e-5)  # float32 band
    out = tmp_path / "depth.json"
    assert main(["score", str(tmp_path / "bed.tif"), "--truth", str(sloping_dataset), "--out", str(out),
                 "--band", "2", "--kind", "depth"]) == 0
    result = json.loads(out.read_text())
    assert result["water"] == {"level": 0.0, "n": N, "slope": list(SLOPE)}
    assert result["geometry"]["survey"]["wet"]["bias"] == pytest.approx(UP, abs=1e-5)
    assert result["geometry"]["f1"]["1%"] == 0.0 and result["geometry"]["f1"]["3%"] == 1.0


def write_edge(root, z) -> np.ndarray:
    """survey/water_edge.csv of `root`: points along both banks at heights `z` [K]."""
    x = np.linspace(-0.5, 0.5, len(z))
    pts = np.column_stack([np.r_[x[::2], x[1::2]],
                           np.r_[np.full(len(x[::2]), -0.6), np.full(len(x[1::2]), 0.6)], z])
    (root / "survey").mkdir(exist_ok=True)
    (root / EDGE_POINTS).write_text("x,y,z\n" + "".join(f"{a!r},{b!r},{c!r}\n" for a, b, c in pts))
    return pts


def test_one_level_is_the_mean_of_the_surveyed_edge_points(tmp_path):
    water = WaterSurface(0.3, 1.34, (-0.01, 0.0))
    with pytest.raises(DatasetError, match=r"water_edge\.csv: no such file; one level \(--one-level\)"):
        one_level_water(tmp_path, water)
    z = np.array([0.31, 0.29, 0.305, 0.28, 0.315])
    write_edge(tmp_path, z)
    flat, record = one_level_water(tmp_path, water)
    assert flat == WaterSurface(float(z.mean()), 1.34) and not flat.tilted
    assert record == {"level": pytest.approx(z.mean()), "n": 1.34, "edge_points": 5,
                      "edge_file": "survey/water_edge.csv"}
    with pytest.raises(ConfigError, match="no water"):
        one_level_water(tmp_path, None)
    (tmp_path / EDGE_POINTS).write_text("x,y,z\n1,2,oops\n")
    with pytest.raises(DatasetError, match="must be three numbers"):
        one_level_water(tmp_path, water)
    (tmp_path / EDGE_POINTS).write_text("x,y,z\n")
    with pytest.raises(DatasetError, match="no points"):
        one_level_water(tmp_path, water)


class SlopeRunner(FakeRunner):
    """`FakeRunner` on a river: the bed 1 m below a surface sloping `SLOPE`, the 3dgs bed its nadir apparent
    bed (depth / n below the surface), and, with `one_level`, one level at the mean surface height given."""

    def __init__(self, one_level: bool):
        super().__init__()
        self.truth = sloping_truth(WaterSurface(0.0, N, SLOPE), max_depth=1.0)
        level = float(self.truth.water.height(self.truth.grid[:, :2]).mean())
        self.water = WaterSurface(level, N) if one_level else self.truth.water
        self.one_level = {"level": level, "n": N, "edge_points": 30, "edge_file": EDGE_POINTS} \
            if one_level else None

    def train(self, cfg, out, ecfg, fcfg, checkpoints, lpips_metric=None):
        row, _, fused = super().train(cfg, out, ecfg, fcfg, checkpoints, lpips_metric)
        return row, self.truth.grid + [0, 0, 1.0 - 1.0 / N], fused


def test_one_level_rows_give_the_references_the_level_and_are_scored_against_the_surface(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    quiet = {"log": lambda s: None, "download": False}
    surface = run_ablation(data, tmp_path / "surface", "smoke", ["3dgs"], [0], SlopeRunner(False), **quiet)
    # the classical correction of the nadir apparent bed below the true surface is exact ...
    assert surface["3dgs x n"][0]["geometry"]["f1"]["1%"] == 1.0
    assert "one_level" not in surface["3dgs x n"][0]["key"]
    res = json.loads((tmp_path / "surface" / "results.json").read_text())
    assert res["water"] == {"level": 0.0, "n": N, "slope": list(SLOPE)} and res["one_level"] is None
    assert "Water: a sloping surface, z = 0 - 0.05 x + 0.02 y (a fall of 5.4 %)" in \
        (tmp_path / "surface" / "table2.md").read_text()
    assert "ONE LEVEL" not in (tmp_path / "surface" / "table2.md").read_text()
    # ... and below one level at the mean height it is off by (n - 1) x the surface's rise over the level:
    # +-1.6 cm at the ends of 2 m falling 10 cm, more than 1 % of the 1 m depth
    out, runner = tmp_path / "level", SlopeRunner(True)
    rows = run_ablation(data, out, "smoke", ["3dgs"], [0], runner, **quiet)
    grid = np.load(out / "3dgs-x-n" / "seed0" / "bed.npy")
    np.testing.assert_allclose(grid, depth_times_n(runner.truth.grid + [0, 0, 1.0 - 1.0 / N], runner.water))
    dz = score_grid(grid, runner.truth)["survey"]["wet"]
    assert (0.012 < np.abs(grid[:, 2] - runner.truth.grid[:, 2]).max() < 0.02
            and dz["bias"] == pytest.approx(0, abs=1e-3))
    assert rows["3dgs x n"][0]["geometry"]["f1"]["1%"] < 0.9
    assert rows["oracle plane"][0]["geometry"]["f1"]["1%"] == 1.0  # scored against the true bed as always
    for name in ("3dgs", "3dgs x n", "init", "oracle plane"):  # every row keyed with it
        assert rows[name][0]["key"]["one_level"] == runner.one_level
    res = json.loads((out / "results.json").read_text())
    assert res["one_level"] == runner.one_level and res["water"]["slope"] == list(SLOPE)
    for table in ("table1.md", "table2.md", "table3.md"):
        assert "ONE LEVEL (--one-level)" in (out / table).read_text()
    # the same folder without it: nothing reused, every row made again under its own key
    logged = []
    run_ablation(data, out, "smoke", ["3dgs"], [0], SlopeRunner(False), log=logged.append, download=False)
    assert sum("made with another" in line and "one_level" in line for line in logged) >= 4
    assert json.loads((out / "results.json").read_text())["one_level"] is None


def test_train_eval_gives_every_row_and_reference_the_one_level(evaluable_dataset, tmp_path):
    data = tmp_path / "data"
    shutil.copytree(evaluable_dataset, data)
    z = np.array([0.01, -0.02, 0.015, 0.005])
    write_edge(data, z)
    runner = TrainEval(data, one_level=True)
    assert runner.water == WaterSurface(float(z.mean()), N) and runner.one_level["edge_points"] == 4
    for variant in ("3dgs", "2dgs+full"):
        cfg = runner.config(variant, "smoke", 0)
        assert cfg.water_level == pytest.approx(z.mean()) and tuple(cfg.water_slope) == (0.0, 0.0)
    bed = runner.truth.grid + [0, 0, 0.25]
    cams = [v.camera for v in runner.ds.train]
    np.testing.assert_array_equal(runner.dietrich_grid(bed), dietrich_grid(bed, cams, runner.water))
    plain = TrainEval(data)
    assert plain.water == plain.ds.water and plain.one_level is None
    assert plain.config("full", "smoke", 0) == replace(runner.config("full", "smoke", 0), water_level=None,
                                                       water_slope=None)


def test_the_command_refuses_one_level_without_edge_points_and_passes_it_to_its_processes(
        evaluable_dataset, tmp_path, monkeypatch, capsys):
    out = tmp_path / "runs"
    argv = ["ablation", "--data", str(evaluable_dataset), "--out", str(out), "--preset", "smoke", "--jobs",
            "1", "--no-download", "--one-level"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "water_edge.csv: no such file" in err[0] and not out.exists()
    from dask.distributed import LocalCluster

    from ragsplat.eval import ablation

    parser = argparse.ArgumentParser()
    cli.add_arguments(parser)
    args = parser.parse_args(argv[1:-4] + ["--variants", "3dgs", "full", "--seeds", "0", "--one-level"])
    args.no_download = True
    monkeypatch.setattr(cli, "prepare", lambda args, fingerprint: None)
    given = tmp_path / "given.txt"  # what each task is given (the task runs on a copy of the function)

    def task(job, variant, seed):
        with open(given, "a") as f:
            f.write(f"{job.one_level}\n")

    monkeypatch.setattr(ablation, "train_row", task)
    with LocalCluster(n_workers=1, processes=False, dashboard_address=None) as cluster:
        args.scheduler = cluster.scheduler_address
        cli.run_rows(args, "aaaa", "0123", lambda: None)
    assert capsys.readouterr().out.count("training 2 rows on the Dask cluster") == 1
    assert given.read_text() == "True\nTrue\n"

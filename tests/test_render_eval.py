"""`ragsplat render` and `ragsplat score RUN` on a finished run, without retraining: renders equal to the
trainer's, files and sizes, z-depth as EXR; the scores equal to the ablation's row of the same run and to the
library functions called directly; one-line errors."""

import json
import math
import shutil
from dataclasses import replace

import numpy as np
import pytest
import torch
from conftest import WATER, render_dataset, tiny_smoke

from ragsplat import train
from ragsplat.bench.synthetic import bed_scene, ring_cameras
from ragsplat.cli.main import main
from ragsplat.dataset import layout, rasters
from ragsplat.dataset.load import load_dataset
from ragsplat.eval import ablation, metrics
from ragsplat.eval.evaluate import evaluate_geometry, score_grid
from ragsplat.eval.references import oracle_grids
from ragsplat.outputs import jsonable
from ragsplat.runs import load_model, load_run, write_render

KEYS = {"run", "data", "dataset_fingerprint", "dataset_seed", "variant", "preset", "seed", "harness_preset",
        "water",
        "max_depth_m", "truth_water", "lpips", "lpips_network", "versions", "code_digest", "num_gaussians",
        "appearance", "geometry", "geometry_fused", "references", "uses_ground_truth"}


@pytest.fixture(scope="module")
def ablated(evaluable_dataset, tmp_path_factory):
    """`ragsplat ablation` of the full variant, seed 0, with a 6-iteration smoke preset: its row folder is a
    finished run, and its row.json holds the scores `ragsplat score` must reproduce."""
    out = tmp_path_factory.mktemp("ablation")
    with pytest.MonkeyPatch.context() as mp:
        tiny_smoke(mp, out)
        assert main(["ablation", "--data", str(evaluable_dataset), "--out", str(out), "--preset", "smoke",
                     "--variants", "full", "--seeds", "0", "--init", "grid", "--jobs", "1",
                     "--no-download"]) == 0
    return out


@pytest.fixture()
def run(ablated):
    return ablated / "full" / "seed0"


def one_line_error(capsys, command: str, phrase: str) -> None:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"ragsplat {command}: error: ") and phrase in err[0], err


def test_renders_are_the_trainers(run, evaluable_dataset):
    model, ds = load_model(run, splits=("train", "test"))
    cfg = train.TrainConfig.from_dict(json.loads((run / "config.json").read_text())["config"])
    trainer = train.Trainer(cfg, load_dataset(evaluable_dataset), run)  # resumes the finished checkpoint
    assert trainer.step == cfg.iterations and model.flags == trainer.flags and model.water == trainer.water
    for view in ds.views[::3]:
        for interface in (True, False):
            for ours, theirs in zip(model.render(view.camera, interface),
                                    trainer.render(view.camera, interface)):
                # the same function (render_splats), same inputs, one process
                assert torch.equal(ours, theirs)


def test_render_each_kind(run, tmp_path, capsys):
    model, ds = load_model(run, splits=("test",))
    view = ds.test[0]
    paths = {}
    for kind in ("wet", "dry", "depth"):
        assert (main(["render", str(run), "--view", view.name, f"--{kind}", "--out", str(tmp_path / kind)])
                == 0)
        paths[kind] = tmp_path / kind / f"{view.name}.png"
        assert str(tmp_path / kind) in capsys.readouterr().out
    shape = (view.camera.height, view.camera.width, 3)
    wet, dry, colours = (layout.read_png(paths[k]) for k in ("wet", "dry", "depth"))
    assert wet.shape == dry.shape == colours.shape == shape
    img, alpha, depth = model.render(view.camera, interface=False)
    # the PNG is the render to the nearest level; round-off: write_png rounds a tie up, np.round to even
    np.testing.assert_allclose(dry, img.numpy().astype(np.float64) * 255, rtol=0, atol=0.5 + 1e-4)
    assert np.abs(wet.astype(int) - dry).mean() > 1  # under water, refraction moves and dims the bed
    exr = layout.read_depth(tmp_path / "depth" / f"{view.name}.exr")
    assert exr.shape == shape[:2] and exr.dtype == np.float32
    opaque = alpha[..., 0].numpy() >= 0.5
    assert opaque.sum() > 10
    # same render; float32 EXR: lossless
    np.testing.assert_array_equal(exr[opaque], depth[..., 0].numpy()[opaque])
    # cameras 2 m above the water, bed 1 m under it: z-depth between 2 and 5 m where the bed is opaque
    assert np.isfinite(exr[opaque]).all() and 2 < exr[opaque].min() and exr[opaque].max() < 5
    # the default place: RUN/renders/KIND
    assert main(["render", str(run), "--view", view.name]) == 0
    # same render, same PNG
    assert (layout.read_png(run / "renders" / "wet" / f"{view.name}.png") == wet).all()


def test_depth_where_nothing_is_drawn(run, tmp_path):
    model, ds = load_model(run, splits=("train",))
    view = ds.train[0]  # the nadir view
    half = replace(model, splats={k: v[model.splats["means"][:, 0] < 0] for k, v in model.splats.items()})
    assert write_render(half, view, "depth", tmp_path) == [tmp_path / "0000.exr", tmp_path / "0000.png"]
    _, alpha, depth = half.render(view.camera, interface=False)
    empty, drawn = alpha[..., 0].numpy() == 0, alpha[..., 0].numpy() > 0
    assert empty.sum() > 20 and drawn.sum() > 20
    exr, colours = layout.read_depth(tmp_path / "0000.exr"), layout.read_png(tmp_path / "0000.png")
    assert (exr[empty] == layout.NO_HIT).all() and (colours[empty] == 0).all()  # as the dataset's gt/depth
    # same render; float32 EXR: lossless
    np.testing.assert_array_equal(exr[drawn], depth[..., 0].numpy()[drawn])
    assert (colours[drawn].max(1) > 0).all()


def test_render_all_views(run, tmp_path, capsys):
    assert (main(["render", str(run), "--view", "all", "--split", "test", "--dry", "--out",
                  str(tmp_path / "t")]) == 0)
    assert capsys.readouterr().out.strip() == f"wrote 2 files for 2 views to {tmp_path / 't'}"
    assert main(["render", str(run), "--view", "all", "--depth", "--out", str(tmp_path / "a")]) == 0
    names = sorted(p.name for p in (tmp_path / "a").iterdir())
    assert names == [".ragsplat"] + sorted(f"{i:04d}.{ext}" for i in range(7) for ext in ("exr", "png"))


def test_eval_matches_the_ablation_and_the_library(run, ablated, evaluable_dataset, tmp_path,
                                                   monkeypatch, capsys):
    monkeypatch.setattr(metrics, "default_vgg16_path", lambda: tmp_path / "absent.pth")
    out = tmp_path / "scores.json"
    assert main(["score", str(run), "--out", str(out), "--no-download"]) == 0
    printed = capsys.readouterr().out
    for text in ("LPIPS n/a", "| init |", "| oracle plane (uses GT) |", "| full (this run), volume |",
                 "| full (this run), fused |", f"wrote {out}",
                 "2 held-out views, without it vs the dry images: PSNR"):
        assert text in printed
    res = json.loads(out.read_text())
    assert set(res) == KEYS and res["variant"] == "full" and res["seed"] == 0 and res["preset"] == "smoke"
    assert (res["water"] == res["truth_water"] == {"level": 0.0, "n": 1.33}
            and res["lpips"]["available"] is False)
    row = json.loads((ablated / "full" / "seed0" / "row.json").read_text())
    # bit-identical: the same library functions on the same run (its PLY is float32, lossless) in one process;
    # JSON keeps a float exactly
    assert res["geometry"] == row["geometry"] and res["appearance"] == row["appearance"]
    assert res["geometry_fused"] == row["geometry_fused"] and res["geometry_fused"]["fusion"]["views"] == 5
    assert (res["references"]["init"]
            == json.loads((ablated / "init" / "seed0" / "row.json").read_text())["geometry"])
    assert res["references"]["oracle plane"] == \
        json.loads((ablated / "oracle-plane" / "row.json").read_text())["geometry"]
    # the library, called directly
    gaussians, _, seed = load_run(run)
    ds = load_dataset(evaluable_dataset, splits=(), ground_truth=True)
    truth, ds_gsd = ds.ground_truth, ds.gsd
    table = ablation.extract_config(train.preset_config("smoke", seed=seed), len(truth.nodes), ds_gsd)
    geometry, _ = evaluate_geometry(gaussians, truth, table)
    assert res["geometry"] == json.loads(json.dumps(jsonable(geometry)))
    assert res["references"]["oracle plane"] == json.loads(
        json.dumps(jsonable(score_grid(oracle_grids(truth)["oracle plane"], truth))))
    assert main(["score", str(run), "--no-download"]) == 0  # the default place: RUN/eval.json
    assert json.loads((run / "eval.json").read_text())["geometry"] == res["geometry"]
    # the volume bed's culls changed: recorded with its scores, and the same as the library's
    assert main(["score", str(run), "--no-download", "--min-opacity", "0.05", "--max-scale-gsd", "inf"]) == 0
    loose = json.loads((run / "eval.json").read_text())["geometry"]
    cfg = replace(table, min_opacity=0.05, max_scale_gsd=math.inf)
    assert loose["extraction"]["config"] == {**res["geometry"]["extraction"]["config"], "min_opacity": 0.05,
                                             "max_scale_gsd": None}  # JSON has no inf
    assert loose == json.loads(json.dumps(jsonable(evaluate_geometry(gaussians, truth, cfg)[0])))


def test_one_line_errors(run, tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["render", str(run), "--view", "nope", "--out", str(tmp_path / "r")]) == 2
    one_line_error(capsys, "render", "no view 'nope' among the 7 views of")
    assert main(["render", str(run), "--view", "0000", "--split", "test", "--out", str(tmp_path / "r")]) == 2
    one_line_error(capsys, "render", "no view '0000' among the 2 test views of")
    for command in ("render", "score"):
        assert main([command, str(empty), "--view", "all"][:2 if command == "score" else 4]) == 2
        one_line_error(capsys, command, "not a finished training run (no config.json")
    # one scoring command: a run's options refused for a bed file and a file's for a run, in one line
    assert main(["score", str(run), "--band", "2", "--references"]) == 2
    one_line_error(capsys, "score", "--band, --references: for a bed file; ")
    bed = tmp_path / "bed.tif"
    assert main(["score", str(bed), "--truth", str(run), "--dem", str(bed), "--min-opacity", "0.1"]) == 2
    one_line_error(capsys, "score", "--dem, --min-opacity: for a run's directory; ")
    assert main(["score", str(bed)]) == 2
    one_line_error(capsys, "score", "a bed file is scored against a dataset: add --truth DIR")
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "photo.png").write_bytes(b"mine")
    assert main(["render", str(run), "--view", "0000", "--out", str(mine)]) == 2
    one_line_error(capsys, "render", "is not empty and was not written by ragsplat")
    assert not (tmp_path / "r").exists() and sorted(p.name for p in mine.iterdir()) == ["photo.png"]
    for argv, option in ((["render", str(run), "--view", "0000", "--wet", "--dry"], "--dry"),
                         (["score", str(run), "--out", str(tmp_path / "scores.txt")], "--out")):
        with pytest.raises(SystemExit) as done:
            main(argv)
        assert done.value.code == 2 and option in capsys.readouterr().err.splitlines()[-1]


def test_eval_needs_ground_truth(tmp_path, capsys):
    cams = ring_cameras(4, 16, 1.5, 0.8, target=(0, 0, -1))
    render_dataset(tmp_path / "data", bed_scene(200, 1.0, 1.0, seed=2), cams, WATER, 1,
                   {"xmin": -0.5, "xmax": 0.5, "ymin": -0.5, "ymax": 0.5})
    assert main(["train", "--data", str(tmp_path / "data"), "--out", str(tmp_path / "run"),
                 "--preset", "smoke",
                 "--iterations", "2", "--init-depth", "1.0", "--backend", "torch", "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["score", str(tmp_path / "run"), "--no-download"]) == 2
    one_line_error(capsys, "score", f"{tmp_path / 'data' / layout.GT_GRID}: ground-truth bed grid is missing")
    assert not (tmp_path / "run" / "eval.json").exists()
    assert main(["render", str(tmp_path / "run"), "--view", "0000"]) == 0  # rendering needs no ground truth
    shutil.rmtree(tmp_path / "data")
    assert main(["render", str(tmp_path / "run"), "--view", "0000"]) == 2
    one_line_error(capsys, "render", "the run's dataset directory does not exist (moved? give --data)")


def test_eval_scores_a_dem_against_the_truth(run, evaluable_dataset, tmp_path, monkeypatch, capsys):
    """The ground truth written as a DEM scores perfectly, and the same raised 15 cm has a 15 cm bias (the
    DEM's cells are read back at their centres, in the dataset's frame); --truth names the dataset."""
    monkeypatch.setattr(metrics, "default_vgg16_path", lambda: tmp_path / "absent.pth")
    grid = load_dataset(evaluable_dataset, splits=(), ground_truth=True).ground_truth.grid
    for name, dz in (("exact", 0.0), ("raised", 0.15)):
        rasters.write_raster(tmp_path / f"{name}.tif", grid[:, :2], [(grid[:, 2] + dz, "bed")],
                            layout.GT_GRID_STEP)
        assert main(["score", str(run), "--truth", str(evaluable_dataset), "--dem",
                     str(tmp_path / f"{name}.tif"),
                     "--out", str(tmp_path / f"{name}.json"), "--no-download"]) == 0
        dem = json.loads((tmp_path / f"{name}.json").read_text())["dem"]
        assert dem["survey"]["wet"]["n"] == len(grid) and (tmp_path / f"{name}_error.png").is_file()
        assert abs(dem["survey"]["wet"]["bias"] - dz) < 1e-6 and abs(dem["survey"]["wet"]["rmse"] - dz) < 1e-6
        assert dem["f1"]["10cm"] == pytest.approx(1.0 if dz == 0 else 0.0, abs=0.02)
    assert "its DEM (raised.tif)" in capsys.readouterr().out

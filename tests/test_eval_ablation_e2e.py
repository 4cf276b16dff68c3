"""`ragsplat ablation` end to end on a tiny synthetic dataset with a shrunken smoke preset (seconds)."""

import json
from dataclasses import replace

import numpy as np
import pytest

from eval import ablation
from ragsplat_core import train
from ragsplat_core.cli import main
from ragsplat_core.refraction import WaterSurface
from ragsplat_core.synthetic import bed_scene, render_views, ring_cameras, write_dataset


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    water = WaterSurface(0.0, 1.33)
    scene = bed_scene(200, half=1.0, depth=1.0, seed=0)
    cams = ring_cameras(4, 16, height=2.0, radius=0.8) + ring_cameras(2, 16, 2.2, 0.5, nadir=False)
    views = render_views(scene, cams, water, backend="torch")
    for i, v in enumerate(views):
        v["split"] = "train" if i < 5 else "test"
    write_dataset(root, views, water, {"xmin": -0.5, "xmax": 0.5, "ymin": -0.5, "ymax": 0.5})
    meta = json.loads((root / "scene.json").read_text())
    (root / "scene.json").write_text(json.dumps({**meta, "spec": {"bed": {"depth": 1.0}}}))
    x, y = np.meshgrid(np.arange(-10, 11) * 0.05, np.arange(-10, 11) * 0.05, indexing="ij")
    z = -1.0 + 0.1 * np.sin(2.0 * x) * np.cos(1.5 * y)  # bed_scene's surface
    (root / "gt").mkdir()
    np.save(root / "gt" / "bed_grid.npy", np.column_stack([x.ravel(), y.ravel(), z.ravel()]))
    return root


def test_ablation_command(dataset, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(train.PRESETS, "smoke", replace(train.PRESETS["smoke"], iterations=6, init_count=200,
                                                          backend="torch"))
    monkeypatch.setitem(ablation.PRESETS, "smoke", replace(ablation.PRESETS["smoke"], checkpoints=3))
    out = tmp_path / "runs"
    argv = ["ablation", "--data", str(dataset), "--out", str(out), "--preset", "smoke", "--variants", "3dgs",
            "full", "--vgg16", str(tmp_path / "absent.pth")]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "| full |" in printed and "LPIPS n/a" in printed
    res = json.loads((out / "results.json").read_text())
    assert list(res["variants"]) == ["3dgs", "full"] and res["seed"] == 0
    full = res["variants"]["full"]
    sched = train.PRESETS["smoke"].schedule
    steps = ablation.eval_steps(6, 3, sched.reset_every, sched.refine_stop_iter) + [6]
    assert len(steps) == 3 and [c["iteration"] for c in full["curve"]] == steps
    times = [c["time_s"] for c in full["curve"]]
    assert times == sorted(times) and times[-1] == pytest.approx(full["train_time_s"])
    assert full["config"]["variant"] == "full" and full["config"]["refraction"]["position"] is True
    assert len(full["appearance"]["per_view"]) == 2 and full["appearance"]["dry"]["psnr"] > 0
    assert full["geometry"]["n_gt"] == 21 * 21 and full["geometry"]["extraction"]["config"]["n_samples"] == 16 * 441
    for name in ("table1.md", "table2.md", "error_vs_time.png"):
        assert (out / name).stat().st_size > 0

    # rerun: both rows reused, nothing trained
    row = out / "full" / "row.json"
    before = row.read_text()
    assert main(argv) == 0
    assert "reusing" in capsys.readouterr().out and row.read_text() == before

    # killed after training but before the row was written: the checkpoint and the saved curve are reused
    row.unlink()
    assert main(argv) == 0
    again = json.loads(row.read_text())
    assert [c["iteration"] for c in again["curve"]] == steps
    assert again["train_time_s"] == pytest.approx(full["train_time_s"])

"""`ragsplat ablation` end to end on a tiny synthetic dataset with a shrunken smoke preset (seconds)."""

import json
from dataclasses import replace

import pytest

from eval import ablation, metrics
from ragsplat_core import train
from ragsplat_core.cli.main import main


def test_ablation_command(evaluable_dataset, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(metrics, "default_vgg16_path", lambda: tmp_path / "absent.pth")  # LPIPS n/a
    monkeypatch.setitem(train.PRESETS, "smoke", replace(train.PRESETS["smoke"], iterations=6, init_count=200,
                                                          backend="torch"))
    monkeypatch.setitem(ablation.PRESETS, "smoke", replace(ablation.PRESETS["smoke"], checkpoints=3))
    out = tmp_path / "runs"
    argv = ["ablation", "--data", str(evaluable_dataset), "--out", str(out), "--preset", "smoke", "--variants", "3dgs",
            "full"]
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

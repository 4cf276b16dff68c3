"""`ragsplat ablation` end to end on a tiny synthetic dataset with a shrunken smoke preset (seconds)."""

import json
import os
import shutil
from dataclasses import replace
from pathlib import Path

import pytest
from conftest import tiny_smoke

from eval import ablation, metrics
from ragsplat_core import train
from ragsplat_core.cli.main import main
from ragsplat_core.outputs import source_digest


def test_ablation_command(evaluable_dataset, tmp_path, monkeypatch, capsys):
    tiny_smoke(monkeypatch, tmp_path)
    monkeypatch.setitem(ablation.PRESETS, "smoke", replace(ablation.PRESETS["smoke"], checkpoints=3))
    data = tmp_path / "data"
    shutil.copytree(evaluable_dataset, data)
    out = tmp_path / "runs"
    argv = ["ablation", "--data", str(data), "--out", str(out), "--preset", "smoke", "--variants", "3dgs",
            "full", "--seeds", "0", "1", "--init", "grid", "--jobs", "1", "--no-download"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "| full | 2 | volume |" in printed and "| 3dgs x n | 2 | volume |" in printed and "LPIPS n/a" in printed
    assert "| oracle plane (uses GT) | - | - |" in printed and "F1@3% (%) | paper |" in printed
    res = json.loads((out / "results.json").read_text())
    # the field's references first (the tracks' need a triangulable dataset: not this tiny one), init last
    assert list(res["rows"]) == ["dietrich (3dgs)", "3dgs x n", "oracle plane", "oracle median plane", "init", "3dgs", "full"]
    assert res["seeds"] == [0, 1] and "the tracks' reference rows n/a" in printed
    assert "| init |" not in printed and "| dietrich (3dgs) | 2 | volume |" in printed
    full = res["rows"]["full"][0]
    # the start (every Gaussian at opacity 0.1) is scored as it stands, not culled away by the table's 0.7
    assert all(r["geometry"]["n_pred"] > 0 and r["geometry"]["extraction"]["gaussians_sampled"] > 0
               for r in res["rows"]["init"])
    sched = train.PRESETS["smoke"].schedule
    steps = [0] + ablation.eval_steps(6, 3, sched.reset_every, sched.refine_stop_iter) + [6]
    assert len(steps) == 4 and [c["iteration"] for c in full["curve"]] == steps
    times = [c["time_s"] for c in full["curve"]]
    assert times[0] == 0 and times == sorted(times) and times[-1] == pytest.approx(full["time"]["wall_s"])
    assert full["time"]["cpu_s"] > 0 and full["time"]["median_step_s"] > 0
    assert full["config"]["variant"] == "full" and full["config"]["refraction"]["position"] is True
    assert len(full["appearance"]["per_view"]) == 2 and full["appearance"]["dry"]["psnr"] > 0
    assert full["geometry"]["n_gt"] == 21 * 21 and full["geometry"]["extraction"]["config"]["n_samples"] == 4 * 441
    assert set(full["geometry"]["f1"]) == {"10cm", "30cm", "1%", "3%"}
    # the fused bed beside it, scored the same way (at the end only)
    fused = full["geometry_fused"]
    assert set(fused["f1"]) == {"10cm", "30cm", "1%", "3%"} and fused["n_gt"] == 21 * 21
    assert fused["fusion"]["views"] == 5 and fused["fusion"]["grid_points"] > 0
    assert fused["fusion"]["config"] == res["harness_preset"]["fuse"]
    assert "| full | 2 | fused |" in printed and "| 3dgs | 2 | volume |" in printed
    assert set(res["summary_fused"]) == {"3dgs", "full"}
    for name in ("table1.md", "table2.md", "table3.md", "error_vs_time.png", "oracle-plane/bed.tif",
                 "oracle-plane/depth_error.png", "full/seed1/bed.npy", "init/seed0/row.json",
                 "full/seed0/bed_fused.npy", "full/seed0/bed_fused.tif", "full/seed0/bed_fused.ply",
                 "full/seed0/depth_error_fused.png"):
        assert (out / name).stat().st_size > 0

    # rerun: every row reused, nothing trained
    row = out / "full" / "seed0" / "row.json"
    before = row.read_text()
    assert main(argv) == 0
    assert "reusing" in capsys.readouterr().out and row.read_text() == before

    # killed after training but before the row was written: the checkpoint and the saved curve are reused
    row.unlink()
    assert main(argv) == 0
    again = json.loads(row.read_text())
    assert [c["iteration"] for c in again["curve"]] == steps
    assert again["time"]["wall_s"] == pytest.approx(full["time"]["wall_s"])

    # one image changed: no row of the old dataset is reused
    image = data / json.loads((data / "transforms.json").read_text())["frames"][0]["file_path"]
    image.write_bytes(image.read_bytes() + b"\0")
    capsys.readouterr()
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "reusing" not in printed and "another dataset" in printed


def test_sigint_keeps_finished_rows_and_the_rerun_completes(evaluable_dataset, tmp_path):
    """A real Ctrl-C to `ragsplat ablation` while the second variant trains: one line, exit 130; the finished
    row and the interrupted variant's checkpoint are kept, and the same command then finishes the table."""
    import os
    import signal
    import subprocess
    import sys
    import time

    import torch

    out = tmp_path / "runs"
    cmd = [sys.executable, "-m", "ragsplat_core.cli.main", "ablation", "--data", str(evaluable_dataset), "--out",
           str(out), "--preset", "smoke", "--variants", "3dgs", "position", "--seeds", "0", "--init", "grid",
           "--jobs", "1", "--no-download"]
    env = {**os.environ, "TORCH_HOME": str(tmp_path / "torch")}  # no LPIPS backbone there: LPIPS n/a
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.time() + 300
    while not (out / "3dgs" / "seed0" / "row.json").exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.02)
    proc.send_signal(signal.SIGINT)  # `position` is starting to train
    err = [line for line in proc.communicate(timeout=300)[1].splitlines() if line.startswith("ragsplat")]
    assert proc.returncode == 130, err
    assert err == ["ragsplat ablation: interrupted; finished files are kept, rerun the same command to resume"]
    assert not (out / "position" / "seed0" / "row.json").exists()
    assert torch.load(out / "position" / "seed0" / "ckpt.pt", weights_only=True)["step"] >= 1
    row = (out / "3dgs" / "seed0" / "row.json").read_bytes()
    done = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env, timeout=300,
                          check=False)
    assert done.returncode == 0 and "[3dgs seed 0] reusing" in done.stdout
    assert (out / "3dgs" / "seed0" / "row.json").read_bytes() == row
    assert set(json.loads((out / "results.json").read_text())["rows"]) >= {"3dgs", "position"}


def test_jobs_train_every_row_once_and_the_tables_reuse_them(evaluable_dataset, tmp_path, monkeypatch, capsys):
    # the child processes run in-process here (the shrunken presets are monkeypatched in this one)
    import eval.cli

    smoke = train.PRESETS["smoke"]
    monkeypatch.setitem(train.PRESETS, "smoke", replace(smoke, iterations=4, init_count=100, backend="torch"))
    monkeypatch.setitem(ablation.PRESETS, "smoke", replace(ablation.PRESETS["smoke"], checkpoints=2))
    monkeypatch.setattr(metrics, "default_vgg16_path", lambda: tmp_path / "absent.pth")
    children = []

    class Child:  # a finished process (the rows trained in this one, in order)
        fail = False

        def __init__(self, cmd, env, log):
            assert cmd[1:3] == ["-m", "ragsplat_core.cli.main"] and env["OMP_NUM_THREADS"] == env["NUMBA_NUM_THREADS"]
            children.append(cmd[3:])
            self.pid, self.returncode = os.getpid(), 1 if self.fail else main(cmd[3:])

        def poll(self):
            return self.returncode

        def wait(self):
            return self.returncode

    monkeypatch.setattr(eval.cli, "spawn", Child)
    out = tmp_path / "runs"
    argv = ["ablation", "--data", str(evaluable_dataset), "--out", str(out), "--preset", "smoke", "--variants",
            "3dgs", "full", "--seeds", "0", "1", "--init", "grid", "--no-download"]
    assert main([*argv, "--jobs", "2"]) == 0
    assert children[0] == children[1] and children[0][:-6] == argv
    assert children[0][-6:-2] == ["--jobs", "1", "--code", source_digest(*ablation.ROW_CODE)]  # keyed to the start
    queue = Path(children[0][-1])  # one queue folder of this command's, shared, removed at the end
    assert children[0][-2] == "--queue" and queue.parent == out
    assert not queue.exists()
    printed = capsys.readouterr().out
    assert printed.count("training ...") == 4 and printed.count("reusing the finished row") == 4
    assert list(json.loads((out / "results.json").read_text())["rows"]) == \
        ["dietrich (3dgs)", "3dgs x n", "oracle plane", "oracle median plane", "init", "3dgs", "full"]
    # a failed process fails the command, with the log to read
    monkeypatch.setattr(Child, "fail", True)
    assert main([*argv, "--jobs", "2"]) == 2
    assert "process 1 of 2 exited with 1 while training no row (log: " in capsys.readouterr().err


def test_a_killed_process_is_named_with_its_row_and_the_rerun_finishes(evaluable_dataset, tmp_path):
    """`--jobs 2` for real: a SIGKILL of one training process ends the command at once (exit 2, one line
    naming the row that process held, the other process stopped at a checkpoint); the same command then
    trains what is left and writes the tables."""
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "runs"
    cmd = [sys.executable, "-m", "ragsplat_core.cli.main", "ablation", "--data", str(evaluable_dataset), "--out",
           str(out), "--preset", "smoke", "--variants", "3dgs", "full", "--seeds", "0", "--init", "grid",
           "--jobs", "2", "--no-download"]
    env = {**os.environ, "TORCH_HOME": str(tmp_path / "torch")}  # no LPIPS backbone there: LPIPS n/a
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    victim, deadline = None, time.time() + 300
    while victim is None and time.time() < deadline and proc.poll() is None:
        for marker in out.glob(".queue-*/*-seed0"):  # a row a process took: its pid inside
            pid = marker.read_text().strip()
            if pid and (out / marker.name.replace("-seed", "/seed") / "key.json").exists():
                victim = (int(pid), marker)
                break
        time.sleep(0.01)
    assert victim is not None, proc.communicate()
    pid, marker = victim
    os.kill(pid, signal.SIGSTOP)  # frozen first: it cannot finish the row between the look and the kill
    assert not marker.with_name(marker.name + ".done").exists()
    os.kill(pid, signal.SIGKILL)
    printed, err = proc.communicate(timeout=300)
    row = marker.name.replace("-seed", " seed ")
    assert proc.returncode == 2, err
    assert f"was killed by SIGKILL while training {row}; stopping the others" in printed
    lines = [line for line in err.splitlines() if line.startswith("ragsplat")]
    assert len(lines) == 1 and f"was killed by SIGKILL while training {row} (log: " in lines[0], err
    assert "rerun the same command to resume" in lines[0]
    assert not (out / "results.json").exists()
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600,
                          check=False)
    assert done.returncode == 0, done.stderr
    rows = json.loads((out / "results.json").read_text())["rows"]
    assert len(rows["3dgs"]) == 1 and len(rows["full"]) == 1


def test_one_level_trains_with_the_level_it_is_given_and_scores_against_the_surface(evaluable_dataset, tmp_path,
                                                                                     monkeypatch, capsys):
    # `--one-level` for real (a shrunken smoke row): the row trains under one level at the mean of the surveyed
    # edge points, the references are given it, the truth's surface scores them, and results.json records both
    smoke = train.PRESETS["smoke"]
    monkeypatch.setitem(train.PRESETS, "smoke", replace(smoke, iterations=4, init_count=100, backend="torch"))
    monkeypatch.setitem(ablation.PRESETS, "smoke", replace(ablation.PRESETS["smoke"], checkpoints=2))
    monkeypatch.setattr(metrics, "default_vgg16_path", lambda: tmp_path / "absent.pth")
    data = tmp_path / "data"
    shutil.copytree(evaluable_dataset, data)
    (data / "survey").mkdir()
    (data / ablation.EDGE_POINTS).write_text("x,y,z\n-0.5,-0.6,0.03\n0.5,-0.6,0.01\n-0.5,0.6,0.02\n0.5,0.6,0.0\n")
    out = tmp_path / "runs"
    assert main(["ablation", "--data", str(data), "--out", str(out), "--preset", "smoke", "--variants", "3dgs",
                 "full", "--seeds", "0", "--init", "grid", "--jobs", "1", "--no-download", "--one-level"]) == 0
    printed = capsys.readouterr().out
    assert "ONE LEVEL (--one-level)" in printed and "0.015 m (the mean of the 4 surveyed edge points" in printed
    res = json.loads((out / "results.json").read_text())
    assert res["one_level"]["level"] == pytest.approx(0.015) and res["water"] == {"level": 0.0, "n": 1.33}
    full = res["rows"]["full"][0]
    assert full["config"]["water_level"] == pytest.approx(0.015) and full["config"]["water_slope"] == [0.0, 0.0]
    assert all(rows[0]["key"]["one_level"] == res["one_level"] for rows in res["rows"].values())

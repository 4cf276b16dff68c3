"""`ragsplat ablation` end to end on a tiny synthetic dataset with a shrunken smoke preset (seconds)."""

import json
import os
import shutil
from dataclasses import replace

import pytest
from conftest import kill_a_worker, tiny_smoke

from ragsplat import train
from ragsplat.cli.main import main
from ragsplat.eval import ablation, metrics


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
    assert ("| full | 2 | volume |" in printed and "| 3dgs x n | 2 | volume |" in printed
            and "LPIPS n/a" in printed)
    assert "| oracle plane (uses GT) | - | - |" in printed and "F1@3% (%) | paper |" in printed
    res = json.loads((out / "results.json").read_text())
    # the field's references first (the tracks' need a triangulable dataset: not this tiny one), init last
    assert (list(res["rows"])
            == ["dietrich (3dgs)", "3dgs x n", "oracle plane", "oracle median plane", "init", "3dgs", "full"])
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
    assert (full["geometry"]["n_gt"] == 21 * 21
            and full["geometry"]["extraction"]["config"]["n_samples"] == 4 * 441)
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
    cmd = [sys.executable, "-m", "ragsplat.cli.main", "ablation", "--data", str(evaluable_dataset),
           "--out", str(out), "--preset", "smoke", "--variants", "3dgs", "position", "--seeds", "0", "--init",
           "grid", "--jobs", "1", "--no-download"]
    env = {**os.environ, "TORCH_HOME": str(tmp_path / "torch")}  # no LPIPS backbone there: LPIPS n/a
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.time() + 300
    while (not (out / "3dgs" / "seed0" / "row.json").exists() and time.time() < deadline
           and proc.poll() is None):
        time.sleep(0.02)
    proc.send_signal(signal.SIGINT)  # `position` is starting to train
    err = [line for line in proc.communicate(timeout=300)[1].splitlines() if line.startswith("ragsplat")]
    assert proc.returncode == 130, err
    assert err == [("ragsplat ablation: interrupted; finished files are kept, rerun the same command "
                    "to resume")]
    assert not (out / "position" / "seed0" / "row.json").exists()
    assert torch.load(out / "position" / "seed0" / "ckpt.pt", weights_only=True)["step"] >= 1
    row = (out / "3dgs" / "seed0" / "row.json").read_bytes()
    done = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env,
                          timeout=300, check=False)
    assert done.returncode == 0 and "[3dgs seed 0] reusing" in done.stdout
    assert (out / "3dgs" / "seed0" / "row.json").read_bytes() == row
    assert set(json.loads((out / "results.json").read_text())["rows"]) >= {"3dgs", "position"}


def test_rows_on_a_dask_cluster_are_the_rows_of_one_process(evaluable_dataset, tmp_path, monkeypatch, capsys):
    """`--scheduler` on a cluster the test starts (two workers in this process, so that the shrunken presets
    reach them): each row is trained once, by a task, and the tables reuse them; the rows equal those of
    `--jobs 1` to round-off. A task that fails ends the command in one line naming its row and log."""
    from dask.distributed import LocalCluster

    smoke = train.PRESETS["smoke"]
    monkeypatch.setitem(train.PRESETS, "smoke", replace(smoke, iterations=4, init_count=100, backend="torch"))
    monkeypatch.setitem(ablation.PRESETS, "smoke", replace(ablation.PRESETS["smoke"], checkpoints=2))
    monkeypatch.setattr(metrics, "default_vgg16_path", lambda: tmp_path / "absent.pth")
    argv = ["ablation", "--data", str(evaluable_dataset), "--preset", "smoke", "--variants", "3dgs", "full",
            "--seeds", "0", "1", "--init", "grid", "--no-download"]
    one, dask = tmp_path / "one", tmp_path / "dask"
    assert main([*argv, "--out", str(one), "--jobs", "1"]) == 0
    capsys.readouterr()
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        assert main([*argv, "--out", str(dask), "--scheduler", cluster.scheduler_address]) == 0
        printed = capsys.readouterr().out
        assert f"training 4 rows on the Dask cluster at {cluster.scheduler_address}" in printed
        assert printed.count("reusing the finished row") == 4 and "training ..." not in printed
        logs = sorted(p.name for p in (dask / "logs").iterdir())
        assert logs == ["3dgs-seed0.log", "3dgs-seed1.log", "full-seed0.log", "full-seed1.log"]
        assert all((dask / "logs" / name).read_text().count("training ...") == 1 for name in logs)
        rows = {path: json.loads((dask / path).read_text()) for path in
                ("3dgs/seed0/row.json", "full/seed1/row.json")}
        for path, row in rows.items():
            other = json.loads((one / path).read_text())
            for threshold, f1 in row["geometry"]["f1"].items():
                assert f1 == pytest.approx(other["geometry"]["f1"][threshold], abs=1e-9), (path, threshold)
            assert row["key"] == other["key"]
        # a task that fails: the command ends, naming the row and its log
        def broken(*args, **kw):
            raise RuntimeError("out of disk")

        monkeypatch.setattr(ablation.TrainEval, "train", broken)
        assert main([*argv, "--out", str(tmp_path / "broken"), "--scheduler", cluster.scheduler_address]) == 2
        err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("ragsplat")]
        assert len(err) == 1 and "failed: RuntimeError: out of disk (log: " in err[0], err
        assert "rerun the same command to resume" in err[0]


def test_a_killed_worker_s_row_is_trained_again_and_the_command_finishes(evaluable_dataset, tmp_path):
    """`--jobs 2` for real (a local cluster of two worker processes): a SIGKILL of the worker training a row
    does not end the command: Dask runs the row again on a worker, which resumes it, and the tables are
    written; the row's log shows both workers."""
    import sys

    out = tmp_path / "runs"
    cmd = [sys.executable, "-m", "ragsplat.cli.main", "ablation", "--data", str(evaluable_dataset),
           "--out", str(out), "--preset", "smoke", "--variants", "3dgs", "full", "--seeds", "0", "--init",
           "grid", "--jobs", "2", "--no-download"]
    env = {**os.environ, "TORCH_HOME": str(tmp_path / "torch")}  # no LPIPS backbone there: LPIPS n/a

    def victim():  # a row a worker took: its pid in the first line
        for log in out.glob("logs/*-seed0.log"):
            first = log.read_text().split("\n", 1)[0]
            row = log.stem.replace("-seed", "/seed")
            if first.endswith(tuple("0123456789")) and (out / row / "key.json").exists():
                return int(first.rsplit(" ", 1)[1]), log

    log, err, status = kill_a_worker(cmd, victim, env)
    assert status == 0, err
    rows = json.loads((out / "results.json").read_text())["rows"]
    assert len(rows["3dgs"]) == 1 and len(rows["full"]) == 1
    workers = [line for line in log.read_text().splitlines() if "worker process" in line]
    assert len(workers) == 2 and workers[0] != workers[1], log.read_text()


def test_one_level_trains_with_the_level_it_is_given_and_scores_against_the_surface(
        evaluable_dataset, tmp_path, monkeypatch, capsys):
    # `--one-level` for real (a shrunken smoke row): the row trains under one level at the mean of the
    # surveyed edge points, the references are given it, the truth's surface scores them, and results.json
    # records both
    smoke = train.PRESETS["smoke"]
    monkeypatch.setitem(train.PRESETS, "smoke", replace(smoke, iterations=4, init_count=100, backend="torch"))
    monkeypatch.setitem(ablation.PRESETS, "smoke", replace(ablation.PRESETS["smoke"], checkpoints=2))
    monkeypatch.setattr(metrics, "default_vgg16_path", lambda: tmp_path / "absent.pth")
    data = tmp_path / "data"
    shutil.copytree(evaluable_dataset, data)
    (data / "survey").mkdir()
    (data / ablation.EDGE_POINTS).write_text("x,y,z\n-0.5,-0.6,0.03\n0.5,-0.6,0.01\n"
                                             "-0.5,0.6,0.02\n0.5,0.6,0.0\n")
    out = tmp_path / "runs"
    assert main(["ablation", "--data", str(data), "--out", str(out), "--preset", "smoke",
                 "--variants", "3dgs", "full", "--seeds", "0", "--init", "grid", "--jobs", "1",
                 "--no-download", "--one-level"]) == 0
    printed = capsys.readouterr().out
    assert ("ONE LEVEL (--one-level)" in printed
            and "0.015 m (the mean of the 4 surveyed edge points" in printed)
    res = json.loads((out / "results.json").read_text())
    assert res["one_level"]["level"] == pytest.approx(0.015) and res["water"] == {"level": 0.0, "n": 1.33}
    full = res["rows"]["full"][0]
    assert (full["config"]["water_level"] == pytest.approx(0.015)
            and full["config"]["water_slope"] == [0.0, 0.0])
    assert all(rows[0]["key"]["one_level"] == res["one_level"] for rows in res["rows"].values())

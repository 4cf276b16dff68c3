"""What the rows of one ablation share is made once: the dataset's triangulated tracks under a lock (two
processes asking at once run pycolmap once), and `--jobs` builds them before its processes start."""

import threading
import time

import numpy as np

from ragsplat.cli.main import main
from ragsplat.dataset import colmap


def test_two_processes_asking_at_once_triangulate_once(tmp_path, monkeypatch):
    calls = []

    def slow_triangulate(root, work):  # long enough for the second caller to arrive while it runs
        calls.append(threading.get_ident())
        work.mkdir(parents=True, exist_ok=True)
        time.sleep(0.5)
        return np.zeros((3, 6)), np.zeros((6, 4)), ["a.png", "b.png"]

    monkeypatch.setattr(colmap, "triangulate", slow_triangulate)
    found = []
    threads = [threading.Thread(target=lambda: found.append(colmap.triangulated_points(tmp_path, "f1")))
               for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 1 and found == [tmp_path / colmap.TRIANGULATED] * 2
    colmap.triangulated_points(tmp_path, "f1")
    assert len(calls) == 1  # cached
    colmap.triangulated_points(tmp_path, "f2")
    assert len(calls) == 2  # another dataset content: made again


def test_jobs_triangulate_before_the_tasks_start(evaluable_dataset, tmp_path, monkeypatch, capsys):
    from dask.distributed import LocalCluster

    from ragsplat.eval import ablation

    order = []
    monkeypatch.setattr(colmap, "triangulated_points",
                        lambda root, fingerprint: order.append("tracks") or tmp_path / "tracks.npy")

    rows = tmp_path / "rows.txt"  # the task runs on a copy of this function: it says what it did in a file

    # a row's task that fails at once: the command stops after the shared inputs
    def fails(job, variant, seed):
        with open(rows, "a") as f:
            f.write("row\n")
        raise RuntimeError("no")

    monkeypatch.setattr(ablation, "train_row", fails)
    with LocalCluster(n_workers=1, processes=False, dashboard_address=None) as cluster:
        argv = ["ablation", "--data", str(evaluable_dataset), "--out", str(tmp_path / "runs"),
                "--preset", "smoke", "--variants", "3dgs", "--seeds", "0", "--no-download", "--scheduler",
                cluster.scheduler_address]
        assert main(argv) == 2  # the default start: the refracted tracks
        assert order == ["tracks"] and rows.read_text() == "row\n"
        assert "training 3dgs seed 0 failed: RuntimeError: no" in capsys.readouterr().err
        order.clear()
        assert main([*argv, "--init", "grid"]) == 2
        assert order == [] and rows.read_text() == "row\nrow\n"  # a start that needs no tracks makes none

"""What the rows of one ablation share is made once: the dataset's triangulated tracks under a lock (two
processes asking at once run pycolmap once), and `--jobs` builds them before its processes start."""

import threading
import time

import numpy as np

import eval.cli
from ragsplat_core.cli.main import main
from ragsplat_core.dataset import colmap


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


def test_jobs_triangulate_before_the_processes_start(evaluable_dataset, tmp_path, monkeypatch, capsys):
    order = []
    monkeypatch.setattr(colmap, "triangulated_points",
                        lambda root, fingerprint: order.append("tracks") or tmp_path / "tracks.npy")

    class Child:  # a process that fails at once: the command stops after the shared inputs were made
        pid, returncode = -1, 1

        def __init__(self, cmd, env, log):
            order.append("process")

        def poll(self):
            return self.returncode

        def wait(self):
            return self.returncode

    monkeypatch.setattr(eval.cli, "spawn", Child)
    argv = ["ablation", "--data", str(evaluable_dataset), "--out", str(tmp_path / "runs"), "--preset", "smoke",
            "--variants", "3dgs", "--seeds", "0", "--no-download"]  # the defaults: refracted start, 2 processes
    assert main(argv) == 2
    assert order == ["tracks", "process", "process"]
    assert "exited with 1 while training no row" in capsys.readouterr().err
    order.clear()
    assert main([*argv, "--init", "grid"]) == 2
    assert order == ["process", "process"]  # a start that needs no tracks makes none

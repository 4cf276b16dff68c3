"""The bad-input table: what a new user gets wrong, each ending in one line on stderr naming the file or
option, exit code 2, and nothing outside the run directory changed (no user file touched, no temporaries
left). Arguments argparse refuses are in test_layout.py; interrupts in the SIGINT tests."""

import json
import shutil

import pytest
import torch

from ragsplat.cli.main import main


def edit_json(path, fn):
    meta = json.loads(path.read_text())
    fn(meta)
    path.write_text(json.dumps(meta))


def first_image(data):
    return data / json.loads((data / "transforms.json").read_text())["frames"][0]["file_path"]


def foreign_out(tmp):
    (tmp / "run").mkdir()
    (tmp / "run" / "config.json").write_text("someone else's")


def fill(argv, tmp):
    return [a.format(data=tmp / "data", run=tmp / "run", tmp=tmp) for a in argv]


def garbage_checkpoint(tmp):
    assert main(fill(TRAIN, tmp)) == 0  # a run of ours, then its checkpoint damaged
    (tmp / "run" / "ckpt.pt").write_bytes(b"\0garbage")


def full_disk(monkeypatch):
    def no_space(obj, f, *a, **k):
        raise OSError(28, "No space left on device", str(f))

    monkeypatch.setattr(torch, "save", no_space)


def read_only(monkeypatch):
    from ragsplat import outputs

    def denied(src, dst):
        raise PermissionError(13, "Permission denied", str(dst))

    monkeypatch.setattr(outputs.os, "replace", denied)


TRAIN = ["train", "--data", "{data}", "--out", "{run}", "--preset", "smoke", "--iterations", "2",
         "--init-depth", "1.0", "--no-progress"]
ABLATION = ["ablation", "--data", "{data}", "--out", "{run}", "--preset", "smoke", "--variants", "3dgs",
            "--no-download"]

# (id, setup(tmp) on the copied dataset `tmp/data`, argv, phrase in the message, environment patch)
CASES = [
    ("data missing", lambda t: shutil.rmtree(t / "data"), TRAIN, "does not exist", None),
    ("transforms not json", lambda t: (t / "data" / "transforms.json").write_text("{"), TRAIN,
     "not valid JSON", None),
    ("camera under water", lambda t: edit_json(t / "data" / "transforms.json",
                                               lambda m: m.update(water={"level": 50.0, "n": 1.33})),
     TRAIN, "not above the water surface", None),
    ("refractive index < 1", lambda t: edit_json(t / "data" / "transforms.json",
                                                 lambda m: m.update(water={"level": 0.0, "n": 0.5})),
     TRAIN, "refractive index must be finite and >= 1, got 0.5", None),
    ("image missing", lambda t: first_image(t / "data").unlink(), TRAIN, "0000.png: image file is missing",
     None),
    ("image truncated", lambda t: first_image(t / "data").write_bytes(b"\x89PNG\r\n"), TRAIN,
     "0000.png: not a readable image", None),
    ("out holds foreign files", foreign_out, TRAIN, "not written by ragsplat", None),
    ("checkpoint garbage", garbage_checkpoint, TRAIN, "not a readable checkpoint", None),
    ("unknown device", lambda t: None, TRAIN + ["--device", "tpu9"], "unknown torch device 'tpu9'", None),
    ("init depth in mm", lambda t: None, TRAIN + ["--init-depth", "1000"], "init depth 1000 m", None),
    ("disk full at the checkpoint", lambda t: None, TRAIN, "run/ckpt.pt: No space left on device", full_disk),
    ("out not writable", lambda t: None, TRAIN, "Permission denied", read_only),
    ("ablation out not writable", lambda t: None, ABLATION, "Permission denied", read_only),
    ("ablation without held-out views", lambda t: edit_json(
        t / "data" / "transforms.json", lambda m: [f.update(split="train") for f in m["frames"]]),
     ABLATION, "no frame has split 'test'", None),
    ("ablation without ground truth", lambda t: (t / "data" / "gt" / "bed_grid.npy").unlink(), ABLATION,
     "ground-truth bed grid is missing", None),
    ("ablation vgg16 path missing", lambda t: None, ABLATION + ["--vgg16", "{tmp}/nowhere.pth"],
     "nowhere.pth: no such file", None),
    ("ablation out holds foreign files", foreign_out, ABLATION, "not written by ragsplat", None),
]


def snapshot(root, skip):
    """{relative path: (size, mtime_ns, bytes)} of every file under root outside `skip`."""
    out = {}
    for p in sorted(root.rglob("*")):
        if p.is_file() and skip not in p.parents and p != skip:
            out[str(p.relative_to(root))] = (p.stat().st_size, p.stat().st_mtime_ns, p.read_bytes())
    return out


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_bad_input_is_one_line_exit_2_and_touches_nothing_else(case, evaluable_dataset, tmp_path,
                                                               monkeypatch, capsys):
    _, setup, argv, phrase, patch = case
    shutil.copytree(evaluable_dataset, tmp_path / "data")
    argv = fill(argv, tmp_path)
    setup(tmp_path)
    if patch is not None:
        patch(monkeypatch)
    capsys.readouterr()
    before = snapshot(tmp_path, tmp_path / "run")
    code = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith(f"ragsplat {argv[0]}") and phrase in err[0], err
    assert snapshot(tmp_path, tmp_path / "run") == before  # nothing outside the run directory changed
    run = tmp_path / "run"
    assert not (run.is_dir() and [p for p in run.rglob("*") if p.name.endswith(".tmp")])  # no temporaries

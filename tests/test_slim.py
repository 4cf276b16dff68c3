"""`python -m tools.slim`: a dataset copy with only what the ablation reads scores a row exactly as the whole
dataset does and never triangulates again; on a machine without rasterio the ablation's rows are made with
`--no-geotiffs`, and the same command where rasterio is writes their GeoTIFFs from the arrays."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
from conftest import tiny_smoke

from ragsplat.cli.main import main
from ragsplat.dataset import colmap, layout, rasters
from ragsplat.dataset.load import load_dataset
from ragsplat.eval.references import SEEDLESS
from ragsplat.eval.rows import slug
from tools import slim

ROOT = Path(__file__).resolve().parents[1]


def fake_tracks(calls):
    """pycolmap finds too few features in the tiny scene: tracks of GT bed points seen along straight rays
    at their apparent depth (d / n), observed by every training view that sees them. Counts its calls."""
    def triangulate(root, work):
        calls.append(root)
        ds = load_dataset(root, splits=("train",), load_dry=False)
        bed = np.load(root / layout.GT_GRID)[::9]
        pts = np.column_stack([bed[:, :2], bed[:, 2] / ds.water.n, np.zeros((len(bed), 3))])
        views = sorted(ds.train, key=lambda v: v.file_path)
        obs = []
        for k, cam in enumerate(v.camera for v in views):
            uv, z = cam.project(pts[:, :3])
            seen = np.flatnonzero((z > 0) & (uv >= 0).all(1) & (uv < [cam.width, cam.height]).all(1))
            obs += [(i, k, *uv[i]) for i in seen]
        return pts, np.asarray(obs, dtype=np.float64), [v.file_path for v in views]
    return triangulate


def test_a_slim_copy_scores_a_row_as_the_whole_dataset(evaluable_dataset, tmp_path, monkeypatch, capsys):
    calls = []
    monkeypatch.setattr(colmap, "triangulate", fake_tracks(calls))
    tiny_smoke(monkeypatch, tmp_path)
    data, copy = tmp_path / "data", tmp_path / "copy"
    shutil.copytree(evaluable_dataset, data)
    layout.write_ply(data / layout.GT_MESH, np.zeros((3, 3)))  # in the fingerprint, left out of the copy
    assert slim.main([str(data), str(copy)]) == 0
    assert f"{copy}: " in capsys.readouterr().out and calls == [data]  # the tracks were made in the source

    stamp = json.loads((copy / colmap.STAMP).read_text())
    assert stamp["fingerprint"] == layout.fingerprint(copy) != layout.fingerprint(data)
    assert colmap.triangulated_points(copy, layout.fingerprint(copy)) == copy / colmap.TRIANGULATED
    assert calls == [data]  # the copy's tracks are the source's, not made again
    assert np.array_equal(np.load(copy / colmap.TRIANGULATED), np.load(data / colmap.TRIANGULATED))
    assert not (copy / layout.GT_MESH).exists() and (copy / layout.GT_GRID).is_file()

    rows = {}
    for name, root in (("whole", data), ("slim", copy)):
        out = tmp_path / f"runs-{name}"
        assert main(["ablation", "--data", str(root), "--out", str(out), "--preset", "smoke", "--variants",
                     "full", "--seeds", "0", "--init", "grid", "--jobs", "1", "--no-download"]) == 0
        rows[name] = {row: json.loads((out / slug(row) / "row.json").read_text())
                      for row in ("full/seed0", *SEEDLESS)}
    for row in SEEDLESS:  # the tracks' references (TINs) and the oracle plane
        assert rows["slim"][row]["geometry"] == rows["whole"][row]["geometry"], row
    whole, thin = rows["whole"]["full/seed0"], rows["slim"]["full/seed0"]
    assert thin["geometry"] == whole["geometry"] and thin["geometry_fused"] == whole["geometry_fused"]
    # appearance: the same images and renders; the time and the dataset's identity are the only differences
    assert thin["appearance"]["refr"] == whole["appearance"]["refr"]
    assert thin["appearance"]["dry"] == whole["appearance"]["dry"]
    assert calls == [data]

    assert slim.main([str(data), str(copy)]) == 2  # a copy goes into a new folder
    assert "not empty" in capsys.readouterr().err
    assert slim.main([str(tmp_path / "nothing"), str(tmp_path / "new")]) == 2


# rasterio absent: its import fails, as on a machine where it is not installed; the ablation as conftest's
# `tiny_smoke` makes it
BARE_ABLATION = """
import sys
from pathlib import Path


class NoRasterio:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] == "rasterio":
            raise ModuleNotFoundError(f"No module named {name!r}")


sys.meta_path.insert(0, NoRasterio())
sys.path.insert(0, sys.argv[1])
import pytest
from conftest import tiny_smoke

from ragsplat.cli.main import main

tiny_smoke(pytest.MonkeyPatch(), Path(sys.argv[2]))
sys.exit(main(sys.argv[3:]))
"""


def test_rows_made_without_rasterio_get_their_geotiffs_where_it_is(evaluable_dataset, tmp_path, monkeypatch):
    monkeypatch.setattr(colmap, "triangulate", fake_tracks([]))
    tiny_smoke(monkeypatch, tmp_path)
    copy, out = tmp_path / "copy", tmp_path / "runs"
    assert slim.main([str(evaluable_dataset), str(copy)]) == 0  # its tracks made, so none is made there
    args = ["ablation", "--data", str(copy), "--out", str(out), "--preset", "smoke", "--variants", "full",
            "--seeds", "0", "--init", "grid", "--jobs", "1", "--no-download"]
    done = subprocess.run([sys.executable, "-c", BARE_ABLATION, str(ROOT / "tests"), str(tmp_path), *args,
                           "--no-geotiffs"], capture_output=True, text=True, cwd=tmp_path, check=False)
    assert done.returncode == 0, done.stderr
    assert not list(out.rglob("*.tif")) and (out / "full/seed0/bed.npy").is_file()
    bare = json.loads((out / "full/seed0/row.json").read_text())
    assert "geotiff" not in bare["outputs"]

    assert main(args) == 0  # here, with rasterio: the rows reused, their GeoTIFFs written
    row = json.loads((out / "full/seed0/row.json").read_text())
    assert row["geometry"] == bare["geometry"]
    assert row["outputs"]["geotiff"] == str(out / "full/seed0/bed.tif")
    direct = tmp_path / "direct.tif"
    rasters.write_elevation(direct, np.load(out / "full/seed0/bed.npy"), layout.GT_GRID_STEP)
    import rasterio

    with rasterio.open(out / "full/seed0/bed.tif") as a, rasterio.open(direct) as b:
        assert (a.shape, a.transform, a.crs) == (b.shape, b.transform, b.crs)
        assert np.array_equal(a.read(), b.read(), equal_nan=True)
    for name in SEEDLESS:  # the references' rows too
        assert (out / slug(name) / "bed.tif").is_file() or not len(np.load(out / slug(name) / "bed.npy"))

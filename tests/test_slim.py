"""`python -m tools.slim`: a dataset copy with only what the ablation reads scores a row exactly as the whole
dataset does and never triangulates again; the rasterio stand-in serves what the ablation calls and refuses
to read a raster."""

import json
import os
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


def test_the_rasterio_stand_in_reads_none_and_its_rasters_unpack_to_the_geotiffs_rasterio_writes(tmp_path):
    package = slim.write_stand_ins(tmp_path / "stand-ins")
    script = """
import sys
import numpy as np
import rasterio
from ragsplat.eval.score import dem_points
from ragsplat.dataset import layout
from ragsplat.dataset import rasters
from ragsplat.errors import DatasetError
assert rasterio.__file__.startswith(sys.argv[1]), rasterio.__file__
georef = layout.Georef()
assert georef.wkt() == layout.LOCAL_CRS
xy = np.array([[0.0, 0.0], [0.05, 0.0], [0.05, 0.1]])
path = sys.argv[2]
bands = [(np.array([1.0, 2.0, np.nan]), "bed"), (np.array([3.0, 4.0, 5.0]), "tvu")]
rasters.write_raster(path, xy, bands, 0.05)
try:
    dem_points(path, georef)
except DatasetError as err:
    print("refused:", err)
"""
    tif = tmp_path / "bed.tif"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(package.parent), str(ROOT)])}
    done = subprocess.run([sys.executable, "-c", script, str(package), str(tif)], env=env,
                          capture_output=True, text=True, cwd=tmp_path, check=False)
    assert done.returncode == 0, done.stderr
    assert "refused:" in done.stdout and "reads no raster" in done.stdout
    # brought back here (rasterio): the same GeoTIFF as rasterio's own writer makes of the same bands
    import rasterio

    assert slim.main(["--unpack", str(tif)]) == 0
    direct = tmp_path / "direct.tif"
    rasters.write_raster(direct, np.array([[0.0, 0.0], [0.05, 0.0], [0.05, 0.1]]),
                        [(np.array([1.0, 2.0, np.nan]), "bed"), (np.array([3.0, 4.0, 5.0]), "tvu")], 0.05)
    with rasterio.open(tif) as a, rasterio.open(direct) as b:
        assert (a.count, a.shape, a.transform, a.nodata, a.descriptions) == (
            b.count, b.shape, b.transform, b.nodata, b.descriptions)
        assert a.crs == b.crs and np.array_equal(a.read(), b.read())
    assert slim.main(["--unpack", str(direct)]) == 2  # a real GeoTIFF is no stand-in's file

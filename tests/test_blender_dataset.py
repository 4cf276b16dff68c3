"""End to end at smoke scale: `ragsplat generate` writes the contracted layout; dry z-depth unprojects onto
the exported bed mesh; reruns resume, shards split and merge, bad output directories are refused."""

import json
import shutil

import cv2
import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from ragsplat.camera import Camera
from ragsplat.cli.main import main
from ragsplat.dataset.layout import NO_HIT, read_depth

pytestmark = pytest.mark.blender


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    out = tmp_path_factory.mktemp("data") / "smoke"
    assert main(["generate", "--preset", "smoke", "--out", str(out), "--quiet"]) == 0
    return out


def test_layout_and_transforms_contract(smoke):
    tf = json.loads((smoke / "transforms.json").read_text())
    scene = json.loads((smoke / "scene.json").read_text())
    assert tf["camera_model"] == "OPENCV" and tf["water"] == {"level": 0.0, "n": 1.33}
    assert (tf["w"], tf["h"]) == (64, 64) and tf["cx"] == 32.0
    frames = tf["frames"]
    assert len(frames) == scene["flight"]["train_views"] + scene["flight"]["test_views"]
    assert {f["split"] for f in frames} == {"train", "test"}
    assert {f["kind"] for f in frames} == {"nadir", "oblique20", "oblique40"}
    for f in frames:
        for key in ("file_path", "dry_file_path", "gt_depth_file_path"):
            assert (smoke / f[key]).is_file()
        assert f["file_path"].startswith("images/wet/")
        cam = Camera.from_c2w_gl(f["transform_matrix"], tf["w"], tf["h"],
                                 intrinsics=(tf["fl_x"], tf["fl_y"], tf["cx"], tf["cy"]))
        np.testing.assert_allclose(cam.w2c, f["w2c"], atol=1e-12)
    img = cv2.imread(str(smoke / frames[0]["file_path"]), cv2.IMREAD_UNCHANGED)
    assert img.dtype == np.uint8 and img.shape == (64, 64, 3)
    assert set(scene["eval_region"]) == {"xmin", "xmax", "ymin", "ymax"} and scene["seed"] == 0
    assert scene["radiance"]["refraction_color"] == pytest.approx(1 / 1.33**2)
    assert scene["versions"]["bpy"] == "5.0.1"
    # The refraction colour 1/n^2 darkens the wet render against the dry one (sRGB: about n^(-2/2.2)) where
    # the view is all water (the pixels whose dry depth lies below the water).
    cam = Camera.from_c2w_gl(frames[0]["transform_matrix"], tf["w"], tf["h"],
                             intrinsics=(tf["fl_x"], tf["fl_y"], tf["cx"], tf["cy"]))
    depth = read_depth(smoke / frames[0]["gt_depth_file_path"])
    j, i = np.indices(depth.shape)
    under = cam.unproject(np.stack([i.ravel() + 0.5, j.ravel() + 0.5], -1), depth.ravel())[:, 2] < -0.1
    wet = cv2.imread(str(smoke / frames[0]["file_path"])).reshape(-1, 3)[under].astype(float).mean()
    dry = cv2.imread(str(smoke / frames[0]["dry_file_path"])).reshape(-1, 3)[under].astype(float).mean()
    assert under.mean() > 0.3 and 0.65 < wet / dry < 0.85
    grid = np.load(smoke / "gt" / "bed_grid.npy")
    r = scene["eval_region"]
    assert grid.dtype == np.float64 and grid[:, 0].min() >= r["xmin"] and grid[:, 0].max() <= r["xmax"]


def test_colmap_model_matches_transforms(smoke):
    tf = json.loads((smoke / "transforms.json").read_text())
    folder = smoke / "colmap"
    cam_line = next(l for l in (folder / "cameras.txt").read_text().splitlines() if not l.startswith("#"))
    assert cam_line.split()[1:4] == ["PINHOLE", "64", "64"]
    rows = [l.split() for l in (folder / "images.txt").read_text().splitlines()
            if l and not l.startswith("#")]
    assert len(rows) == len(tf["frames"])
    for row, frame in zip(rows, tf["frames"]):
        w, x, y, z = map(float, row[1:5])
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        w2c = np.array(frame["w2c"])
        np.testing.assert_allclose(R, w2c[:3, :3], atol=1e-9)
        np.testing.assert_allclose(list(map(float, row[5:8])), w2c[:3, 3], atol=1e-9)
        assert row[9] == frame["file_path"].removeprefix("images/")
    for split in ("train", "test"):  # the split, as COLMAP image lists
        names = (folder / f"{split}.txt").read_text().split()
        assert names == [f["file_path"].removeprefix("images/") for f in tf["frames"] if f["split"] == split]


def test_files_read_by_users_tools(smoke):
    """OpenCV reads the depth EXR, nerfstudio finds its keys, rasterio reads the elevation raster."""
    import subprocess
    import sys

    tf = json.loads((smoke / "transforms.json").read_text())
    f = tf["frames"][0]
    # OpenCV reads EXR only when asked before import: in a child process
    code = ("import os, sys; os.environ['OPENCV_IO_ENABLE_OPENEXR'] = '1'; import cv2, numpy as np; "
            "d = cv2.imread(sys.argv[1], cv2.IMREAD_UNCHANGED); np.save(sys.argv[2], d)")
    subprocess.run([sys.executable, "-c", code, str(smoke / f["gt_depth_file_path"]), str(smoke / "cv.npy")],
                   check=True)
    via_cv = np.load(smoke / "cv.npy")
    (smoke / "cv.npy").unlink()
    np.testing.assert_array_equal(via_cv, read_depth(smoke / f["gt_depth_file_path"]))  # one file's float32s
    assert via_cv.max() > 0
    # nerfstudio: poses as they are, the split by file lists, no key nerfstudio would misread
    assert tf["applied_transform"] == np.eye(4)[:3].tolist() and tf["orientation_override"] == "none"
    assert tf["train_filenames"] == [f["file_path"] for f in tf["frames"] if f["split"] == "train"]
    assert tf["test_filenames"] == [f["file_path"] for f in tf["frames"] if f["split"] == "test"]
    assert (not any("depth_file_path" in f for f in tf["frames"])
            and not (smoke / "colmap" / "sparse").exists())
    # the elevation raster: local metric CRS, nodata outside the wet area, values = the wet grid
    import rasterio

    grid = np.load(smoke / "gt" / "bed_grid.npy")
    with rasterio.open(smoke / "gt" / "bed_elevation.tif") as r:
        band = r.read(1)
        wkt = r.crs.to_wkt()
        assert wkt.startswith("LOCAL_CS") and 'UNIT["metre",1' in wkt
        assert r.res == (0.05, 0.05) and r.nodata == -9999.0
        rows, cols = rasterio.transform.rowcol(r.transform, grid[:, 0], grid[:, 1])
        np.testing.assert_allclose(band[rows, cols], grid[:, 2], atol=1e-6)
        assert (band == r.nodata).sum() == band.size - len(grid)


def test_reach_ground_truth(smoke):
    scene = json.loads((smoke / "scene.json").read_text())
    assert scene["scene"] == "reach"
    nulls = scene["null_models"]
    assert nulls["max_depth_m"] == 2.0 and nulls["median_plane"]["f1_3%"] < 0.4
    wet, banks = np.load(smoke / "gt" / "bed_grid.npy"), np.load(smoke / "gt" / "bank_grid.npy")
    assert (wet[:, 2] < 0).all() and (banks[:, 2] >= 0).all() and len(banks) > 0
    line = json.loads((smoke / "gt" / "waterline.json").read_text())["geometry"]
    assert line["type"] == "MultiLineString" and len(line["coordinates"]) >= 2


def bed_height(mesh: trimesh.Trimesh, xy: np.ndarray) -> np.ndarray:
    """Height of the PLY mesh at xy [N, 2] by point-in-triangle search (independent of the grid code)."""
    tri = mesh.triangles  # [F, 3, 3]
    tree = cKDTree(tri[:, :, :2].mean(1))
    _, cand = tree.query(xy, k=8)
    a, b, c = (tri[cand, k, :2] for k in range(3))  # [N, 8, 2]
    v0, v1, v2 = b - a, c - a, xy[:, None] - a
    den = v0[..., 0] * v1[..., 1] - v1[..., 0] * v0[..., 1]
    s = (v2[..., 0] * v1[..., 1] - v1[..., 0] * v2[..., 1]) / den
    t = (v0[..., 0] * v2[..., 1] - v2[..., 0] * v0[..., 1]) / den
    inside = (s >= -1e-9) & (t >= -1e-9) & (s + t <= 1 + 1e-9)
    assert inside.any(1).all()
    k = inside.argmax(1)
    n = np.arange(len(xy))
    z = tri[cand[n, k]][..., 2]  # [N, 3]
    return z[:, 0] + s[n, k] * (z[:, 1] - z[:, 0]) + t[n, k] * (z[:, 2] - z[:, 0])


def test_dry_depth_unprojects_onto_the_bed_mesh(smoke):
    tf = json.loads((smoke / "transforms.json").read_text())
    mesh = trimesh.load(smoke / "gt" / "bed.ply", process=False)
    lo, hi = mesh.vertices[:, :2].min(0) + 0.1, mesh.vertices[:, :2].max(0) - 0.1
    worst, count = 0.0, 0
    for f in tf["frames"]:
        cam = Camera.from_c2w_gl(f["transform_matrix"], tf["w"], tf["h"],
                                 intrinsics=(tf["fl_x"], tf["fl_y"], tf["cx"], tf["cy"]))
        depth = read_depth(smoke / f["gt_depth_file_path"]).astype(np.float64)
        assert depth.shape == (tf["h"], tf["w"]) and np.all(depth > 0)
        j, i = np.nonzero(depth < NO_HIT)
        pts = cam.unproject(np.stack([i + 0.5, j + 0.5], -1), depth[j, i])
        on_bed = np.all((pts[:, :2] > lo) & (pts[:, :2] < hi), axis=1)  # the rest is the flat floor
        err = np.abs(pts[on_bed, 2] - bed_height(mesh, pts[on_bed, :2]))
        worst, count = max(worst, err.max()), count + on_bed.sum()
    print(f"\ndry depth -> bed mesh: {count} pixels, max vertical error {worst * 1e6:.1f} um")
    assert count > 10000 and worst < 0.01


def test_rerun_resumes_and_shards_merge(smoke, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(smoke, copy)
    before = {p: p.stat().st_mtime_ns for p in copy.rglob("*.png")}
    assert main(["generate", "--preset", "smoke", "--out", str(copy), "--quiet"]) == 0
    assert {p: p.stat().st_mtime_ns for p in copy.rglob("*.png")} == before  # nothing re-rendered
    original = (copy / "transforms.json").read_text()
    # Lose two views and the merged metadata (as after a kill); shard 0/2 owns view 2, shard 1/2 view 1.
    for name in ("0001", "0002"):
        for p in (copy / "images" / "wet" / f"{name}.png", copy / "images" / "dry" / f"{name}.png",
                  copy / "gt" / "depth" / f"{name}.exr"):
            p.unlink()
    (copy / "transforms.json").unlink()
    assert main(["generate", "--preset", "smoke", "--out", str(copy), "--shard", "0/2", "--quiet"]) == 0
    assert ((copy / "images" / "wet" / "0002.png").exists()
            and not (copy / "images" / "wet" / "0001.png").exists())
    assert not (copy / "transforms.json").exists()  # incomplete: no merge yet
    assert main(["generate", "--preset", "smoke", "--out", str(copy), "--shard", "1/2", "--quiet"]) == 0
    assert (copy / "transforms.json").read_text() == original
    for name in ("0001", "0002"):  # re-rendered bit-identically (same renderer, seed and machine as `smoke`)
        assert (copy / "images" / "wet" / f"{name}.png").read_bytes() == \
            (smoke / "images" / "wet" / f"{name}.png").read_bytes()
    assert not list(copy.rglob("*.tmp")) and not list(copy.rglob(".*.render"))


def test_rerun_renders_damaged_files_again(smoke, tmp_path, capsys):
    copy = tmp_path / "copy"
    shutil.copytree(smoke, copy)
    png, exr = copy / "images" / "wet" / "0003.png", copy / "gt" / "depth" / "0004.exr"
    png.write_bytes(png.read_bytes()[:100])  # truncated
    exr.write_bytes(b"\0" * exr.stat().st_size)  # same size, garbage: only the manifest's hash can tell
    assert main(["generate", "--preset", "smoke", "--out", str(copy), "--quiet"]) == 0
    assert "2 damaged files rendered again" in capsys.readouterr().out
    for p in (png, exr):  # the same renderer, seed and machine as `smoke`: the same bytes
        assert p.read_bytes() == (smoke / p.relative_to(copy)).read_bytes()
    manifest = json.loads((copy / "manifest.json").read_text())
    assert len(manifest) == 3 * len(json.loads((copy / "transforms.json").read_text())["frames"])


def test_refuses_foreign_or_mismatched_output(smoke, tmp_path, capsys):
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "keep.txt").write_text("mine")
    assert main(["generate", "--preset", "smoke", "--out", str(foreign)]) == 2
    assert [p.name for p in foreign.iterdir()] == ["keep.txt"]
    assert main(["generate", "--preset", "smoke", "--seed", "5", "--out", str(smoke)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(line.startswith("ragsplat generate: error:") for line in err)
    with pytest.raises(SystemExit) as bad_shard:  # argparse: usage and exit 2
        main(["generate", "--preset", "smoke", "--out", str(tmp_path / "x"), "--shard", "2/2"])
    assert bad_shard.value.code == 2


def test_dry_scene_renders_only_dry_passes(tmp_path):
    out = tmp_path / "dry"
    assert main(["generate", "--preset", "smoke", "--no-water", "--out", str(out), "--quiet"]) == 0
    assert not (out / "images" / "wet").exists()
    tf = json.loads((out / "transforms.json").read_text())
    assert tf["water"] is None and all(f["file_path"].startswith("images/dry/") for f in tf["frames"])
    assert json.loads((out / "scene.json").read_text())["passes"] == ["dry", "depth"]


def test_radiance_scale_switch(tmp_path):
    out = tmp_path / "bright"
    # One view (shard 0 of 17) is enough: without the 1/n^2 colour, wet and dry are about equally bright.
    assert main(["generate", "--preset", "smoke", "--no-radiance-scale", "--shard", "0/17", "--out", str(out),
                 "--quiet"]) == 0
    wet = cv2.imread(str(out / "images" / "wet" / "0000.png")).astype(float).mean()
    dry = cv2.imread(str(out / "images" / "dry" / "0000.png")).astype(float).mean()
    assert 0.95 < wet / dry < 1.05
    assert json.loads((out / "scene" / "spec.json").read_text())["water"]["radiance_scale"] is False


def test_sigint_keeps_only_whole_files_and_the_rerun_completes(smoke, tmp_path):
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "interrupted"
    # A shell's background job ignores SIGINT and children inherit that: the command gets Python's default
    start = ("import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
             "sys.argv[0] = 'ragsplat'; runpy.run_module('ragsplat.cli.main', run_name='__main__')")
    cmd = [sys.executable, "-c", start, "generate", "--preset", "smoke", "--out", str(out), "--quiet"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    # the first finished image: most of the render is still ahead (a later signal can miss a fast render)
    while not any(out.glob("images/*/*.png")) and time.time() < deadline and proc.poll() is None:
        time.sleep(0.01)
    proc.send_signal(signal.SIGINT)
    err = proc.communicate(timeout=120)[1].strip().splitlines()
    assert proc.returncode == 130 and len(err) == 1, err
    assert (err[0] == "ragsplat generate: interrupted; finished files are kept, rerun the same command to "
                      "resume")
    assert (not list(out.rglob("*.tmp")) and not list(out.rglob("*.render"))
            and not list(out.glob("scene/job.*")))
    assert main(["generate", "--preset", "smoke", "--out", str(out), "--quiet"]) == 0
    for p in out.glob("images/*/*.png"):
        assert p.read_bytes() == (smoke / p.relative_to(out)).read_bytes()


def test_a_killed_renderer_and_a_full_disk_are_one_line_and_the_rerun_completes(smoke, tmp_path,
                                                                                 monkeypatch, capsys):
    import os
    import subprocess
    import sys

    from ragsplat import outputs
    from ragsplat.datagen import build

    out = tmp_path / "data"
    argv = ["generate", "--preset", "smoke", "--out", str(out), "--quiet"]
    real_popen = subprocess.Popen

    def oom_killed(cmd, **kw):  # the Blender child dies as the kernel's OOM killer would kill it
        return real_popen([sys.executable, "-c",
                           "import os, signal; os.kill(os.getpid(), signal.SIGKILL)"], **kw)

    monkeypatch.setattr(build.subprocess, "Popen", oom_killed)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert (len(err) == 1 and "killed by signal 9 (out of memory?)" in err[0]
            and "rerun to resume" in err[0]), err
    assert not list(out.rglob("*.tmp")) and not list(out.glob("scene/job.*"))
    monkeypatch.undo()

    # a crash (SIGSEGV) is retried once by a new renderer; a second crash is reported as the kill above
    starts = []

    def crashes(times):
        def popen(cmd, **kw):
            if "ragsplat.blender_scenes.render" not in cmd:  # git, for the metadata's versions
                return real_popen(cmd, **kw)
            starts.append(cmd)
            if len(starts) <= times:
                cmd = [sys.executable, "-c", "import os, signal; os.kill(os.getpid(), signal.SIGSEGV)"]
            return real_popen(cmd, **kw)
        return popen

    monkeypatch.setattr(build.subprocess, "Popen", crashes(2))
    assert main(argv) == 2 and len(starts) == 2
    said = capsys.readouterr()
    assert "killed by signal 11" in said.err and len(said.err.strip().splitlines()) == 1, said.err
    assert "the renderer crashed (signal 11, see " in said.out, said.out  # the retry, told once
    starts.clear()
    monkeypatch.setattr(build.subprocess, "Popen", crashes(1))
    assert main(argv) == 0 and len(starts) == 4  # a crash, its retry, the lens photos', the ortho truth
    assert capsys.readouterr().out.count("the renderer crashed (signal 11") == 1
    assert (out / "manifest.json").is_file()
    shutil.rmtree(out)
    monkeypatch.undo()

    real_replace = os.replace

    def disk_full(src, dst):  # the disk fills when the metadata is written, after every image
        if str(dst).endswith("transforms.json"):
            raise OSError(28, "No space left on device", str(dst))
        real_replace(src, dst)

    monkeypatch.setattr(outputs.os, "replace", disk_full)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "transforms.json: No space left on device" in err[0], err
    assert not list(out.rglob("*.tmp")) and not (out / "transforms.json").exists()
    monkeypatch.undo()
    # what a SIGKILL mid-write leaves (no handler runs): a rerun ignores such stale temporaries
    (out / "images" / "wet" / ".0000.png.99999.tmp").write_bytes(b"half a PNG")
    (out / ".transforms.json.99999.tmp").write_bytes(b"{")
    assert main(argv) == 0  # the rerun skips the finished images and completes
    for p in out.glob("images/*/*.png"):
        assert p.read_bytes() == (smoke / p.relative_to(out)).read_bytes()


def test_a_rerun_that_renders_nothing_keeps_the_fingerprint(smoke, tmp_path, capsys):
    from ragsplat.dataset.layout import fingerprint

    out = tmp_path / "copy"
    shutil.copytree(smoke, out)
    scene = json.loads((out / "scene.json").read_text())
    scene["versions"]["git_commit"] = "an older commit"  # rendered by another version of the code
    (out / "scene.json").write_text(json.dumps(scene, indent=2) + "\n")
    before = fingerprint(out)
    assert main(["generate", "--preset", "smoke", "--out", str(out), "--quiet"]) == 0
    assert "nothing to render" in capsys.readouterr().out
    assert fingerprint(out) == before  # the rows keyed on it stay valid
    assert json.loads((out / "scene.json").read_text())["versions"]["git_commit"] == "an older commit"


def test_smoke_long_renders_a_survey_along_the_reach(tmp_path):
    """The strips flight over a sloping reach, without the lens photos (`RenderSpec.lens`): complete, and its
    survey holds the training photos, the edge along both banks and no images-lens/ (about 20 s)."""
    out = tmp_path / "smoke-long"
    assert main(["generate", "--preset", "smoke-long", "--out", str(out), "--quiet"]) == 0
    tf = json.loads((out / "transforms.json").read_text())
    scene = json.loads((out / "scene.json").read_text())
    train = [f for f in tf["frames"] if f["split"] == "train"]
    assert len(train) == scene["flight"]["train_views"] == 72 and tf["water"]["slope"] == [-0.003, 0.0]
    x = np.array([np.linalg.inv(f["w2c"])[0, 3] for f in train])
    r = scene["eval_region"]
    assert x.min() < r["xmin"] / 2 and x.max() > r["xmax"] / 2  # photos along the whole reach
    survey = out / "survey"
    assert not (out / "images" / "lens").exists() and not (survey / "images-lens").exists()
    assert (len(list((survey / "images").glob("*.jpg"))) == len(list((survey / "images-gps").glob("*.jpg")))
            == 72)
    assert "survey/images-lens" not in json.loads((survey / "survey.json").read_text())["geo"]
    edge = np.loadtxt(survey / "water_edge.csv", delimiter=",", skiprows=1)
    assert len(edge) == 30 and (edge[:, 1] < 0).sum() == 15  # 15 a bank


def test_a_stretch_is_a_small_dataset_that_the_whole_one_resumes_from(tmp_path, capsys):
    """`--stretch X0 X1`: the wet training photos within half a footprint of the core, their survey, the
    truth cut to the core (scored by `ragsplat score`: the truth's own points score 100 % with full cover);
    the whole dataset later renders only what the stretch left (about 30 s)."""
    from ragsplat.datagen import flight
    from ragsplat.datagen.spec import preset

    out = tmp_path / "smoke-long"
    argv = ["generate", "--preset", "smoke-long", "--out", str(out), "--quiet"]
    assert main([*argv, "--stretch", "5", "100"]) == 2 and not out.exists()  # beyond the evaluated reach
    assert main([*argv, "--stretch", "-2", "2"]) == 0
    root = out / "stretch_-2_2"
    spec = preset("smoke-long")
    half = flight.footprint(spec)[0] / 2
    near = [p.name for p in flight.plan(spec)
            if p.split == "train" and -2 - half <= p.camera.camera_center[0] <= 2 + half]
    assert 0 < len(near) < 72
    assert sorted(p.stem for p in (out / "images" / "wet").glob("*.png")) == sorted(near)
    assert not (out / "transforms.json").exists()  # the dataset itself is not complete
    assert sorted(p.stem for p in (root / "survey" / "images").glob("*.jpg")) == sorted(near)
    scene = json.loads((root / "scene.json").read_text())
    assert (scene["eval_region"]["xmin"], scene["eval_region"]["xmax"]) == (-2, 2)
    grid = np.load(root / "gt" / "bed_grid.npy")
    assert grid[:, 0].min() >= -2 and grid[:, 0].max() < 2
    points = root / "truth.csv"
    np.savetxt(points, grid, delimiter=",", header="x,y,z", comments="")
    assert main(["score", str(points), "--truth", str(root), "--no-filter"]) == 0
    result = json.loads((root / "truth_score.json").read_text())
    assert result["geometry"]["f1"]["1%"] == 1.0 and result["geometry"]["survey"]["coverage"] == 1.0
    wet = {p.name: p.stat().st_mtime_ns for p in (out / "images" / "wet").glob("*.png")}
    capsys.readouterr()
    assert main(argv) == 0
    assert "complete" in capsys.readouterr().out
    assert all((out / "images" / "wet" / name).stat().st_mtime_ns == t for name, t in wet.items())


def test_the_orthographic_truth_lies_where_the_dry_photos_see_the_bed(smoke):
    from ragsplat.dataset import layout
    from ragsplat.dataset.load import load_dataset
    from ragsplat.eval.ortho import ortho_scores, read_truth
    from ragsplat.ortho import OrthoGrid, apparent_mosaic

    truth, step, west, north = read_truth(smoke)
    grid = OrthoGrid(west, north, step, truth.shape[1], truth.shape[0])
    region = json.loads((smoke / "scene.json").read_text())["eval_region"]
    assert west <= region["xmin"] < west + step and north - step < region["ymax"] <= north
    x, y = grid.centres()
    np.testing.assert_allclose(x / step, np.round(x / step), atol=1e-9)  # centres on the step's multiples
    xx, yy = np.meshgrid(x, y)
    heights = layout.Surface.load(smoke / layout.GT_SURFACE).height_at(np.column_stack([xx.ravel(),
                                                                                      yy.ravel()]))
    ds = load_dataset(smoke, splits=("train",))
    photos = [(v.camera, v.dry_rgb.numpy()) for v in ds.train if v.kind == "nadir"]
    mosaic = apparent_mosaic(photos, grid, heights.reshape(xx.shape), None)  # the dry photos, exact heights
    cells = mosaic[..., 3] > 0
    score = ortho_scores(mosaic[..., :3], truth, cells)
    print(f"\northographic truth against the dry nadir photos mosaicked: {score}")
    assert cells.mean() > 0.8 and np.abs(score["shift_cells"]).max() < 0.15 and score["psnr"] > 20
    # the mosaic drawn one cell east: the scorer finds it there
    moved = ortho_scores(np.roll(mosaic[..., :3], 1, axis=1), truth, cells & np.roll(cells, 1, axis=1))
    assert abs(moved["shift_cells"][0] - 1) < 0.25 and abs(moved["shift_cells"][1]) < 0.25

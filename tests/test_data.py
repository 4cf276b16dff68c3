import json

import numpy as np
import pytest
import torch

from ragsplat.bench.synthetic import ring_cameras, write_dataset
from ragsplat.camera import Camera
from ragsplat.dataset import load_dataset
from ragsplat.dataset.layout import read_png
from ragsplat.errors import DatasetError, RagsplatError
from ragsplat.water_surface import WaterSurface

W, H = 12, 8


def _views(n=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    down = np.diag([1.0, -1.0, -1.0])  # looking straight down from 5 m
    cams = [Camera.from_fov(W, H, 60.0, down, -down @ [0.1 * i, 0.0, 5.0]) for i in range(n)]
    return [{"camera": c, "image": torch.rand(H, W, 3, generator=g), "dry": torch.rand(H, W, 3, generator=g),
             "split": "test" if i == n - 1 else "train", "kind": "nadir"} for i, c in enumerate(cams)]


@pytest.fixture
def ds(tmp_path):
    views = _views()
    root = write_dataset(tmp_path / "ds", views, WaterSurface(-0.5, 1.33),
                         {"xmin": -1, "xmax": 1, "ymin": -2, "ymax": 2})
    return root, views


def _edit(root, fn):
    meta = json.loads((root / "transforms.json").read_text())
    fn(meta)
    (root / "transforms.json").write_text(json.dumps(meta))


def test_round_trip(ds):
    root, views = ds
    d = load_dataset(root)
    assert d.water == WaterSurface(-0.5, 1.33)
    assert [v.name for v in d.train] == ["0000", "0001", "0002"] and [v.name for v in d.test] == ["0003"]
    assert d.eval_region == {"xmin": -1.0, "xmax": 1.0, "ymin": -2.0, "ymax": 2.0}
    for got, want in zip(d.views, views):
        img = got.image
        assert img.dtype == torch.float32 and img.shape == (H, W, 3)
        assert float(img.min()) >= 0 and float(img.max()) <= 1
        # 8-bit quantisation: within half a step of what was written
        assert torch.allclose(img, want["image"], atol=0.5 / 255 + 1e-6)
        assert torch.allclose(got.dry, want["dry"], atol=0.5 / 255 + 1e-6)
        np.testing.assert_allclose(got.camera.w2c, want["camera"].w2c, atol=1e-12)
        np.testing.assert_allclose(got.camera.K, want["camera"].K)


def test_splits_and_no_dry(ds):
    root, _ = ds
    d = load_dataset(root, splits=("test",), load_dry=False)
    assert [v.split for v in d.views] == ["test"] and d.views[0].dry is None


def test_dry_only_scene(tmp_path):
    root = write_dataset(tmp_path / "dry", _views(2), None)
    d = load_dataset(root)
    assert d.water is None and d.views[0].file_path.startswith("images/dry/")


def test_camera_extent():
    cams = ring_cameras(6, 8, 10.0, 4.0)  # nadir at the centre + 6 on a radius-4 circle
    views = [{"camera": c, "image": torch.zeros(8, 8, 3)} for c in cams]
    from ragsplat.dataset import Dataset, View

    d = Dataset(None, None, [View(str(i), "train", "", v["camera"], torch.zeros(8, 8, 3, dtype=torch.uint8),
                                  None, "", None, None) for i, v in enumerate(views)])
    assert d.camera_extent() == pytest.approx(1.1 * 4.0, rel=1e-9)


def test_error_is_ragsplat_and_value_error():
    assert issubclass(DatasetError, RagsplatError) and issubclass(DatasetError, ValueError)


@pytest.mark.parametrize("edit, match", [
    (lambda m: m.pop("fl_x"), "'fl_x' must be a finite number"),
    (lambda m: m.update(camera_model="OPENCV_FISHEYE"), "not supported"),
    (lambda m: m.update(k1=0.1), "distortion"),
    (lambda m: m.pop("water"), "missing 'water'"),
    (lambda m: m.update(water={"level": 0.0, "n": 0.5}), "refractive index"),
    (lambda m: m.update(frames=[]), "non-empty list"),
    (lambda m: m["frames"][1].update(split="val"), r"frames\[1\].split"),
    (lambda m: m["frames"][2].update(name="0000"), "duplicate"),
    (lambda m: m["frames"][0].pop("file_path"), "no 'file_path'"),
    (lambda m: m["frames"][0]["w2c"][0].__setitem__(3, 9.0), "different poses"),
    (lambda m: m["frames"][0].update(w2c=[[1, 0], [0, 1]]), "4x4"),
    (lambda m: [f.pop(k) for f in m["frames"] for k in ("w2c", "transform_matrix")], "neither"),
    (lambda m: m["frames"][1].update(file_path="images/wet/nope.png"), "image file is missing"),
    (lambda m: m.update(w=13), "image is 12 x 8"),
    (lambda m: [f.update(split="test") for f in m["frames"]], "no frame has split 'train'"),
    (lambda m: m.update(water={"level": 6.0, "n": 1.33}),
     r"frames\[0\] \(0000\): camera centre z = 5 is not above"),
])
def test_bad_transforms_one_line(ds, edit, match):
    root, _ = ds
    _edit(root, edit)
    with pytest.raises(DatasetError, match=match) as err:
        load_dataset(root)
    assert "\n" not in str(err.value) and str(root) in str(err.value)


def test_missing_and_broken_files(ds, tmp_path):
    root, _ = ds
    with pytest.raises(DatasetError, match="does not exist"):
        load_dataset(tmp_path / "nowhere")
    (root / "images/wet/0001.png").write_bytes(b"not a png")
    with pytest.raises(DatasetError, match="not a readable image"):
        load_dataset(root)
    (root / "transforms.json").write_text("{broken")
    with pytest.raises(DatasetError, match="not valid JSON"):
        load_dataset(root)
    (root / "transforms.json").unlink()
    with pytest.raises(DatasetError, match="transforms.json: file is missing"):
        load_dataset(root)


def test_bad_eval_region(ds):
    root, _ = ds
    (root / "scene.json").write_text(json.dumps(
        {"eval_region": {"xmin": 1, "xmax": 0, "ymin": 0, "ymax": 1}}))
    with pytest.raises(DatasetError, match="eval_region is empty"):
        load_dataset(root)


def test_read_png_grey_and_alpha(tmp_path):
    import cv2

    grey = (np.arange(12, dtype=np.uint8).reshape(3, 4) * 20)
    cv2.imwrite(str(tmp_path / "g.png"), grey)
    img = read_png(tmp_path / "g.png")
    assert img.shape == (3, 4, 3) and np.array_equal(img[..., 1], grey)
    bgra = np.zeros((2, 2, 4), np.uint8)
    bgra[..., 0] = 200  # blue in OpenCV's order
    cv2.imwrite(str(tmp_path / "a.png"), bgra)
    assert read_png(tmp_path / "a.png")[0, 0].tolist() == [0, 0, 200]
    cv2.imwrite(str(tmp_path / "d.png"), np.zeros((2, 2, 3), np.uint16))
    with pytest.raises(ValueError, match="8-bit"):
        read_png(tmp_path / "d.png")


def test_per_frame_intrinsics(ds):
    """nerfstudio lets every frame carry its own intrinsics; a frame's own value wins over the file's."""
    root, views = ds

    def per_frame(meta):
        for i, f in enumerate(meta["frames"]):
            f.update({k: meta[k] for k in ("fl_x", "fl_y", "cx", "cy", "w", "h")}, fl_x=meta["fl_x"] + i)
        for k in ("fl_x", "fl_y", "cx", "cy"):
            meta.pop(k)
        meta["frames"][0]["transform_matrix"] = views[0]["camera"].c2w_gl.tolist()
        meta["frames"][0].pop("w2c")  # w2c carries no intrinsics: the pose must come from either form

    _edit(root, per_frame)
    d = load_dataset(root)
    assert [v.camera.fx for v in d.views] == [views[0]["camera"].fx + i for i in range(len(views))]

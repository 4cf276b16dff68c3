"""Load a dataset directory (the data contract in the README) into cameras, image tensors and splits.

Every problem with the files on disk raises `DatasetError`: one line naming the file and what is wrong.
`DatasetError` is both a `UsageError` (the CLI prints it and exits 2) and a `ValueError`.

Images are kept as uint8 tensors (a quarter of the memory of float32 at the paper's size) and converted
to float32 in [0, 1] on access (`View.image`, `View.dry`); no colour-space conversion is applied: the
training target is the sRGB image itself, as in 3DGS.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

from ragsplat_core.camera import Camera
from ragsplat_core.cli import UsageError
from ragsplat_core.refraction import WaterSurface

SPLITS = ("train", "test")
_POSE_TOL = 1e-4  # w2c and transform_matrix must describe the same pose (metres / unitless rotation)
_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


class DatasetError(UsageError, ValueError):
    """A missing, unreadable or inconsistent dataset file (one line)."""


@dataclass(eq=False)
class View:
    """One camera pose with its training image and, when the dataset has one, its dry image."""

    name: str
    split: str
    kind: str
    camera: Camera
    rgb: torch.Tensor  # [H, W, 3] uint8, the training input (with water if the scene has water)
    dry_rgb: torch.Tensor | None  # [H, W, 3] uint8, the render without water, or None
    file_path: str
    dry_file_path: str | None
    depth_file_path: str | None

    @property
    def image(self) -> torch.Tensor:  # [H, W, 3] float32 in [0, 1]
        return self.rgb.to(torch.float32) / 255.0

    @property
    def dry(self) -> torch.Tensor | None:  # [H, W, 3] float32 in [0, 1]
        return None if self.dry_rgb is None else self.dry_rgb.to(torch.float32) / 255.0


@dataclass(eq=False)
class Dataset:
    root: Path
    water: WaterSurface | None  # None: a dry-only scene (trained as plain 3DGS)
    views: list[View]
    scene: dict | None = None  # scene.json, when present
    eval_region: dict | None = None  # {"xmin", "xmax", "ymin", "ymax"} from scene.json
    transforms: dict = field(default_factory=dict)  # the raw transforms.json

    def split(self, name: str) -> list[View]:
        if name not in SPLITS:
            raise ValueError(f"unknown split {name!r}, expected one of {SPLITS}")
        return [v for v in self.views if v.split == name]

    @property
    def train(self) -> list[View]:
        return self.split("train")

    @property
    def test(self) -> list[View]:
        return self.split("test")

    def camera_extent(self) -> float:
        """3DGS's `cameras_extent`: 1.1 x the largest distance of a training camera from their mean centre.

        Scales the position learning rate and the densification thresholds (never below 1e-3 m, so a single
        camera still gives a usable scale).
        """
        centres = np.stack([v.camera.camera_center for v in self.train])  # [V, 3]
        radius = np.linalg.norm(centres - centres.mean(0), axis=1).max()
        return max(1.1 * float(radius), 1e-3)


def _fail(path: Path, what: str) -> DatasetError:
    return DatasetError(f"{path}: {what}")


def read_png(path: Path, width: int | None = None, height: int | None = None) -> torch.Tensor:
    """An 8-bit RGB(A) or grey PNG -> [H, W, 3] uint8 tensor (alpha dropped); checks the size if given."""
    if not path.is_file():
        raise _fail(path, "image file is missing")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise _fail(path, "not a readable image")
    if img.dtype != np.uint8:
        raise _fail(path, f"expected an 8-bit image, got {img.dtype}")
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    elif img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    else:
        raise _fail(path, f"unsupported channel count {img.shape[2]}")
    if width is not None and (img.shape[1], img.shape[0]) != (width, height):
        raise _fail(path, f"image is {img.shape[1]} x {img.shape[0]}, transforms.json says {width} x {height}")
    return torch.from_numpy(np.ascontiguousarray(img))


def write_png(path: Path, image: torch.Tensor) -> None:
    """[H, W, 3] float in [0, 1] (or uint8) -> 8-bit PNG, rounding to nearest; parent folders are created."""
    arr = image.detach().cpu()
    if arr.dtype != torch.uint8:
        arr = (arr.clamp(0, 1) * 255 + 0.5).to(torch.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), cv2.cvtColor(arr.numpy(), cv2.COLOR_RGB2BGR)):
        raise OSError(f"{path}: could not write PNG")


def _read_json(path: Path) -> dict:
    if not path.is_file():
        raise _fail(path, "file is missing")
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise _fail(path, f"not valid JSON ({err})") from None
    if not isinstance(data, dict):
        raise _fail(path, "expected a JSON object at the top level")
    return data


def _number(src: dict, key: str, path: Path, where: str = "") -> float:
    value = src.get(key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise _fail(path, f"{where}'{key}' must be a finite number, got {value!r}")
    return float(value)


def _matrix(value, path: Path, where: str) -> np.ndarray:
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        m = np.zeros(0)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise _fail(path, f"{where} must be a finite 4x4 matrix")
    return m


def _water(meta: dict, path: Path) -> WaterSurface | None:
    if "water" not in meta:
        raise _fail(path, "missing 'water' (an object {level, n}, or null for a dry-only scene)")
    spec = meta["water"]
    if spec is None:
        return None
    if not isinstance(spec, dict):
        raise _fail(path, f"'water' must be an object {{level, n}} or null, got {spec!r}")
    try:
        return WaterSurface(_number(spec, "level", path, "water."), _number(spec, "n", path, "water."))
    except ValueError as err:
        if isinstance(err, DatasetError):
            raise
        raise _fail(path, str(err)) from None


def _camera(frame: dict, intr: tuple, size: tuple[int, int], path: Path, where: str) -> Camera:
    """From `w2c` (OpenCV) when present, else `transform_matrix`; when both are there they must agree."""
    w, h = size
    try:
        cams = []
        if "transform_matrix" in frame:
            cams.append(Camera.from_c2w_gl(_matrix(frame["transform_matrix"], path, f"{where}.transform_matrix"),
                                           w, h, intrinsics=intr))
        if "w2c" in frame:
            m = _matrix(frame["w2c"], path, f"{where}.w2c")
            if np.abs(m[3] - [0, 0, 0, 1]).max() > _POSE_TOL:
                raise _fail(path, f"{where}.w2c last row must be [0, 0, 0, 1]")
            cams.append(Camera(w, h, *intr, m[:3, :3], m[:3, 3]))
    except ValueError as err:
        if isinstance(err, DatasetError):
            raise
        raise _fail(path, f"{where}: {err}") from None
    if not cams:
        raise _fail(path, f"{where} has neither 'w2c' nor 'transform_matrix'")
    if len(cams) == 2 and np.abs(cams[0].w2c - cams[1].w2c).max() > _POSE_TOL:
        raise _fail(path, f"{where}: 'w2c' and 'transform_matrix' describe different poses")
    return cams[-1]


def load_dataset(root: str | Path, splits: tuple[str, ...] = SPLITS, load_dry: bool = True) -> Dataset:
    """Read `root/transforms.json` (+ `scene.json` if present) and the images of the chosen splits.

    `load_dry=False` skips the dry images (training reads only the wet ones). Raises DatasetError.
    """
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset directory does not exist")
    tpath = root / "transforms.json"
    meta = _read_json(tpath)
    model = meta.get("camera_model", "OPENCV")
    if model not in ("OPENCV", "PINHOLE"):
        raise _fail(tpath, f"camera_model {model!r} is not supported (pinhole OPENCV only)")
    for key in _DISTORTION_KEYS:
        if key in meta and _number(meta, key, tpath) != 0.0:
            raise _fail(tpath, f"lens distortion '{key}' = {meta[key]} is not supported")
    intr = tuple(_number(meta, k, tpath) for k in ("fl_x", "fl_y", "cx", "cy"))
    w, h = _number(meta, "w", tpath), _number(meta, "h", tpath)
    if w != int(w) or h != int(h) or w < 1 or h < 1:
        raise _fail(tpath, f"image size must be positive integers, got w={w}, h={h}")
    size = (int(w), int(h))
    water = _water(meta, tpath)
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise _fail(tpath, "'frames' must be a non-empty list")
    for s in splits:
        if s not in SPLITS:
            raise ValueError(f"unknown split {s!r}, expected one of {SPLITS}")

    views, names = [], set()
    for i, frame in enumerate(frames):
        where = f"frames[{i}]"
        if not isinstance(frame, dict):
            raise _fail(tpath, f"{where} must be an object")
        split = frame.get("split", "train")
        if split not in SPLITS:
            raise _fail(tpath, f"{where}.split is {split!r}, expected one of {SPLITS}")
        name = str(frame.get("name", i))
        if name in names:
            raise _fail(tpath, f"{where}: duplicate frame name {name!r}")
        names.add(name)
        if "file_path" not in frame:
            raise _fail(tpath, f"{where} has no 'file_path'")
        camera = _camera(frame, intr, size, tpath, where)
        if split not in splits:
            continue
        rgb = read_png(root / frame["file_path"], *size)
        dry_path = frame.get("dry_file_path")
        dry = read_png(root / dry_path, *size) if (load_dry and dry_path) else None
        views.append(View(name, split, str(frame.get("kind", "")), camera, rgb, dry, frame["file_path"],
                          dry_path, frame.get("depth_file_path")))
    if "train" in splits and not any(v.split == "train" for v in views):
        raise _fail(tpath, "no frame has split 'train'")

    scene, region = None, None
    if (root / "scene.json").exists():
        scene = _read_json(root / "scene.json")
        if "eval_region" in scene:
            region = scene["eval_region"]
            if not isinstance(region, dict):
                raise _fail(root / "scene.json", "'eval_region' must be an object {xmin, xmax, ymin, ymax}")
            region = {k: _number(region, k, root / "scene.json", "eval_region.") for k in
                      ("xmin", "xmax", "ymin", "ymax")}
            if region["xmin"] >= region["xmax"] or region["ymin"] >= region["ymax"]:
                raise _fail(root / "scene.json", f"eval_region is empty: {region}")
    return Dataset(root, water, views, scene, region, meta)

"""Read a dataset directory (the data contract of `layout`) into cameras, image tensors, bed info and
ground truth.

Every problem with the files on disk raises `DatasetError`: one line naming the file and what is wrong.

Images are kept as uint8 tensors (a quarter of the memory of float32 at the paper's size) and converted
to float32 in [0, 1] on access (`View.image`, `View.dry`); no colour-space conversion is applied: the
training target is the sRGB image itself, as in 3DGS.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ragsplat.camera import Camera, ground_sample_distance
from ragsplat.dataset import layout
from ragsplat.errors import ConfigError, DatasetError
from ragsplat.water_surface import WaterSurface

SPLITS = ("train", "test")
_POSE_TOL = 1e-4  # w2c and transform_matrix must describe the same pose (metres / unitless rotation)
_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")


@dataclass(frozen=True)
class BedInfo:
    """What the generator says about the bed (scene.json `spec.bed`); None where it does not say."""

    depth: float | None = None  # mean depth below the water level (m)
    size: float | None = None  # side of the square bed centred on the origin (m)


@dataclass(eq=False)
class GroundTruth:
    """The exact bed for scoring geometry."""

    grid: np.ndarray  # [N, 3] float64 submerged bed points on a regular horizontal grid over `region`
    region: dict[str, float]  # {"xmin", "xmax", "ymin", "ymax"}: the evaluated part of the bed
    max_depth: float  # metres below the water surface: what the scale-free thresholds (1 %, 3 %) refer to
    water: WaterSurface  # the surface depths are measured from (a dry scene: the plane z = 0, n = 1)
    banks: np.ndarray | None = None  # [M, 3] emerged ground on the same grid (a reach), or None
    surface: layout.Surface | None = None  # the exact height function (gt/bed_surface.npz), when present

    @property
    def nodes(self) -> np.ndarray:  # [N + M, 3] every ground-truth node: the submerged bed, then the banks
        return self.grid if self.banks is None else np.concatenate([self.grid, self.banks])


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
    gt_depth_file_path: str | None  # dry z-depth EXR (metres), ground truth
    # [H, W] bool, True where the pixel counts in the loss; None: every pixel
    mask: torch.Tensor | None = None

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
    bed: BedInfo = field(default_factory=BedInfo)
    eval_region: dict[str, float] | None = None  # {"xmin", "xmax", "ymin", "ymax"} from scene.json
    ground_truth: GroundTruth | None = None  # loaded on request (`load_dataset(ground_truth=True)`)
    fingerprint: str | None = None  # `layout.fingerprint` of the directory it was read from
    georef: layout.Georef = field(default_factory=layout.Georef)  # the frame's CRS and offset (outputs)
    # metres per pixel at the water surface, of every training frame's camera (loaded or not):
    # `camera.ground_sample_distance`; None for a dry scene
    gsd: float | None = None
    # every training frame's camera, loaded or not (a finished run's views: `ragsplat.uncertainty`)
    train_cameras: list[Camera] = field(default_factory=list)

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


def _read_sized(path: Path, width: int, height: int, what: str) -> np.ndarray:
    """[H, W, 3] uint8 of an 8-bit image `what` ("image", "mask") whose size must be width x height."""
    if not path.is_file():
        raise _fail(path, f"{what} file is missing")
    try:
        img = layout.read_png(path)
    except ValueError as err:
        raise DatasetError(str(err)) from None
    if (img.shape[1], img.shape[0]) != (width, height):
        raise _fail(path,
                    f"{what} is {img.shape[1]} x {img.shape[0]}, transforms.json says {width} x {height}")
    return img


def read_image(path: Path, width: int, height: int) -> torch.Tensor:
    """[H, W, 3] uint8 tensor of an 8-bit PNG whose size must be width x height."""
    return torch.from_numpy(_read_sized(path, width, height, "image"))


def read_mask(path: Path, width: int, height: int) -> torch.Tensor:
    """[H, W] bool of a mask image (nerfstudio's `mask_path`): True where the pixel is non-zero (used)."""
    used = torch.from_numpy(_read_sized(path, width, height, "mask").max(axis=2) > 0)
    if not used.any():
        raise _fail(path, "mask excludes every pixel")
    return used


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
    slope = spec.get("slope", [0.0, 0.0])
    if not (isinstance(slope, list) and len(slope) == 2):
        raise _fail(path, f"'water.slope' must be [dz/dx, dz/dy], got {slope!r}")
    profile = spec.get("profile")
    if profile is not None and not (isinstance(profile, dict) and all(
            isinstance(profile.get(k), list) for k in ("origin", "direction", "stations", "offsets"))):
        raise _fail(path, "'water.profile' must be an object {origin, direction, stations, offsets} of lists")
    try:
        return WaterSurface(_number(spec, "level", path, "water."), _number(spec, "n", path, "water."),
                            tuple(_number(dict(enumerate(slope)), i, path, "water.slope ") for i in range(2)),
                            profile)
    except ValueError as err:
        if isinstance(err, DatasetError):
            raise
        raise _fail(path, str(err)) from None


_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", *_DISTORTION_KEYS)


def _intrinsics(meta: dict, frame: dict, path: Path, where: str) -> tuple[tuple, tuple[int, int]]:
    """((fx, fy, cx, cy), (w, h)) of one frame: its own keys, else the file's (nerfstudio allows both)."""
    src = {k: v for d in (meta, frame) for k, v in d.items() if k in _INTRINSIC_KEYS}
    for key in _DISTORTION_KEYS:
        if key in src and _number(src, key, path) != 0.0:
            raise _fail(path, f"lens distortion '{key}' = {src[key]} is not supported ({where})")
    missing = [k for k in ("fl_x", "fl_y", "cx", "cy", "w", "h") if k not in src]
    if missing:
        raise _fail(path,
                    f"'{missing[0]}' must be a finite number, given for the file or for {where}; got none")
    intr = tuple(_number(src, k, path) for k in ("fl_x", "fl_y", "cx", "cy"))
    w, h = _number(src, "w", path), _number(src, "h", path)
    if w != int(w) or h != int(h) or w < 1 or h < 1:
        raise _fail(path, f"image size must be positive integers, got w={w}, h={h} ({where})")
    return intr, (int(w), int(h))


def _camera(frame: dict, intr: tuple, size: tuple[int, int], path: Path, where: str) -> Camera:
    """From `w2c` (OpenCV) when present, else `transform_matrix`; when both are there they must agree."""
    w, h = size
    try:
        cams = []
        if "transform_matrix" in frame:
            cams.append(Camera.from_c2w_gl(
                _matrix(frame["transform_matrix"], path, f"{where}.transform_matrix"), w, h, intrinsics=intr))
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


def load_dataset(root: str | Path, splits: tuple[str, ...] = SPLITS, load_dry: bool = True,
                 ground_truth: bool = False) -> Dataset:
    """Read `root/transforms.json` (+ `scene.json` if present) and the images of the chosen splits.

    `load_dry=False` skips the dry images (training reads only the wet ones); `ground_truth=True` also
    loads the ground-truth bed grid and requires it. Raises DatasetError.
    """
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: dataset directory does not exist")
    tpath = root / layout.TRANSFORMS
    meta = _read_json(tpath)
    model = meta.get("camera_model", "OPENCV")
    if model not in ("OPENCV", "PINHOLE"):
        raise _fail(tpath, f"camera_model {model!r} is not supported (pinhole OPENCV only)")
    water = _water(meta, tpath)
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise _fail(tpath, "'frames' must be a non-empty list")
    for s in splits:
        if s not in SPLITS:
            raise ValueError(f"unknown split {s!r}, expected one of {SPLITS}")

    views, names, train_cameras = [], set(), []
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
        intr, size = _intrinsics(meta, frame, tpath, where)
        camera = _camera(frame, intr, size, tpath, where)
        if water is not None and not water.depth(camera.camera_center) < 0:
            raise _fail(tpath, f"{where} ({name}): camera centre z = {camera.camera_center[2]:g} is not "
                               f"above the water surface ({water.height(camera.camera_center[:2]):g} there); "
                               f"refraction needs the camera in air")
        if split == "train":
            train_cameras.append(camera)
        if split not in splits:
            continue
        rgb = read_image(root / frame["file_path"], *size)
        dry_path = frame.get("dry_file_path")
        dry = read_image(root / dry_path, *size) if (load_dry and dry_path) else None
        mask = read_mask(root / frame["mask_path"], *size) if frame.get("mask_path") else None
        views.append(View(name, split, str(frame.get("kind", "")), camera, rgb, dry, frame["file_path"],
                          dry_path, frame.get("gt_depth_file_path"), mask))
    if "train" in splits and not any(v.split == "train" for v in views):
        raise _fail(tpath, "no frame has split 'train'")

    bed, region = BedInfo(), None
    spath = root / layout.SCENE
    if spath.exists():
        scene = _read_json(spath)
        spec = scene.get("spec")
        spec_bed = spec.get("bed") if isinstance(spec, dict) else None
        if isinstance(spec_bed, dict):
            bed = BedInfo(depth=_positive(spec_bed.get("depth")), size=_positive(spec_bed.get("size")))
        if "eval_region" in scene:
            region = scene["eval_region"]
            if not isinstance(region, dict):
                raise _fail(spath, "'eval_region' must be an object {xmin, xmax, ymin, ymax}")
            region = {k: _number(region, k, spath, "eval_region.") for k in ("xmin", "xmax", "ymin", "ymax")}
            if region["xmin"] >= region["xmax"] or region["ymin"] >= region["ymax"]:
                raise _fail(spath, f"eval_region is empty: {region}")
    truth = _ground_truth(root, region, water, scene if spath.exists() else {}) if ground_truth else None
    # at the surface's height under the cameras' middle (a river's slope changes it by a few per mille)
    gsd = None if water is None else ground_sample_distance(train_cameras, float(water.height(
        np.median([c.camera_center[:2] for c in train_cameras], axis=0)))) if train_cameras else None
    return Dataset(root, water, views, bed, region, truth, layout.fingerprint(root), _georef(meta, tpath),
                   gsd, train_cameras)


def _georef(meta: dict, path: Path) -> layout.Georef:
    spec = meta.get("georef")
    if spec is None:
        return layout.Georef()
    offset = spec.get("offset") if isinstance(spec, dict) else None
    if not (isinstance(offset, list) and len(offset) == 3):
        raise _fail(path, "'georef' must be an object {offset: [x0, y0, z0], crs}")
    offset = tuple(_number(dict(enumerate(offset)), i, path, "georef.offset ") for i in range(3))
    try:
        return layout.Georef(offset, str(spec.get("crs", layout.LOCAL_CRS)))
    except ConfigError as err:
        raise _fail(path, str(err)) from None


def _positive(value) -> float | None:
    ok = (isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
          and value > 0)
    return float(value) if ok else None


def _ground_truth(root: Path, region: dict | None, water, scene: dict) -> GroundTruth:
    if region is None:
        raise _fail(root / layout.SCENE, "no eval_region (the ground truth needs one)")
    path = root / layout.GT_GRID
    if not path.is_file():
        raise _fail(path, "ground-truth bed grid is missing")
    grid = _grid(path)
    water = water if water is not None else WaterSurface(0.0, 1.0)
    nulls = scene.get("null_models")
    depth = _positive(nulls.get("max_depth_m")) if isinstance(nulls, dict) else None
    banks = _grid(root / layout.GT_BANKS) if (root / layout.GT_BANKS).is_file() else None
    spath = root / layout.GT_SURFACE
    try:
        surface = layout.Surface.load(spath) if spath.is_file() else None
    except (OSError, ValueError, KeyError) as err:
        raise _fail(spath, f"not a readable bed surface ({err})") from None
    return GroundTruth(grid, region, depth or float(water.depth(grid).max()), water, banks, surface)


def _grid(path: Path) -> np.ndarray:
    """A ground-truth point grid [N, 3] from a .npy file (DatasetError when it is not one)."""
    try:
        grid = np.load(path)
    except (OSError, ValueError) as err:
        raise _fail(path, f"not a readable .npy array ({err})") from None
    if grid.ndim != 2 or grid.shape[1] != 3 or len(grid) == 0 or not np.isfinite(grid).all():
        raise _fail(path, f"expected a non-empty finite float array [N, 3], got shape {grid.shape}")
    return grid

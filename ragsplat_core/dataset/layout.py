"""The dataset directory: paths, file formats and the builders of its two JSON files (the data contract).

DIR/
  transforms.json            nerfstudio-readable cameras + frames (`transforms_json`, `frame`)
  scene.json                 the generator's spec, eval_region and figures (`scene_json`)
  images/wet/NNNN.png        with-water render (8-bit sRGB): the training input (absent for a dry scene)
  images/dry/NNNN.png        the same pose without water
  gt/depth/NNNN.exr          dry z-depth in metres along the optical axis: one float32 channel "Z",
                             pixel centres exact (pixel filter 0.01 px); 1e10 where no surface was hit
  gt/bed.ply                 the exact bed mesh (double vertices, world metres)
  gt/bed_grid.npy            float64 [N, 3] bed points on a 5 cm horizontal grid over eval_region
  colmap/sparse/0/           COLMAP text model: cameras.txt (one PINHOLE), images.txt, empty points3D.txt
  scene/                     generator inputs and state: spec.json, geometry.npz, albedo.png, render log

Every writer of a dataset (the Blender generator in `datagen`, the small in-memory scenes of
`ragsplat_core.bench.synthetic`) writes through this module and every reader reads through
`ragsplat_core.dataset.load`. numpy and OpenCV only, no torch: Blender's process imports it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ragsplat_core.outputs import atomic_path, write_bytes

TRANSFORMS = "transforms.json"
SCENE = "scene.json"
GT_MESH = "gt/bed.ply"
GT_GRID = "gt/bed_grid.npy"
GT_GRID_STEP = 0.05  # metres between ground-truth grid points
COLMAP = "colmap/sparse/0"
PASSES = ("wet", "dry", "depth")
DEPTH_CHANNEL = "Z"
NO_HIT = 1e10  # Cycles' depth where a ray escapes; far beyond any scene distance


def relative_path(kind: str, name: str) -> str:
    """Where pass `kind` ("wet" | "dry" | "depth") of view `name` lives, relative to the dataset root."""
    return f"gt/depth/{name}.exr" if kind == "depth" else f"images/{kind}/{name}.png"


def output_path(root: Path, kind: str, name: str) -> Path:
    return Path(root) / relative_path(kind, name)


# ---------------------------------------------------------------- file formats


def write_npy(path: Path, array: np.ndarray) -> None:
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.save(f, array)


def write_depth(path: Path, depth: np.ndarray) -> None:
    """z-depth [H, W] (row 0 at the top) -> single-channel float32 EXR, written atomically."""
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    channels = {DEPTH_CHANNEL: np.ascontiguousarray(depth, dtype=np.float32)}
    with atomic_path(path) as tmp, OpenEXR.File(header, channels) as f:
        f.write(str(tmp))


def read_depth(path) -> np.ndarray:
    """z-depth [H, W] float32 (metres, row 0 at the top; NO_HIT where the ray escaped)."""
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as f:
        channels = f.channels()
        if DEPTH_CHANNEL not in channels:
            raise ValueError(f"{path}: no channel {DEPTH_CHANNEL!r} (has {sorted(channels)})")
        return np.array(channels[DEPTH_CHANNEL].pixels, dtype=np.float32)


def read_png(path: Path) -> np.ndarray:
    """An 8-bit RGB(A) or grey PNG -> [H, W, 3] uint8 RGB (alpha dropped). Raises ValueError."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{path}: not a readable image")
    if img.dtype != np.uint8:
        raise ValueError(f"{path}: expected an 8-bit image, got {img.dtype}")
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    elif img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    else:
        raise ValueError(f"{path}: unsupported channel count {img.shape[2]}")
    return np.ascontiguousarray(img)


def write_png(path: Path, image) -> None:
    """[H, W, 3] RGB, float in [0, 1] (rounded to nearest) or uint8; numpy or a CPU/GPU tensor."""
    import cv2

    if hasattr(image, "detach"):  # a torch tensor, without importing torch here
        image = image.detach().cpu().numpy()
    arr = np.asarray(image)
    if arr.dtype != np.uint8:
        arr = (np.clip(arr, 0, 1) * 255 + 0.5).astype(np.uint8)
    ok, png = cv2.imencode(".png", cv2.cvtColor(arr, cv2.COLOR_RGB2BGR))
    if not ok:
        raise OSError(f"{path}: could not encode PNG")
    write_bytes(path, png.tobytes())


# ---------------------------------------------------------------- transforms.json and scene.json


def frame(name: str, camera, split: str, kind: str, file_path: str, dry_file_path: str | None = None,
          depth_file_path: str | None = None) -> dict:
    """One `frames` entry: both pose forms (nerfstudio `transform_matrix` and OpenCV `w2c`), the split
    ("train" | "test"), the view kind ("nadir", "oblique20", ...) and the image paths."""
    out = {"file_path": file_path, "dry_file_path": dry_file_path, "depth_file_path": depth_file_path,
           "transform_matrix": camera.c2w_gl.tolist(), "w2c": camera.w2c.tolist(), "split": split,
           "name": name, "kind": kind}
    return {k: v for k, v in out.items() if v is not None}


def transforms_json(camera, frames: list[dict], water) -> dict:
    """transforms.json: shared pinhole intrinsics of `camera` (no distortion), `water` (anything with
    `level` and `n`, or None for a dry scene) and the frames."""
    return {
        "camera_model": "OPENCV",
        "fl_x": camera.fx, "fl_y": camera.fy, "cx": camera.cx, "cy": camera.cy, "w": camera.width,
        "h": camera.height, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        "water": None if water is None else {"level": water.level, "n": water.n},
        "frames": frames,
    }


def scene_json(spec: dict, eval_region: dict | None, **figures) -> dict:
    """scene.json: the generator's `spec` (the contract reads `spec.bed.depth`, the mean bed depth below
    the water, and `spec.bed.size`, the side of the square bed centred on the origin), the evaluation
    region {xmin, xmax, ymin, ymax} and whatever else the generator reports."""
    out = {"spec": spec, **figures}
    if eval_region is not None:
        out["eval_region"] = eval_region
    return out


# ---------------------------------------------------------------- COLMAP


def _quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of a rotation matrix (COLMAP's convention)."""
    w = np.sqrt(max(0.0, 1 + R[0, 0] + R[1, 1] + R[2, 2])) / 2
    x = np.sqrt(max(0.0, 1 + R[0, 0] - R[1, 1] - R[2, 2])) / 2
    y = np.sqrt(max(0.0, 1 - R[0, 0] + R[1, 1] - R[2, 2])) / 2
    z = np.sqrt(max(0.0, 1 - R[0, 0] - R[1, 1] + R[2, 2])) / 2
    x = np.copysign(x, R[2, 1] - R[1, 2])
    y = np.copysign(y, R[0, 2] - R[2, 0])
    z = np.copysign(z, R[1, 0] - R[0, 1])
    q = np.array([w, x, y, z])
    return q / np.linalg.norm(q)


def write_colmap(folder: Path, views, image_kind: str) -> None:
    """COLMAP text model of `views` (objects with `name` and `camera`, all sharing intrinsics). Same pixel
    convention as ours: the top-left pixel's centre is (0.5, 0.5). Image names are relative to DIR/images."""
    cam = views[0].camera
    write_bytes(folder / "cameras.txt", (
        "# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        f"1 PINHOLE {cam.width} {cam.height} {cam.fx!r} {cam.fy!r} {cam.cx!r} {cam.cy!r}\n").encode())
    lines = ["# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "# POINTS2D (none)"]
    for i, v in enumerate(views, start=1):
        q, t = _quaternion(v.camera.R), v.camera.t
        lines.append(f"{i} {' '.join(repr(float(x)) for x in (*q, *t))} 1 {image_kind}/{v.name}.png")
        lines.append("")
    write_bytes(folder / "images.txt", ("\n".join(lines) + "\n").encode())
    write_bytes(folder / "points3D.txt", b"# 3D point list: empty (poses are known exactly)\n")

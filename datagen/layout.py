"""Dataset directory layout, atomic file writes, depth EXR format, and the metadata files.

DIR/
  transforms.json            nerfstudio-readable cameras + frames (see `transforms`)
  scene.json                 resolved spec, seed, versions, eval_region, flight figures, radiance model
  images/wet/NNNN.png        with-water render (8-bit sRGB): the training input (absent for a dry scene)
  images/dry/NNNN.png        the same pose without water
  gt/depth/NNNN.exr          dry z-depth in metres along the optical axis: one float32 channel "Z",
                             pixel centres exact (pixel filter 0.01 px); 1e10 where no surface was hit
  gt/bed.ply                 the exact bed mesh (double vertices, world metres)
  gt/bed_grid.npy            float64 [N, 3] bed points on a 5 cm horizontal grid over eval_region
  colmap/sparse/0/           COLMAP text model: cameras.txt (one PINHOLE), images.txt, empty points3D.txt
  scene/                     generator inputs and state: spec.json, geometry.npz, albedo.png, render log
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

PASSES = ("wet", "dry", "depth")
DEPTH_CHANNEL = "Z"
NO_HIT = 1e10  # Cycles' depth where a ray escapes; far beyond any scene distance


def output_path(root: Path, kind: str, name: str) -> Path:
    """Where pass `kind` ("wet" | "dry" | "depth") of view `name` lives."""
    if kind == "depth":
        return root / "gt" / "depth" / f"{name}.exr"
    return root / "images" / kind / f"{name}.png"


def temp_path(path: Path) -> Path:
    """A sibling name for writing `path` before an atomic rename (same folder: same file system)."""
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


def write_atomic(path: Path, data: bytes) -> None:
    tmp = temp_path(path)
    tmp.write_bytes(data)
    os.replace(tmp, path)


def write_json(path: Path, obj) -> None:
    write_atomic(path, (json.dumps(obj, indent=2) + "\n").encode())


def write_npy(path: Path, array: np.ndarray) -> None:
    tmp = temp_path(path)
    with open(tmp, "wb") as f:
        np.save(f, array)
    os.replace(tmp, path)


def write_depth(path: Path, depth: np.ndarray) -> None:
    """z-depth [H, W] (row 0 at the top) -> single-channel float32 EXR, written atomically."""
    import OpenEXR

    tmp = temp_path(path)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {DEPTH_CHANNEL: np.ascontiguousarray(depth, dtype=np.float32)}) as f:
        f.write(str(tmp))
    os.replace(tmp, path)


def read_depth(path) -> np.ndarray:
    """z-depth [H, W] float32 (metres, row 0 at the top; NO_HIT where the ray escaped)."""
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as f:
        channels = f.channels()
        if DEPTH_CHANNEL not in channels:
            raise ValueError(f"{path}: no channel {DEPTH_CHANNEL!r} (has {sorted(channels)})")
        return np.array(channels[DEPTH_CHANNEL].pixels, dtype=np.float32)


def transforms(poses, water, passes) -> dict:
    """transforms.json content; `water` is a WaterSpec or None, `passes` the rendered pass kinds."""
    cam = poses[0].camera
    frames = []
    for p in poses:
        wet = "wet" in passes
        frames.append({
            "file_path": f"images/{'wet' if wet else 'dry'}/{p.name}.png",
            "dry_file_path": f"images/dry/{p.name}.png",
            "depth_file_path": f"gt/depth/{p.name}.exr",
            "transform_matrix": p.camera.c2w_gl.tolist(),
            "w2c": p.camera.w2c.tolist(),
            "split": p.split,
            "name": p.name,
            "kind": p.kind,
        })
    return {
        "camera_model": "OPENCV",
        "fl_x": cam.fx, "fl_y": cam.fy, "cx": cam.cx, "cy": cam.cy, "w": cam.width, "h": cam.height,
        "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        "water": None if water is None else {"level": water.level, "n": water.n},
        "frames": frames,
    }


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


def write_colmap(folder: Path, poses, image_kind: str) -> None:
    """COLMAP text model of all poses (both splits; the split is in transforms.json). Same pixel convention
    as ours: the top-left pixel's centre is (0.5, 0.5). Image names are relative to DIR/images."""
    folder.mkdir(parents=True, exist_ok=True)
    cam = poses[0].camera
    write_atomic(folder / "cameras.txt", (
        "# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        f"1 PINHOLE {cam.width} {cam.height} {cam.fx!r} {cam.fy!r} {cam.cx!r} {cam.cy!r}\n").encode())
    lines = ["# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "# POINTS2D (none)"]
    for i, p in enumerate(poses, start=1):
        q, t = _quaternion(p.camera.R), p.camera.t
        lines.append(f"{i} {' '.join(repr(float(v)) for v in (*q, *t))} 1 {image_kind}/{p.name}.png")
        lines.append("")
    write_atomic(folder / "images.txt", ("\n".join(lines) + "\n").encode())
    write_atomic(folder / "points3D.txt", b"# 3D point list: empty (poses are known exactly)\n")

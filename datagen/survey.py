"""The survey a surveyor hands over, made from a rendered dataset: the training photos as JPEGs with their
focal length in EXIF (`survey/images/`), the camera centres as an RTK drone records them, with seeded noise
(`survey/positions.csv`), the water level as measured at the edge, with noise (`survey/water_level.txt`),
and ground control on the banks with the targets' pixels (`survey/gcp.csv`, `survey/gcp_pixels.csv`).
No poses: recovering them is `ragsplat survey`'s job; the dataset's transforms.json stays the truth that
scores it. numpy only (JPEG through Pillow)."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ragsplat_core.dataset import layout
from ragsplat_core.outputs import write_bytes, write_json


@dataclass(frozen=True)
class SurveyNoise:
    """Standard deviations (metres) of what the field instruments add."""

    horizontal: float = 0.02  # RTK camera centre, x and y
    vertical: float = 0.03  # RTK camera centre, z
    level: float = 0.01  # the water level measured at the edge
    gcp: float = 0.01  # a ground control point's surveyed position, each axis
    gcp_pixel: float = 0.3  # where a target's centre is picked in a photo (pixels, each axis)
    gcp_count: int = 6  # targets on the banks


def write_survey(root: Path, poses, level: float, seed: int = 0, noise: SurveyNoise = SurveyNoise(),
                 banks: np.ndarray | None = None, targets: np.ndarray | None = None) -> bool:
    """Writes ROOT/survey/ from the dataset ROOT's wet training views `poses` (`flight.plan`: name, camera,
    split) and the true water `level` (see the module docstring); with the banks' ground truth points
    `banks` [B, 3], also ground control: `noise.gcp_count` points on the banks spread apart (`gcp.csv`, with
    `noise.gcp`) and their pixels in every training photo that holds them (`gcp_pixels.csv`, with
    `noise.gcp_pixel`), as a surveyor who picked the targets' centres would give them; where the scene has
    checkerboard `targets` [T, 3] rendered (field conditions), those are the ground control. Returns False
    when a survey made with the same seed and noise is already there (nothing written)."""
    root = Path(root)
    record = {"seed": seed, "noise": asdict(noise), "views": "the training views, wet"}
    path = root / layout.SURVEY_RECORD
    if path.is_file() and json.loads(path.read_text()) == record:
        return False
    rng = np.random.default_rng(seed)
    train = [p for p in poses if p.split == "train"]
    names = [f"{p.name}.jpg" for p in train]
    for p, name in zip(train, names):
        image = layout.read_png(layout.output_path(root, "wet", p.name))
        layout.write_jpeg(root / layout.SURVEY_IMAGES / name, image, p.camera.fx)
    sigma = np.array([noise.horizontal, noise.horizontal, noise.vertical])
    centres = np.array([p.camera.camera_center for p in train])
    layout.write_positions(root / layout.SURVEY_POSITIONS, names, centres + rng.normal(size=centres.shape) * sigma)
    write_bytes(root / layout.SURVEY_LEVEL, f"{level + rng.normal() * noise.level:.4f}\n".encode())
    if targets is None and banks is not None:
        dry = banks[banks[:, 2] > level + 0.05]
        targets = spread(dry, noise.gcp_count, rng) if len(dry) >= 3 else None
    if targets is not None:
        gcps = [f"GCP{k + 1}" for k in range(len(targets))]
        layout.write_positions(root / layout.SURVEY_GCP, gcps, targets + rng.normal(size=targets.shape) * noise.gcp)
        rows = []
        for p, name in zip(train, names):
            uv, z = p.camera.project(targets)
            uv = uv + rng.normal(size=uv.shape) * noise.gcp_pixel
            inside = (z > 0) & (uv >= 2).all(1) & (uv[:, 0] <= p.camera.width - 2) & (uv[:, 1] <= p.camera.height - 2)
            rows += [(name, gcps[k], *uv[k]) for k in np.flatnonzero(inside)]
        layout.write_gcp_pixels(root / layout.SURVEY_GCP_PIXELS, rows)
    write_json(path, record)  # last: its presence marks a finished survey
    return True


def spread(points: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """[count, 3] of `points` [P, 3] far apart: farthest-point sampling from a random start."""
    chosen = [int(rng.integers(len(points)))]
    far = np.linalg.norm(points[:, :2] - points[chosen[0], :2], axis=1)
    while len(chosen) < min(count, len(points)):
        chosen.append(int(far.argmax()))
        far = np.minimum(far, np.linalg.norm(points[:, :2] - points[chosen[-1], :2], axis=1))
    return points[chosen]

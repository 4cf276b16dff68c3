"""The survey a surveyor hands over, made from a rendered dataset: the training photos as JPEGs with their
focal length in EXIF (`survey/images/`), the camera centres as an RTK drone records them, with seeded noise
(`survey/positions.csv`), and the water level as measured at the edge, with noise (`survey/water_level.txt`).
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


def write_survey(root: Path, poses, level: float, seed: int = 0, noise: SurveyNoise = SurveyNoise()) -> bool:
    """Writes ROOT/survey/ from the dataset ROOT's wet training views `poses` (`flight.plan`: name, camera,
    split) and the true water `level` (see the module docstring). Returns False when a survey made with the
    same seed and noise is already there (nothing written)."""
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
    write_json(path, record)  # last: its presence marks a finished survey
    return True

"""The survey a surveyor hands over, made from a rendered dataset: the training photos as JPEGs with their
focal length in EXIF (`survey/images/`), the camera centres as an RTK drone records them, with seeded noise
(`survey/positions.csv`), the water level as measured at the edge, with noise (`survey/water_level.txt`),
points on the water's edge along both banks as a surveyor measures them with RTK (`survey/water_edge.csv`,
header x,y,z, with noise on z) and ground control on the banks with the targets' pixels (`survey/gcp.csv`,
`survey/gcp_pixels.csv`). On a sloping surface water_level.txt holds one level at the mean of the edge
points' heights: what a tool that takes one flat water level would be given. No poses: recovering them is
`ragsplat survey`'s job; the dataset's transforms.json stays the truth that scores it. numpy only (JPEG
through Pillow)."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ragsplat_core.dataset import layout
from ragsplat_core.outputs import write_bytes, write_json

EDGE_POINTS = 15  # edge points measured along each bank
_EDGE_STREAM = 4  # the edge points' noise: a random stream apart from the survey's and the conditions' (1-3)


@dataclass(frozen=True)
class SurveyNoise:
    """Standard deviations (metres) of what the field instruments add."""

    horizontal: float = 0.02  # RTK camera centre, x and y
    vertical: float = 0.03  # RTK camera centre, z
    level: float = 0.01  # the water level measured at the edge (each edge point's height too)
    gcp: float = 0.01  # a ground control point's surveyed position, each axis
    gcp_pixel: float = 0.3  # where a target's centre is picked in a photo (pixels, each axis)
    gcp_count: int = 6  # targets on the banks


def write_survey(root: Path, poses, water, seed: int = 0, noise: SurveyNoise = SurveyNoise(),
                 banks: np.ndarray | None = None, targets: np.ndarray | None = None,
                 waterline: list[np.ndarray] | None = None, region: dict | None = None) -> bool:
    """Writes ROOT/survey/ from the dataset ROOT's wet training views `poses` (`flight.plan`: name, camera,
    split) and the true water surface `water` (`WaterSpec`: level, slope; see the module docstring); with
    the banks' ground truth points `banks` [B, 3], also ground control: `noise.gcp_count` points on the
    banks spread apart (`gcp.csv`, with `noise.gcp`) and their pixels in every training photo that holds
    them (`gcp_pixels.csv`, with `noise.gcp_pixel`), as a surveyor who picked the targets' centres would
    give them; where the scene has checkerboard `targets` [T, 3] rendered (field conditions), those are the
    ground control. With the `waterline` polylines [K, >= 2] (a reach), also the edge points
    (`edge_points`, along the evaluated `region`'s x-range). Returns False when a survey made with the same
    seed and noise is already there (nothing written but a missing water_edge.csv, which older surveys
    lack)."""
    root = Path(root)
    record = {"seed": seed, "noise": asdict(noise), "views": "the training views, wet"}
    path = root / layout.SURVEY_RECORD
    edge = None
    if waterline is not None:
        xy = edge_points(waterline, *((region["xmin"], region["xmax"]) if region else (-np.inf, np.inf)))
        edge = np.column_stack([xy, water.height(xy)])  # on the surface: the waterline's true heights
    if path.is_file() and json.loads(path.read_text()) == record:
        if edge is not None and not (root / layout.SURVEY_EDGE).is_file():
            _write_edge(root, edge, seed, noise)
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
    level = float(edge[:, 2].mean()) if water.sloping and edge is not None else water.level  # one level
    write_bytes(root / layout.SURVEY_LEVEL, f"{level + rng.normal() * noise.level:.4f}\n".encode())
    if edge is not None:
        _write_edge(root, edge, seed, noise)
    if targets is None and banks is not None:
        dry = banks[banks[:, 2] > water.height(banks[:, :2]) + 0.05]
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


def edge_points(lines: list[np.ndarray], xmin: float, xmax: float, count: int = EDGE_POINTS) -> np.ndarray:
    """[2 count, 2] points on the water's edge, `count` along each bank: the banks are the two waterline
    polylines [K, >= 2] that run farthest along x (the others ring bars and boulders); each is cut to its
    longest stretch within xmin..xmax and the vertices nearest `count` even steps along it are taken (the
    polylines' vertices lie exactly on the waterline, on the mesh's edges)."""
    lines = [np.asarray(line, np.float64)[:, :2] for line in lines]
    banks = sorted(lines, key=lambda line: -np.ptp(line[:, 0]))[:2]
    if len(banks) < 2:
        raise ValueError(f"the waterline has {len(banks)} polylines, not two banks")
    banks.sort(key=lambda line: line[:, 1].mean())  # the -y bank first
    out = []
    for line in banks:
        inside = np.concatenate([[0], (line[:, 0] >= xmin) & (line[:, 0] <= xmax), [0]]).astype(int)
        starts, ends = np.flatnonzero(np.diff(inside) == 1), np.flatnonzero(np.diff(inside) == -1)
        k = int(np.argmax(ends - starts))
        part = line[starts[k]:ends[k]]
        along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(part, axis=0), axis=1))])
        steps = (np.arange(count) + 0.5) / count * along[-1]
        out.append(part[np.abs(along[None] - steps[:, None]).argmin(1)])
    return np.concatenate(out)


def _write_edge(root: Path, edge: np.ndarray, seed: int, noise: SurveyNoise) -> None:
    """layout.SURVEY_EDGE from the true edge points [P, 3], with `noise.level` on each height (its own
    random stream)."""
    z = edge[:, 2] + np.random.default_rng([seed, _EDGE_STREAM]).normal(size=len(edge)) * noise.level
    layout.write_points(root / layout.SURVEY_EDGE, np.column_stack([edge[:, :2], z]))


def spread(points: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """[count, 3] of `points` [P, 3] far apart: farthest-point sampling from a random start."""
    chosen = [int(rng.integers(len(points)))]
    far = np.linalg.norm(points[:, :2] - points[chosen[0], :2], axis=1)
    while len(chosen) < min(count, len(points)):
        chosen.append(int(far.argmax()))
        far = np.minimum(far, np.linalg.norm(points[:, :2] - points[chosen[-1], :2], axis=1))
    return points[chosen]

"""What every stage of `ragsplat survey` shares: its config (`SurveyConfig`), the progress protocol
(`Progress`), the cache of finished stages (`Stamps`, the rerun logic written once: a stage whose
key is unchanged and whose outputs are there is skipped), the key digest and the products' names.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

from ragsplat.dataset.exif import BAROMETER_SIGMA, CONSUMER_SIGMA
from ragsplat.train.config import INIT

AUTO = "auto"


STAGES = ("sfm", "georef", "water", "train", "export")


RTK_SIGMA = (0.02, 0.03)  # an RTK drone's camera centre, horizontal and vertical (m)


PRODUCTS = ("dem.tif", "bed.laz", "depth.png", "ortho_bed.tif", "ortho_apparent.tif")


ORTHOS = PRODUCTS[3:]  # the orthophotos, each tile's in its folder, merged into the survey's


@dataclass(frozen=True)
class SurveyConfig:
    """A survey run's inputs and settings (`ragsplat survey --help` says each); written resolved to
    RUN/survey.json."""

    images: Path
    out: Path
    positions: Path | None = None
    gcp: Path | None = None
    gcp_pixels: Path | None = None
    gcp_sigma: float = 0.01
    water_level: float | str = AUTO
    water_surface: Path | None = None
    n: float = 1.33
    crs: str | None = None
    masks: Path | None = None
    lens: str = "radial"
    no_water_adjustment: bool = False
    rtk_sigma: tuple[float, float] | None = None
    gps_sigma: tuple[float, float] = CONSUMER_SIGMA
    barometer_sigma: float = BAROMETER_SIGMA
    variant: str | None = None  # None: the preset's (`train.defaults.survey_variant`)
    init: str = INIT
    preset: str = "small"
    iterations: int | None = None
    surfel_depth: str | None = None  # None: the preset's (`TrainConfig.surfel_depth`)
    seed: int = 0
    resolution: float = 0.05
    max_size: int | None = None
    stop_after: str | None = None
    tile_size: float | None = None  # m; None: TILE_GSD ground sample distances
    tile_overlap: float | None = None  # m; None: TILE_OVERLAP of the side
    uncertainty: Path | None = None  # a fitted `uncertainty.UncertaintyModel` (JSON): the DEM's band 3
    level_sigma: float | None = None  # m; None: the adjustment's where it estimated the level, else 0
    n_sigma: float = 0.0
    culls: dict = field(default_factory=dict)  # `ExtractConfig` fields to change ({}: the evaluation's)


def line(stage: str, text: str, since: float | None = None) -> str:
    """A progress line about `stage`; with `since` (a perf_counter start), the seconds it took."""
    took = "" if since is None else f" ({time.perf_counter() - since:.0f} s)"
    return f"[{stage}] {text}{took}"


class Progress:
    """What the pipeline tells its caller as it goes: this one says nothing; the command's prints lines and
    bars. `bar` returns a context manager with tqdm's update / set_postfix / close."""

    def say(self, stage: str, text: str, since: float | None = None) -> None:
        """One line about `stage`; with `since` (a perf_counter start), the seconds it took."""

    def bar(self, total: int, desc: str, unit: str):
        return _Silent()

    def count(self, desc: str, unit: str):
        """(bar, on_count(done, total))."""
        return _Silent(), lambda done, total: None

    def training(self, total: int, desc: str, initial: int):
        """(bar, on_step(trainer)) for `Trainer.train`."""
        return _Silent(), lambda trainer: None


class _Silent(contextlib.nullcontext):
    def __enter__(self):  # the bar itself, as tqdm's
        return self

    def update(self, n: int = 1) -> None:
        pass

    def set_postfix(self, *args, **kwargs) -> None:
        pass

    def refresh(self) -> None:
        pass

    def close(self) -> None:
        pass


def digest(*parts) -> str:
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:16]


class Stamps:
    """RUN/stages.json: the key each finished stage was made with; a stage whose key is unchanged is
    skipped."""

    def __init__(self, run: Path):
        self.path = run / "stages.json"
        self.keys = json.loads(self.path.read_text()) if self.path.is_file() else {}

    def done(self, stage: str, key: str, *outputs: Path) -> bool:
        """Whether `stage` was made with `key` and its `outputs` are still there."""
        return self.keys.get(stage) == key and all(Path(o).exists() for o in outputs)

    def mark(self, stage: str, key: str) -> None:
        """Records `stage` as made with `key`; a new key makes every later stage stale."""
        from ragsplat.outputs import write_json

        if self.keys.get(stage) == key:
            return
        self.keys = {**{s: k for s, k in self.keys.items() if STAGES.index(s) < STAGES.index(stage)},
                     stage: key}
        write_json(self.path, self.keys)

    def clear(self, stage: str) -> None:
        """Records `stage` and every later one as not made (a rerun makes them again)."""
        from ragsplat.outputs import write_json

        self.keys = {s: k for s, k in self.keys.items() if STAGES.index(s) < STAGES.index(stage)}
        write_json(self.path, self.keys)


def fresh_folder(folder: Path) -> Path:
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    return folder


def points_box(points):
    """[2, 2] the (lo, hi) corners in x, y of points [P, >=2]: their 1 and 99 %, so that a few stray points
    do not stretch it. The survey's extent (`water.json`'s extent_m) and a tile's area (`seen_area`)."""
    import numpy as np

    return np.percentile(points[:, :2], [1, 99], axis=0)

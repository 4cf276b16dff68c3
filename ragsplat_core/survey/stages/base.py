"""What every stage of `ragsplat survey` shares: its config (`SurveyConfig`), the progress protocol
(`Progress`), the cache of finished stages (`Stamps`, the rerun logic written once: a stage whose
key is unchanged and whose outputs are there is skipped), the key digest and the products' names.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

from ragsplat.dataset.exif import BAROMETER_SIGMA, CONSUMER_SIGMA
from ragsplat.outputs import changed, write_json
from ragsplat.train.config import INIT

AUTO = "auto"


STAGES = ("sfm", "georef", "water", "train", "export")


RTK_SIGMA = (0.02, 0.03)  # an RTK drone's camera centre, horizontal and vertical (m)


LENSES = ("radial", "pinhole")  # --lens by name; anything else is a calibration file


PRODUCTS = ("dem.tif", "bed.laz", "depth.png", "ortho_bed.tif", "ortho_apparent.tif")


ORTHOS = PRODUCTS[3:]  # the orthophotos, each tile's in its folder, merged into the survey's


@dataclass(frozen=True)
class SurveyConfig:
    """A survey run's inputs and settings, each field's help in its metadata (`ragsplat survey` takes its
    options' defaults and help from the fields; `%(default)s` expands to the default); written resolved to
    RUN/survey.json."""

    images: Path = field(metadata={"help": "the folder of the survey's photos (JPEG/PNG)"})
    out: Path = field(metadata={"help": "run directory (a rerun resumes)"})
    positions: Path | None = field(default=None, metadata={"help": (
        "camera centres as the drone's RTK recorded them: CSV with header name,x,y,z (image file name; "
        "metres, z up, the frame of the water level and the products); without --positions or --gcp the "
        "positions come from the photos' EXIF GPS and DJI XMP")})
    gcp: Path | None = field(default=None, metadata={"help": (
        "ground control points instead: CSV with header name,x,y,z (as surveyed), with --gcp-pixels")})
    gcp_pixels: Path | None = field(default=None, metadata={"help": (
        "where each target is in the photos: CSV with header image,name,u,v (pixels, the image's top-left "
        "corner at 0,0)")})
    gcp_sigma: float = field(default=0.01, metadata={"help": (
        "ground control accuracy, each axis (m; default %(default)s)")})
    water_level: float | str = field(default=AUTO, metadata={"help": (
        "height of the calm, flat water surface in the positions' frame (m), or auto (the default without "
        "--water-surface): the level estimated from the photos, in the adjustment through the water")})
    water_surface: Path | None = field(default=None, metadata={"help": (
        "points on the water's edge as measured along both banks (RTK): CSV with header x,y,z, the "
        "positions' frame; a river's sloping surface is fitted to them")})
    n: float = field(default=1.33, metadata={"help": "refractive index of the water (%(default)s)"})
    crs: str | None = field(default=None, metadata={"help": (
        "the positions' CRS for the products, e.g. EPSG:32633; with positions from the photos the "
        "projected CRS (metres) they are converted to (default: the UTM zone of their mean position)")})
    masks: Path | None = field(default=None, metadata={"help": (
        "masks named <image name>.png, zero where pixels are left out of training")})
    lens: str = field(default="radial", metadata={"help": (
        "radial: the lens's radial distortion k1, k2 estimated in the adjustment through the water (one "
        "lens for all photos) and the photos undistorted for training; pinhole: none (photos already "
        "undistorted); FILE: the lens calibrated before and held, a survey's water.json (a flight of the "
        "same camera with obliques or ground control) or JSON with k1 and k2 (COLMAP's RADIAL, OpenCV's "
        "in normalised coordinates); from a nadir-only flight an estimate can trade with a dome in the "
        "frame; default %(default)s")})
    no_water_adjustment: bool = field(default=False, metadata={"help": (
        "keep the pinhole structure-from-motion poses (only for comparison: through water they are tilted "
        "and the bed comes out too deep)")})
    rtk_sigma: tuple[float, float] | None = field(default=None, metadata={"help": (
        f"RTK position accuracy, horizontal and vertical (m; default {RTK_SIGMA[0]:g} {RTK_SIGMA[1]:g}, or "
        "with positions from the photos each RTK-fixed photo's own reported accuracy)")})
    gps_sigma: tuple[float, float] = field(default=CONSUMER_SIGMA, metadata={"help": (
        "accuracy of positions from the photos without RTK fix (consumer GPS), horizontal and vertical (m; "
        "default %(default)s)")})
    barometer_sigma: float = field(default=BAROMETER_SIGMA, metadata={"help": (
        "accuracy of those photos' heights where they come from the drone's barometer (DJI "
        "RelativeAltitude, above the take-off point) (m; default %(default)s)")})
    # None: the preset's (`train.defaults.survey_variant`)
    variant: str | None = field(default=None, metadata={"help": "the variant trained"})
    init: str = field(default=INIT, metadata={"help": "the training's start (default: %(default)s)"})
    preset: str = field(default="small", metadata={"help": (
        "training preset (%(default)s; long for river-scale photos of a few cm a pixel, whose surfels' "
        "centre z the default takes for them)")})
    iterations: int | None = field(default=None, metadata={"help": "override the preset's iteration count"})
    # None: the preset's (`TrainConfig.surfel_depth`)
    surfel_depth: str | None = field(default=None, metadata={"help": (
        "a surfel sample's z in training: where the pixel's ray meets it (ray) or its centre's (centre, as "
        "gsplat does on a GPU)")})
    seed: int = field(default=0, metadata={"help": "training seed (default %(default)s)"})
    resolution: float = field(default=0.05, metadata={"help": "DEM cell (%(default)s m)"})
    max_size: int | None = field(default=None, metadata={"help": (
        "downscale images for training so their longer side is at most PX pixels (default: full size, or "
        "two pixels a DEM cell where that halves the pixels, or the largest that fits the memory)")})
    stop_after: str | None = field(default=None, metadata={"help": (
        "stop after this stage (sfm, georef or water: the poses without training)")})
    # m; None: TILE_GSD ground sample distances
    tile_size: float | None = field(default=None, metadata={"help": (
        "split a larger survey into tiles of at most M metres a side, each trained on its own and their "
        "DEMs merged")})
    # m; None: TILE_OVERLAP of the side
    tile_overlap: float | None = field(default=None, metadata={"help": (
        "each tile's overlap with its neighbours (m; default: a tenth of the side)")})
    # the uncertainty band's and the culls' options are `ragsplat export`'s too (`cli.args`)
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


class Stamps:
    """RUN/stages.json: the key each finished stage was made with (`outputs.digest` of its inputs, the stage
    before it by its key); a stage whose key is unchanged is skipped."""

    def __init__(self, run: Path):
        self.path = run / "stages.json"
        self.keys = json.loads(self.path.read_text()) if self.path.is_file() else {}

    def done(self, stage: str, key: str, *outputs: Path) -> bool:
        """Whether `stage` was made with `key` and its `outputs` are still there."""
        return not changed(self.keys.get(stage), key) and all(Path(o).exists() for o in outputs)

    def mark(self, stage: str, key: str) -> None:
        """Records `stage` as made with `key`; a new key makes every later stage stale."""
        if self.keys.get(stage) == key:
            return
        self.keys = {**{s: k for s, k in self.keys.items() if STAGES.index(s) < STAGES.index(stage)},
                     stage: key}
        write_json(self.path, self.keys)

    def clear(self, stage: str) -> None:
        """Records `stage` and every later one as not made (a rerun makes them again)."""
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

"""`ragsplat survey`'s stages as library functions: from a survey's photos to its DEM, every stage cached in
the run folder and skipped by a rerun whose inputs are the same (`run`, one call a stage; the command only
parses arguments). Before any work, everything that can be refused is (`check_inputs`); then

1. structure from motion (`structure_from_motion`, `survey.sfm`: pycolmap SIFT, every pair matched, or each
   photo with its spatial neighbours above `sfm.EXHAUSTIVE_MAX` photos, incremental mapping) -> RUN/sfm/;
2. georeferencing (`georeference`): the similarity that takes the model's camera centres to the RTK
   positions (given, or from the photos' EXIF GPS and DJI XMP, `survey.exif`), or the ground control points
   triangulated from their pixels to their surveyed positions, robust to a few wrong ones (`survey.georef`)
   -> RUN/georef.json;
3. the water (`adjust_through_water`): one level, or the surface fitted to the water's edge points
   (`survey.water`), or the level estimated; bundle adjustment with the submerged tracks projected through
   it and the cameras held near their positions, or the ground control points at theirs (`survey.bundle`)
   -> RUN/model/ (a COLMAP model), RUN/water.json;
4. training (`train_and_export`: the imported survey, the best variant and start as `make ablation`
   measures them) and the products RUN/dem.tif, RUN/bed.laz, RUN/depth.png and, on the DEM's grid, the
   orthophotos RUN/ortho_bed.tif (the bed without the water) and RUN/ortho_apparent.tif (the photos
   mosaicked through it; `ragsplat.ortho`). A survey larger than a tile
   (`TILE_GSD` ground sample distances, or `SurveyConfig.tile_size`) is split into overlapping tiles
   (`survey.tiles`), each imported, trained and extracted on its own in RUN/tiles/K/ (a Dask task each where
   a client is given), and their beds merged: each cell from the tile whose core holds it; the layout and
   the seams' agreement in RUN/tiles.json. A survey of one tile trains in RUN/data and RUN/train, as it
   always has. With a fitted uncertainty model (`SurveyConfig.uncertainty`) the DEM gets band 3, each cell's
   TVU95, and the LAZ an extra dimension `tvu95` (`export.cell_tvu95`; a tiled survey's merged like the
   heights), the level's standard deviation the adjustment's where it estimated the level (`level_sigma`).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import shutil
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

from ragsplat.survey.exif import BAROMETER_SIGMA, CONSUMER_SIGMA
from ragsplat.train.config import INIT

if TYPE_CHECKING:
    import numpy as np
    import pycolmap
    import torch

    from ragsplat.dataset.load import Dataset
    from ragsplat.refraction import WaterSurface
    from ragsplat.survey.bundle import Bundle
    from ragsplat.survey.exif import PhotoPosition
    from ragsplat.survey.georef import Similarity
    from ragsplat.survey.sfm import Tracks
    from ragsplat.survey.tiles import Tile
    from ragsplat.survey.water import EdgeFit

AUTO = "auto"
STAGES = ("sfm", "georef", "water", "train", "export")
RTK_SIGMA = (0.02, 0.03)  # an RTK drone's camera centre, horizontal and vertical (m)
PRODUCTS = ("dem.tif", "bed.laz", "depth.png", "ortho_bed.tif", "ortho_apparent.tif")
ORTHOS = PRODUCTS[3:]  # the orthophotos, each tile's in its folder, merged into the survey's
# The training's Gaussian budget grows with the survey's area in ground sample distances (GSD^2): 0.17 per
# GSD^2 is the `small` preset's 40 000 on the synthetic survey's 127 m^2 (its points' 1-99 % box) at 2.33 cm;
# a smaller survey keeps the preset's budget. MAX_GAUSSIANS bounds memory (about 1 kB each while training).
GAUSSIANS_PER_GSD2 = 0.17
MAX_GAUSSIANS = 3_000_000
# Photos coarser than this (m a pixel) train with the surfels' centre z where neither --surfel-depth nor the
# preset chose it (the `long` preset's choice): the geometric mean of `small`'s 2.33 cm, where the ray's z is
# right, and the long reach's 4.65 cm, where the centre's z was 8.5 points ahead at 1 % of depth
# (tuning/small.json and long.json, "surfel_depth"). A consumer drone's mapping flight is such a survey.
COARSE_GSD = 0.033
# Photos finer than the DEM needs train downscaled to this many pixels across a DEM cell: two samples a
# cell resolve it, and the training's time goes with the pixels (OpenDroneMap's default dense cloud,
# --pc-quality medium, likewise works on photos at half their size). A downscale that would keep more than
# DEM_KEEP of the pixels is not made: it would save little time for the detail it loses.
DEM_SAMPLES = 2
DEM_KEEP = 0.5
IMAGE_MEMORY = 0.4  # the training's images (uint8) may take this share of the machine's memory
# With the level free, points that cross it as it moves make the cost slightly rough: on `small` (seed 7) it
# settles within 0.01 mm in 6-9 iterations and then creeps on by 1e-7 relative per step, so stop at 1e-7.
LEVEL_TOL = 1e-7
# An estimated level less certain than this is said to be poorly determined: on a flat bed with no dry ground
# (a synthetic survey of 18 photos from 4 m) the level could move 0.5 m for 0.2 % of the cost while its
# linearised uncertainty read 6.6 cm; on `small`, with banks and pools, it read 0.44 cm and was 0.3 cm off.
LEVEL_WARN = 0.02
# Such a level is looked for at the shoreline within 3 of its sigmas, at least this far (m).
SHORE_SPAN = 0.2
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")
# A tile's side in ground sample distances. Every tile trains the preset's steps however many photos it holds,
# so the tiles' count sets the training's time: this side makes the long reach two tiles, one per worker on
# a 2-core CPU, at a small cost at 1 % of depth against three (chosen on the development seed by the tiles'
# targets, docs/lab/performance.md, "Two tiles"), and keeps `small` one tile. The overlap with each neighbour,
# a share of the side, gives the cells near a seam a full view from both.
TILE_GSD = 1500
TILE_OVERLAP = 0.1
# Without --tile-size, a survey of at most this many photos is one tile whatever ground it covers: about
# what one worker trains in a `long` tile, while tiles cut by ground alone cut a high flight's few photos into
# tiles too small to triangulate (docs/survey.md, stage 5).
ONE_TILE_PHOTOS = 200
# 3DGS scales the position rate and the densification's sizes by the cameras' extent, which grows with a
# tile's length (55-57 m on the long reach's two tiles). A survey trains at most at the scale the `long`
# preset was chosen at: its development stretch's 19.82 m at 4.654 cm, 426 ground sample distances
# (`small`'s 4.6 m are 198; both keep their own). Larger tiles trained at it like the stretch
# (docs/lab/performance.md).
SCENE_SCALE_GSD = 426


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


def _digest(*parts) -> str:
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


def run(cfg: SurveyConfig, progress: Progress | None = None, cluster=None) -> list[Path]:
    """The survey `cfg` from its photos to its products (`PRODUCTS` in `cfg.out` and the report on them,
    `report.REPORT`: their paths returned; none when `cfg.stop_after` stops it early), every stage cached in
    `cfg.out`, the resolved config in
    RUN/survey.json. `progress` hears of each stage (default: nothing). `cluster(tasks)`, a context manager
    that opens a `dask.distributed.Client`, trains the tiles of a survey of several as Dask tasks; None: one
    after another in this process. Raises DatasetError, ConfigError, OutputError."""
    from ragsplat.survey.report import Recorder, write_report

    progress = Recorder(progress or Progress())
    survey = check_inputs(cfg, progress)
    stamps = Stamps(survey.cfg.out)
    structure = structure_from_motion(survey, stamps, progress)
    if survey.cfg.stop_after == "sfm":
        return []
    geo = georeference(survey, structure, stamps, progress)
    if survey.cfg.stop_after == "georef":
        return []
    water = adjust_through_water(survey, structure, geo, stamps, progress)
    if survey.cfg.stop_after == "water":
        return []
    products = train_and_export(survey, water, stamps, progress, cluster)
    t0 = time.perf_counter()
    report = write_report(survey.cfg.out, progress.said)
    progress.say("report", f"{report}", t0)
    return [*products, report]


@dataclass(frozen=True)
class Positions:
    """What fixes the survey's frame: the cameras' positions (a file, or the photos' EXIF GPS and DJI XMP),
    or ground control points and where the photos see them."""

    source: Path  # the file (or, for EXIF, the photos' folder) that names the photos
    located: list[str]  # the photos it names (with a position, or seeing a target)
    positions: dict[str, np.ndarray] | None = None  # photo -> camera centre (CRS); None with ground control
    control: dict[str, np.ndarray] | None = None  # target -> surveyed position (CRS)
    pixels: list | None = None  # (photo, target, (u, v)): the targets in the photos
    tagged: list[PhotoPosition] | None = None  # the photos' GPS records, where the positions came from them
    sigma: dict[str, np.ndarray] | None = None  # photo -> (horizontal, vertical) sigma, from the photos

    @property
    def frame(self) -> dict[str, np.ndarray]:
        """The known positions: the cameras', else the targets'."""
        return self.positions or self.control

    @property
    def rtk_fixed(self) -> int:
        """How many photos' GPS is RTK fixed (positions from the photos)."""
        return sum(p.rtk_fixed for p in self.tagged)

    @property
    def holds_tilt(self) -> bool:
        """Whether the positions fix the frame's tilt: given, ground control, RTK, or heights from the
        barometer; consumer GPS heights alone (metres from photo to photo) do not."""
        return self.tagged is None or any(p.rtk_fixed or p.barometric for p in self.tagged)


@dataclass(frozen=True)
class GivenWater:
    """The water as the user gives it: one level, a surface fitted to its edge points, or none (estimated)."""

    surface: WaterSurface | None  # in the CRS; None: estimated in the adjustment through the water
    edge: EdgeFit | None = None  # the fit to the edge points (--water-surface)
    edge_points: np.ndarray | None = None  # [K, 3] those points (CRS)


@dataclass(frozen=True)
class Survey:
    """A survey's inputs, read and checked before any work."""

    cfg: SurveyConfig  # resolved: the CRS from the photos, the --max-size that fits
    photos: list[Path]
    where: Positions
    given: GivenWater
    origin: np.ndarray  # [3] the local frame's origin in the CRS (whole metres)
    water: WaterSurface | None  # the given surface in the local frame

    @property
    def names(self) -> list[str]:
        return [p.name for p in self.photos]

    @property
    def rtk_sigma(self) -> tuple[float, float]:
        return self.cfg.rtk_sigma or RTK_SIGMA


@dataclass(frozen=True)
class Structure:
    """Stage 1's model (RUN/sfm/model) and the key it was made with."""

    key: str
    rec: pycolmap.Reconstruction


@dataclass(frozen=True)
class Correspondences:
    """The model's camera centres, or its triangulated targets, paired with their known positions."""

    src: np.ndarray  # [K, 3] in the model's frame
    dst: np.ndarray  # [K, 3] known, in the local frame
    labels: list[str]  # the photos' or the targets' names
    what: str  # in words
    tol: float | np.ndarray  # 10 sigma of each position (one for all, or [K])
    noise: dict  # georef.json's account of the positions' noise
    have: list[int] | None = None  # the tracks' cameras with a position (positions)
    rtk: np.ndarray | None = None  # [K] bool: RTK fixed (positions from the photos)
    gcp: dict | None = None  # target -> (model xyz, observations) (ground control)
    usable: list[str] | None = None  # the targets placed in the model (ground control)


@dataclass(frozen=True)
class Georeferenced:
    """Stage 2: the similarity from the model to the local frame, and what it was fitted to."""

    key: str
    given: str  # the positions' fingerprint (with their accuracy, where each photo has its own)
    tracks: Tracks
    sim: Similarity
    pairs: Correspondences


@dataclass(frozen=True)
class Problem:
    """The adjustment through the water's unknowns and observations in the local frame: the georeferenced
    cameras and points (the targets after the points, with ground control), and what holds the frame."""

    R: torch.Tensor  # [I, 3, 3] world -> camera
    C: torch.Tensor  # [I, 3]
    points: torch.Tensor  # [P (+ G), 3]
    point: torch.Tensor  # [M] index into points
    image: torch.Tensor  # [M] index into the cameras
    pixels: torch.Tensor  # [M, 2]
    held: dict  # `bundle.adjust`'s priors: the cameras at their positions, or the targets at theirs
    gcp_rows: torch.Tensor | None = None  # [G] the targets' rows in points


@dataclass(frozen=True)
class Adjusted:
    """The cameras and points after the adjustment through the water (or as georeferenced, without it)."""

    R: torch.Tensor
    C: torch.Tensor
    points: torch.Tensor  # [P, 3] the tracks' points (the targets' rows dropped)
    water: WaterSurface  # in the local frame: as given, or as estimated (and levelled)
    surface: WaterSurface  # the same in the CRS
    bundle: Bundle | None  # None: --no-water-adjustment
    estimated: dict | None = None  # water.json's account of the estimated water
    lens: dict | None = None  # water.json's account of the lens's distortion (--lens radial)
    gcp_residual: dict | None = None  # target -> adjusted minus surveyed position (m), with ground control


@dataclass(frozen=True)
class Water:
    """Stage 3: the adjusted model (RUN/model), the water's surface (CRS) and the model's points' box."""

    key: str
    model: Path
    surface: WaterSurface
    extent: np.ndarray  # [2, 2] the points' 1 and 99 % in x, y (CRS)


def check_inputs(cfg: SurveyConfig, progress: Progress) -> Survey:
    """Everything that can be refused, refused before any work: the photos, what fixes their frame
    (`locate`), the water as given, a camera above it, the sizes (`_check_sizes`); then the run folder
    claimed and RUN/survey.json written with the config resolved."""
    import numpy as np

    from ragsplat.errors import DatasetError
    from ragsplat.outputs import claim, write_json

    if not cfg.images.is_dir():
        raise DatasetError(f"{cfg.images}: no such folder of photos")
    photos = sorted(p for p in cfg.images.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if len(photos) < 3:
        raise DatasetError(f"{cfg.images}: {len(photos)} photos (JPEG, PNG or TIFF); at least 3 are needed")
    if cfg.variant is None:
        from ragsplat.train.defaults import survey_variant

        cfg = replace(cfg, variant=survey_variant(cfg.preset))
    if cfg.uncertainty is not None:
        from ragsplat.export import read_uncertainty

        read_uncertainty(cfg.uncertainty)  # ConfigError before any work
    cfg, where = locate(cfg, photos, progress)
    given = water_as_given(cfg, where, progress)
    if where.positions is not None and given.surface is not None:
        _check_above(given.surface, np.array([where.positions[n] for n in where.located]))
    sized = where.located if where.positions else where.control
    cfg = _check_sizes(cfg, progress, photos, np.array([where.frame[n] for n in sized]), given.surface,
                       where.tagged)
    claim(cfg.out, "survey run")
    write_json(cfg.out / "survey.json",
               {k: str(v) if isinstance(v, Path) else v for k, v in asdict(cfg).items()})
    # a local origin (whole metres): UTM-sized coordinates keep millimetres in every float64 step
    origin = np.round(np.mean(list(where.frame.values()), axis=0))
    water = None if given.surface is None else given.surface.shifted(origin)
    return Survey(cfg, photos, where, given, origin, water)


def locate(cfg: SurveyConfig, photos: list[Path], progress: Progress) -> tuple[SurveyConfig, Positions]:
    """What will fix the photos' frame: the positions file, or the photos' EXIF GPS and DJI XMP (the CRS
    they choose set in the returned config), or the ground control points with their pixels. ConfigError
    for a half-given ground control, DatasetError unless enough of the names are photos."""
    from ragsplat.dataset import layout
    from ragsplat.errors import ConfigError, DatasetError

    names = [p.name for p in photos]
    tagged = sigma = pixels = None
    if cfg.positions is not None:
        positions, control = layout.read_positions(cfg.positions), None
        known, source = positions, cfg.positions
    elif cfg.gcp is None:  # the positions from the photos' EXIF GPS and DJI XMP
        from ragsplat.survey import exif

        if cfg.gcp_pixels is not None:
            raise ConfigError("--gcp-pixels needs --gcp (the targets' surveyed positions)")

        tagged = exif.read_photos(photos)
        positions, crs = exif.positions(tagged, cfg.crs)
        cfg = replace(cfg, crs=cfg.crs or exif.crs_label(crs))
        sigma = dict(zip(names, exif.sigmas(tagged, cfg.rtk_sigma, tuple(cfg.gps_sigma),
                                            cfg.barometer_sigma)))
        control, known, source = None, positions, cfg.images
        fixed = sum(p.rtk_fixed for p in tagged)
        baro = sum(p.barometric for p in tagged)
        heights = sorted({p.altitude_source for p in tagged if not p.barometric})
        said = ([f"{baro} from the barometer (DJI RelativeAltitude, to {cfg.barometer_sigma:g} m)"] if baro
                else []) + ([f"as the photos give them ({', '.join(heights)})"] if heights else [])
        progress.say("check", f"positions from the photos: {len(tagged)} of {len(photos)} have GPS "
                     f"({fixed} RTK fixed, {len(tagged) - fixed} consumer GPS), in {exif.describe_crs(crs)}; "
                     f"heights {', '.join(said)}")
    else:
        if cfg.gcp_pixels is None:
            raise ConfigError("--gcp needs --gcp-pixels (where each target is in the photos)")
        positions, control = None, layout.read_positions(cfg.gcp)
        pixels = layout.read_gcp_pixels(cfg.gcp_pixels)
        known, source = {image: None for image, _, _ in pixels}, cfg.gcp_pixels
        strange = sorted({name for _, name, _ in pixels} - set(control))
        if strange:
            raise DatasetError(f"{cfg.gcp_pixels}: targets not in {cfg.gcp}: {', '.join(strange[:5])}")
    unknown = sorted(set(known) - set(names))
    located = [n for n in names if n in known]
    if len(located) < (3 if control is None else 2):
        raise DatasetError(f"{source}: {len(located)} of its names are photos in {cfg.images} "
                           f"(e.g. {', '.join(sorted(known)[:3])} vs {', '.join(names[:3])}); at least "
                           f"{3 if control is None else 2} are needed")
    if unknown:
        progress.say("check", f"{len(unknown)} names in {source} are not photos in {cfg.images} (ignored), "
                     f"e.g. {unknown[0]}")
    return cfg, Positions(source, located, positions, control, pixels, tagged, sigma)


def water_as_given(cfg: SurveyConfig, where: Positions, progress: Progress) -> GivenWater:
    """The water given: a surface fitted to the edge points (--water-surface, which must lie near the
    positions), one level, or none: estimated in the adjustment through it (which --no-water-adjustment
    refuses, a ConfigError)."""
    import numpy as np

    from ragsplat.dataset import layout
    from ragsplat.errors import ConfigError
    from ragsplat.refraction import WaterSurface
    from ragsplat.survey import water as water_fit

    if cfg.water_surface is not None:
        edge_points = layout.read_points(cfg.water_surface)
        frame = np.array(list(where.frame.values()), float)
        _check_near(edge_points, frame, cfg.water_surface, "the photos' positions" if where.control is None
                    else f"the ground control ({cfg.gcp})", cfg.crs)
        edge = water_fit.fit_edge(edge_points)
        surface = WaterSurface(edge.level, cfg.n, edge.slope, edge.profile)
        progress.say("check", f"water surface from {len(edge.residuals)} edge points: {_describe(surface)}, "
                     f"rms {100 * edge.report()['rms_m']:.1f} cm, {int((~edge.inliers).sum())} left out")
        return GivenWater(surface, edge, edge_points)
    if cfg.water_level == AUTO:  # estimated in the adjustment through the water (stage 3)
        if cfg.no_water_adjustment:
            raise ConfigError("--no-water-adjustment needs a water level or surface: without one it is "
                              "estimated in that adjustment (give --water-level Z or --water-surface "
                              "EDGE.csv)")
        return GivenWater(None)
    return GivenWater(WaterSurface(cfg.water_level, cfg.n))


def structure_from_motion(survey: Survey, stamps: Stamps, progress: Progress) -> Structure:
    """Stage 1: the photos' model by pycolmap (`survey.sfm`) in RUN/sfm/, every pair matched, or each photo
    with its nearest where the survey is large and every photo has a position; kept while the photos are the
    same."""
    import numpy as np
    import pycolmap

    from ragsplat.dataset import layout
    from ragsplat.outputs import write_json
    from ragsplat.survey import sfm

    cfg, photos, names, positions = survey.cfg, survey.photos, survey.names, survey.where.positions
    key = _digest({p.name: layout.file_digest(p) for p in photos}, sfm.CAMERA_MODEL, sfm.FEATURE_MAX_SIZE)
    work = cfg.out / "sfm"
    t0 = time.perf_counter()
    if not stamps.done("sfm", key, work / "model"):
        pairs = None
        if len(names) > sfm.EXHAUSTIVE_MAX and (positions is not None and all(n in positions for n in names)):
            pairs = sfm.neighbour_pairs(np.array([positions[n] for n in names]), sfm.NEIGHBOURS)
        how = ("every pair matched" if pairs is None
               else f"each photo matched with its {sfm.NEIGHBOURS} nearest")
        progress.say("sfm", f"structure from motion of {len(photos)} photos (pycolmap SIFT, {how}, "
                     "incremental mapping; CPU) ...")
        timings = {}
        rec = sfm.reconstruct(cfg.images, names, work, pairs=pairs, timings=timings,
                              progress=lambda desc, total, unit: progress.bar(total, f"[sfm] {desc}", unit))
        rec.write_text(str(_fresh(work / "model")))
        write_json(work / "timings.json", timings)
        progress.say("sfm", f"features {timings['features_s']:.0f} s, {timings['pairs']} pairs matched in "
                     f"{timings['matching_s']:.0f} s, mapping {timings['mapping_s']:.0f} s")
        stamps.mark("sfm", key)
    rec = pycolmap.Reconstruction(str(work / "model"))
    progress.say("sfm", f"{rec.num_reg_images()} of {len(photos)} photos registered, {rec.num_points3D()} "
                 f"points, reprojection error {rec.compute_mean_reprojection_error():.2f} px", t0)
    return Structure(key, rec)


def georeference(survey: Survey, structure: Structure, stamps: Stamps, progress: Progress) -> Georeferenced:
    """Stage 2: the similarity (RANSAC, `survey.georef`) that takes the model's camera centres to their
    positions, or its triangulated targets to their surveyed positions; its report in RUN/georef.json.
    DatasetError where too few correspond, or the cameras then do not look down."""
    import numpy as np

    from ragsplat.dataset import layout
    from ragsplat.errors import DatasetError
    from ragsplat.outputs import write_json
    from ragsplat.survey import georef, sfm

    cfg, where, names = survey.cfg, survey.where, survey.names
    given = layout.file_digest(where.source) if where.tagged is None else _digest(
        {n: where.positions[n].tolist() for n in names}, {n: where.sigma[n].tolist() for n in names}, cfg.crs)
    key = _digest(structure.key, given, None if where.control is None else layout.file_digest(cfg.gcp),
                  survey.origin.tolist())
    trk = sfm.tracks(structure.rec)
    if where.control is None:
        pairs = _camera_pairs(survey, trk)
    else:
        pairs = _control_pairs(survey, structure.rec, trk)
    threshold = np.maximum(0.2, pairs.tol)  # 10 sigma, at least 20 cm: only gross errors are left out
    sim, inliers = georef.ransac_similarity(pairs.src, pairs.dst, threshold=threshold)
    looks = (trk.R[:, 2, :].numpy() @ sim.R.T)[:, 2]  # the optical axes' z in the positions' frame
    if np.median(looks) > -0.2:
        raise DatasetError(f"{where.source}: after alignment the cameras do not look down (median optical "
                           f"axis z {np.median(looks):+.2f}): are the coordinates metres with z up?")
    if survey.water is not None:
        _check_above(survey.water, sim.apply(trk.C.numpy()))
    report = _georef_report(survey, pairs, sim, inliers, threshold)
    write_json(cfg.out / "georef.json", report)
    progress.say("georef", f"similarity to {pairs.what}: scale {sim.scale:.4g}, {int(inliers.sum())} of "
                 f"{len(pairs.labels)} inliers, rms {100 * report['rms_m']:.1f} cm (each one's: "
                 f"{cfg.out / 'georef.json'})")
    if "scale_uncertainty" in report:
        scale = report["scale_uncertainty"]
        progress.say("georef", "the scale comes from consumer GPS: depths and heights may be off by up to "
                     f"about {100 * scale['relative']:.0f} % (rms {report['rms_m']:.2f} m over the flight's "
                     f"{scale['extent_m']:.0f} m); for depths to 1 %, give ground control (--gcp, "
                     "--gcp-pixels) or fly with RTK")
    stamps.mark("georef", key)
    return Georeferenced(key, given, trk, sim, pairs)


def _camera_pairs(survey: Survey, trk: Tracks) -> Correspondences:
    """The registered cameras' centres and their positions, each position's threshold from its source."""
    import numpy as np

    from ragsplat.errors import DatasetError

    where = survey.where
    have = [k for k, n in enumerate(trk.names) if n in where.positions]
    if len(have) < 3:
        raise DatasetError(f"{survey.cfg.positions}: only {len(have)} registered photos have a position; 3 "
                           "are needed")
    src = trk.C[have].numpy()
    dst = np.array([where.positions[trk.names[k]] for k in have]) - survey.origin
    labels = [trk.names[k] for k in have]
    if where.tagged is None:
        return Correspondences(src, dst, labels, f"{len(have)} RTK positions", 10 * survey.rtk_sigma[1],
                               {"model": "RTK", "sigma_m": list(survey.rtk_sigma)}, have)
    # the threshold follows each position's source: consumer GPS scatter is no outlier
    ours = np.array([where.sigma[n] for n in labels])
    is_fixed = {p.name: p.rtk_fixed for p in where.tagged}
    rtk = np.array([is_fixed[n] for n in labels])
    what = (f"{len(have)} positions from the photos ({int(rtk.sum())} RTK fixed, {int((~rtk).sum())} "
            "consumer GPS)")
    noise = _noise_model(where.tagged, where.sigma, labels)
    return Correspondences(src, dst, labels, what, 10 * ours.max(1), noise, have, rtk)


def _control_pairs(survey: Survey, rec, trk: Tracks) -> Correspondences:
    """The ground control points triangulated in the model from their pixels, and their surveyed positions."""
    import numpy as np

    from ragsplat.errors import DatasetError
    from ragsplat.survey import sfm

    cfg, control = survey.cfg, survey.where.control
    gcp = sfm.control_points(rec, trk, survey.where.pixels)  # name -> (model xyz, observations)
    usable = [n for n, (xyz, obs) in gcp.items() if np.isfinite(xyz).all()]
    if len(usable) < 3:
        seen = ", ".join(f"{n} ({len(gcp[n][1]) if n in gcp else 0} photos)" for n in sorted(control))
        raise DatasetError(f"{cfg.gcp_pixels}: only {len(usable)} ground control points are seen in 2 or "
                           f"more registered photos from different places; 3 are needed ({seen})")
    src = np.array([gcp[n][0] for n in usable])
    dst = np.array([control[n] for n in usable]) - survey.origin
    return Correspondences(src, dst, usable, f"{len(usable)} ground control points", 10 * cfg.gcp_sigma,
                           {"model": "ground control", "sigma_m": cfg.gcp_sigma}, gcp=gcp, usable=usable)


def _georef_report(survey: Survey, pairs: Correspondences, sim: Similarity, inliers: np.ndarray,
                   threshold) -> dict:
    """RUN/georef.json: the similarity, each correspondence's residual, the positions and their noise."""
    import numpy as np

    cfg, origin, tagged, sigma = survey.cfg, survey.origin, survey.where.tagged, survey.where.sigma
    res = sim.apply(pairs.src) - pairs.dst
    report = {"to": pairs.what, "scale": sim.scale, "R": sim.R.tolist(), "t": (sim.t + origin).tolist(),
              "origin": origin.tolist(), "inliers": int(inliers.sum()), "count": len(pairs.labels),
              "residual_m": {name: r.tolist() for name, r in zip(pairs.labels, res)},
              "rms_m": float(np.sqrt((res[inliers] ** 2).sum(1).mean())),
              "positions": {"source": "the photos' EXIF GPS and DJI XMP" if tagged is not None
                            else str(survey.where.source), "crs": cfg.crs},
              "noise": {**pairs.noise, "threshold_m": _rounded(threshold),
                        "fit": "similarity (7 parameters), RANSAC on 3 correspondences then refitted to the "
                        "inliers; a correspondence whose residual exceeds the threshold is an outlier"}}
    if tagged is not None:
        rtk = pairs.rtk
        report["positions"] |= {"heights": sorted({p.altitude_source for p in tagged}), "photos": {
            p.name: {"lat": p.lat, "lon": p.lon, "altitude": p.altitude, "rtk_flag": p.rtk_flag,
                     "sigma_m": sigma[p.name].tolist(), "gimbal_ypr_deg": p.gimbal} for p in tagged}}
        report["noise"]["rms_m_by_source"] = {
            kind: float(np.sqrt((res[inliers & pick] ** 2).sum(1).mean())) if (inliers & pick).any() else None
            for kind, pick in (("rtk_fixed", rtk), ("consumer_gps", ~rtk))}
        if (inliers & rtk).sum() < 3:  # the scale is consumer GPS's: say how far depths can be off
            extent = float(np.ptp(pairs.dst[inliers, :2], axis=0).max())
            report["scale_uncertainty"] = {
                "relative": report["rms_m"] / extent, "extent_m": extent,
                "from": "the positions' rms residual over the flight's longest horizontal side: consumer "
                        "GPS fixes the scale no better (its errors are shared along a flight line, so the "
                        "fit's own standard error would understate them); depths and heights are scaled with "
                        "it"}
    return report


def adjust_through_water(survey: Survey, structure: Structure, geo: Georeferenced, stamps: Stamps,
                         progress: Progress) -> Water:
    """Stage 3: the bundle adjustment through the water (`_adjust`), the cameras held at their positions or
    the targets at theirs, the water estimated where not given; the adjusted model in RUN/model/, the
    water's report in RUN/water.json (a new one makes the training's folders stale)."""
    import numpy as np
    import torch

    from ragsplat.dataset import layout
    from ragsplat.outputs import write_json
    from ragsplat.refraction import WaterSurface
    from ragsplat.survey import sfm

    cfg, water = survey.cfg, survey.water
    held_by = list(survey.rtk_sigma) if survey.where.sigma is None else geo.given  # one accuracy, or each's
    key = _digest(geo.key, layout.water_json(water) if water is not None else [AUTO, cfg.n],
                  cfg.no_water_adjustment, held_by, cfg.gcp_sigma, cfg.lens)
    model = cfg.out / "model"
    t0 = time.perf_counter()
    if not stamps.done("water", key, model, cfg.out / "water.json"):
        fit = _adjust(survey, geo, _problem(survey, geo), progress)
        check = _water_report(survey, fit)
        origin = torch.as_tensor(survey.origin)
        sfm.set_poses(structure.rec, geo.tracks, fit.R, fit.C + origin, fit.points + origin,
                      None if fit.lens is None else fit.bundle.lens)
        structure.rec.write_text(str(_fresh(model)))
        write_json(cfg.out / "water.json", check)
        for stale in ("data", "train"):  # made from the previous poses
            shutil.rmtree(cfg.out / stale, ignore_errors=True)
        stamps.mark("water", key)
    check = json.loads((cfg.out / "water.json").read_text())
    surface = WaterSurface(**{**check["surface"], "n": cfg.n})  # as given, or as estimated
    _say_water(progress, surface, check, t0)
    return Water(key, model, surface, np.asarray(check["extent_m"]))


def _problem(survey: Survey, geo: Georeferenced) -> Problem:
    """The tracks georeferenced, and held: each camera at its position (RTK centimetres, or as its source
    allows), or the targets, joined to the points with their observations, at their surveyed positions."""
    import numpy as np
    import torch

    trk, sim, pairs, where = geo.tracks, geo.sim, geo.pairs, survey.where
    R = trk.R @ torch.as_tensor(sim.R.T)  # world = s R x + t: cam_from_world' = cam_from_world R^T
    C = torch.as_tensor(sim.apply(trk.C.numpy()))
    P = torch.as_tensor(sim.apply(trk.points.numpy()))
    point, image, pix = trk.point, trk.image, trk.pixels
    if where.control is None:
        prior = torch.full_like(C, float("nan"))
        prior[pairs.have] = torch.as_tensor(pairs.dst)
        if where.sigma is None:
            sigma = (survey.rtk_sigma[0],) * 2 + (survey.rtk_sigma[1],)
            return Problem(R, C, P, point, image, pix, {"prior_C": prior, "prior_sigma": sigma})
        # each camera held as its source allows (RTK centimetres, consumer GPS metres)
        each = torch.ones_like(C)
        each[pairs.have] = torch.as_tensor(np.array([where.sigma[trk.names[k]][[0, 0, 1]]
                                                     for k in pairs.have]))
        return Problem(R, C, P, point, image, pix, {"prior_C": prior, "prior_sigma": each})
    gcp_rows = torch.arange(len(P), len(P) + len(pairs.usable))
    obs = [(row, k, uv) for row, n in zip(gcp_rows.tolist(), pairs.usable) for k, uv in pairs.gcp[n][1]]
    point = torch.cat([point, torch.tensor([o[0] for o in obs])])
    image = torch.cat([image, torch.tensor([o[1] for o in obs])])
    pix = torch.cat([pix, torch.as_tensor(np.array([o[2] for o in obs]))])
    P = torch.cat([P, torch.as_tensor(sim.apply(pairs.src))])
    held = {"prior_points": (gcp_rows, torch.as_tensor(pairs.dst)), "point_sigma": survey.cfg.gcp_sigma}
    return Problem(R, C, P, point, image, pix, held, gcp_rows)


def _adjust(survey: Survey, geo: Georeferenced, problem: Problem, progress: Progress) -> Adjusted:
    """`problem` adjusted through the water (`survey.bundle`), with the lens's distortion (--lens radial) and,
    where none is given, the water (`_estimate_water`); as it is with --no-water-adjustment."""
    import torch

    from ragsplat.survey import bundle

    cfg, trk = survey.cfg, geo.tracks
    water, surface, adj, estimated, lens_record = survey.water, survey.given.surface, None, None, None
    R, C, P = problem.R, problem.C, problem.points
    if not cfg.no_water_adjustment:
        progress.say("water", f"bundle adjustment through the water ({len(problem.point)} observations of "
                     f"{len(P)} points, {len(C)} cameras) ...")
        with progress.bar(30, "[water] adjustment", "iteration") as b:
            def step(cost):
                b.update(1)
                b.set_postfix(cost=f"{cost:.4g}", refresh=False)

            lens = ("lens",) if cfg.lens == "radial" else ()
            if water is None:  # the level too, from a start among the model's points
                adj, water, estimated = _estimate_water(survey, geo, problem, lens, step)
                surface = water.shifted(-survey.origin)
            else:
                adj = bundle.adjust(R, C, trk.intrinsics, P, problem.point, problem.image, problem.pixels,
                                    water, free=lens, tol=LEVEL_TOL if lens else 1e-9, on_iteration=step,
                                    **problem.held)
            if lens:
                lens_record = {"model": "RADIAL (COLMAP): x (1 + k1 r^2 + k2 r^4), normalised coordinates",
                               "k1": adj.lens[0], "k2": adj.lens[1],
                               "sigma": {k: adj.sigma[k] for k in ("k1", "k2")}}
        R, C, P = adj.R, adj.C, adj.points
    gcp_residual = None
    if problem.gcp_rows is not None:
        dst = geo.pairs.dst
        gcp_residual = {n: (P[r] - torch.as_tensor(dst[k])).tolist() for k, (n, r) in
                        enumerate(zip(geo.pairs.usable, problem.gcp_rows.tolist()))}
        P = P[: len(trk.points)]
    return Adjusted(R, C, P, water, surface, adj, estimated, lens_record, gcp_residual)


def _estimate_water(survey: Survey, geo: Georeferenced, problem: Problem, lens: tuple[str, ...],
                    step) -> tuple[Bundle, WaterSurface, dict]:
    """(the adjustment, the water (local frame), water.json's account of it) with the level free, started
    among the model's points; where the positions fix no tilt (consumer GPS) the slope too, and then the
    frame levelled by the water's plane, unless that plane tilts more than the positions' heights leave open
    (`georef.tilt_allowed`): then the level alone, the frame as the positions hold it."""
    import torch

    from ragsplat.refraction import WaterSurface
    from ragsplat.survey import bundle, georef
    from ragsplat.survey import water as water_fit

    cfg, trk, origin, P = survey.cfg, geo.tracks, survey.origin, problem.points
    start = water_fit.start_level(P[: len(trk.points)].numpy())
    # positions that fix no tilt (consumer GPS heights): the water's slope too, then the frame levelled by it
    free = ("level",) if survey.where.holds_tilt else ("level", "slope")

    def adjusted(free: tuple[str, ...], level: float = start) -> Bundle:
        return bundle.adjust(problem.R, problem.C, trk.intrinsics, P, problem.point, problem.image,
                             problem.pixels, WaterSurface(level, cfg.n), free=free + lens, tol=LEVEL_TOL,
                             on_iteration=step, **problem.held)

    adj = adjusted(free)

    def of_water(sigma):  # the water's parameters' (the lens's go to "lens")
        return {k: v for k, v in sigma.items() if k not in ("k1", "k2")}

    estimated = {"free": list(free), "start_m": start + origin[2], "sigma_m": of_water(adj.sigma),
                 "sigma_given_cameras_m": of_water(adj.sigma_given_cameras),
                 "frame": "consumer GPS (metres)" if "slope" in free else _frame_holder(survey.where),
                 # the frame's height a consumer drone's, to metres: the level matters relative to the model
                 "relative_level": survey.where.tagged is not None and not survey.where.rtk_fixed}
    water = adj.water
    if water.tilted:  # the frame levelled by the water's plane, unless the positions' heights forbid the turn
        known = ~torch.isnan(problem.held["prior_C"][:, 0])
        allowed = georef.tilt_allowed(problem.held["prior_C"][known, :2].numpy(),
                                      problem.held["prior_sigma"][known, 2].numpy())
        if math.hypot(*water.slope) > allowed:
            estimated["slope_refused"] = {"slope": list(water.slope), "allowed": allowed}
            adj = adjusted(("level",))
            estimated.update(free=["level"], sigma_m=of_water(adj.sigma),
                             sigma_given_cameras_m=of_water(adj.sigma_given_cameras))
            return _by_shoreline(P[: len(trk.points)].numpy(), cfg.n, adj, estimated, adjusted)
        level = georef.levelling(water)
        adj = replace(adj, R=adj.R @ torch.as_tensor(level.R.T), C=torch.as_tensor(level.apply(adj.C)),
                      points=torch.as_tensor(level.apply(adj.points)))
        estimated["levelled_deg"] = math.degrees(math.atan(math.hypot(*water.slope)))
        estimated["slope_before_levelling"] = list(water.slope)
        water = WaterSurface(water.level, cfg.n)
        return adj, water, estimated
    return _by_shoreline(P[: len(trk.points)].numpy(), cfg.n, adj, estimated, adjusted)


def _by_shoreline(pinhole: np.ndarray, n: float, adj: Bundle, estimated: dict,
                  adjusted) -> tuple[Bundle, WaterSurface, dict]:
    """The adjustment's level, or, where it is poorly determined and the model's points [P, 3] (pinhole,
    the frame held level by the positions) find the shoreline more surely (`water.shoreline_level`), the
    adjustment again (`adjusted(free, level)`) with the level held at the shoreline's; `estimated` says
    which."""
    from ragsplat.survey import water as water_fit

    sigma = level_sigma(estimated)[0]
    if sigma <= LEVEL_WARN:
        return adj, adj.water, estimated
    shore = water_fit.shoreline_level(pinhole, n, adj.water.level, min(max(3 * sigma, SHORE_SPAN), 1.0))
    if shore is None or shore.sigma >= sigma:
        estimated["shoreline"] = None if shore is None else shore.report()
        return adj, adj.water, estimated
    from_photos = {"level": adj.water.level, "sigma_m": sigma}
    adj = adjusted((), shore.level)
    estimated.update(by="shoreline", shoreline=shore.report(), adjustment=from_photos,
                     sigma_m={"level": shore.sigma}, sigma_given_cameras_m={"level": shore.sigma})
    return adj, adj.water, estimated


def level_sigma(est: dict) -> tuple[float, bool]:
    """(the estimated level's standard deviation that the depths feel, whether it is relative to the model)
    from water.json's "estimated": in a frame whose height is a consumer drone's (GPS or barometer, held to
    metres), the level's uncertainty with the cameras held; else its own. A record without
    "relative_level" is one whose frame was consumer GPS exactly when the slope was free."""
    relative = est.get("relative_level", "slope" in est["free"])
    return float(est["sigma_given_cameras_m" if relative else "sigma_m"]["level"]), relative


def _frame_holder(where: Positions) -> str:
    """What holds the frame's tilt, in words (the positions hold it)."""
    if where.tagged is not None and not where.rtk_fixed:
        return "held by the barometer's heights (decimetres)"
    return "held by the positions"


def _water_report(survey: Survey, fit: Adjusted) -> dict:
    """RUN/water.json: the surface, how the points lie around it, the adjustment's fit, and the estimated
    water, lens and targets' residuals where there are."""
    import numpy as np

    from ragsplat.dataset import layout
    from ragsplat.survey import water as water_fit

    given, origin, adj, P = survey.given, survey.origin, fit.bundle, fit.points
    z = -fit.water.depth(P.numpy())  # height above the surface
    above = z[z >= 0]
    return {"surface": layout.water_json(fit.surface), "described": _describe(fit.surface),
            **({} if fit.estimated is None else {"estimated": fit.estimated}),
            **({} if fit.lens is None else {"lens": fit.lens}),
            **({} if given.edge is None else {
                "edge_fit": given.edge.report(),
                "along_the_reach": water_fit.profile(P.numpy(), fit.water.height(P.numpy()[:, :2]),
                                                     given.edge_points - origin)}),
            "extent_m": (points_box(P.numpy()) + origin[:2]).tolist(),
            "points_above": int((z >= 0).sum()),
            "points_below": int((z < 0).sum()),
            "lowest_above_m": float(np.percentile(above, 1)) if len(above) else None,
            "adjusted": adj is not None,
            "rms_px": None if adj is None else float(adj.residuals.pow(2).mean().sqrt()),
            "iterations": None if adj is None else adj.iterations,
            **({} if fit.gcp_residual is None else {"gcp_residual_m": fit.gcp_residual})}


def _say_water(progress: Progress, surface: WaterSurface, check: dict, t0: float) -> None:
    """Stage 3's lines: the estimated level and its uncertainty, the points around the surface, the fit."""
    if "estimated" in check:  # in a frame held only to metres, its uncertainty relative to the model matters
        est = check["estimated"]
        sigma, relative = level_sigma(est)
        shore = est.get("by") == "shoreline"
        progress.say("water", ("the level from the shoreline, where the model's ground bends into the water "
                               f"({est['shoreline']['straddling']} places)" if shore
                               else "the level estimated from the photos")
                     + f": {surface.level:.3f} m +- {100 * sigma:.1f} cm (1 sigma"
                     + ("" if not relative
                        else ", relative to the model; the frame's height is the GPS's")
                     + ")"
                     + ("" if "levelled_deg" not in est else
                        f"; the frame levelled by the water's plane, {est['levelled_deg']:.2f} degrees")
                     + ("" if "slope_refused" not in est else
                        "; not levelled by the water's plane, tilted "
                        f"{math.degrees(math.atan(math.hypot(*est['slope_refused']['slope']))):.2f} degrees, "
                        "more than the positions' heights leave open ("
                        f"{math.degrees(math.atan(est['slope_refused']['allowed'])):.2f}): give photos with "
                        "the drone's barometric heights, ground control or --water-surface EDGE.csv")
                     + ("" if not shore else "; through the water alone "
                        f"{100 * est['adjustment']['sigma_m']:.1f} cm")
                     + ("" if sigma <= LEVEL_WARN else "; poorly determined (a flat bed, little depth "
                        "variation or no oblique views hide it"
                        + (", and no shoreline was found" if est.get("shoreline") is None else "")
                        + "): measure it and give --water-level, or --water-surface EDGE.csv"))
    lowest = check["lowest_above_m"]
    progress.say("water", f"{check['described']}: {check['points_below']} points below it, "
                 f"{check['points_above']} above"
                 + ("" if lowest is None else f" (the lowest 1 % within {100 * lowest:.1f} cm of it)")
                 + ("" if check["rms_px"] is None
                    else f"; reprojection error {check['rms_px']:.2f} px after the adjustment")
                 + ("" if "lens" not in check else f"; the lens's distortion k1 {check['lens']['k1']:+.4f}, "
                    f"k2 {check['lens']['k2']:+.4f}"), t0)


def train_and_export(survey: Survey, water: Water, stamps: Stamps, progress: Progress, cluster) -> list[Path]:
    """Stage 4: the DEM's size checked over the model's points, then one training and its export
    (`train_one`, `export`), or the tiles' (`train_tiles`) where the survey is larger than a tile."""
    import numpy as np

    from ragsplat.export import sample_count

    cfg = survey.cfg
    lo, hi = water.extent
    sample_count(lo, hi, cfg.resolution)  # the DEM's size over the model's points, before training
    products = [cfg.out / name for name in PRODUCTS]
    tiling, size, overlap = _tiles(cfg, water.model, water.surface, lo, hi)
    if len(tiling) == 1:
        trained = train_one(cfg, water, float(np.prod(hi - lo)), progress)
        export(cfg, water, trained, products, stamps, progress)
    else:
        train_tiles(cfg, water, tiling, size, overlap, products, stamps, progress, cluster)
    return products


def train_one(cfg: SurveyConfig, water: Water, area: float, progress: Progress) -> Path:
    """A survey of one tile imported into RUN/data and trained (resuming) in RUN/train, returned."""
    trained = cfg.out / "train"
    _train(cfg, progress, water.model, cfg.out / "data", trained, water.surface, area)
    return trained


def export(cfg: SurveyConfig, water: Water, trained: Path, products: list[Path], stamps: Stamps,
           progress: Progress) -> None:
    """The products of the training in `trained` (`export.export_run`, with the TVU95 band where
    `cfg.uncertainty` names a model), kept while its checkpoint, the uncertainty's settings and the culls
    are."""
    band = uncertainty_settings(cfg)
    key = _bed_key(_digest(water.key, (trained / "point_cloud.ply").stat().st_mtime_ns, cfg.resolution), band,
                   cfg.culls)
    t0 = time.perf_counter()
    if not stamps.done("export", key, *products):
        from ragsplat.export import export_run, run_orthophotos

        dem, las, png, ortho, apparent = products
        b, on_block = progress.count("[export] bed", "block")
        with b:
            bed = export_run(trained, dem, cfg.resolution, las, None, png, on_block=on_block,
                             **_uncertainty_kwargs(band), **cfg.culls)
        progress.say("export", f"{len(bed.grid)} cells of {cfg.resolution:g} m{_tvu_words(bed)}", t0)
        t1 = time.perf_counter()
        grid = run_orthophotos(trained, bed, ortho, apparent)
        stamps.mark("export", key)
        progress.say("ortho", f"the bed without the water and the photos' mosaic, {grid.width} x "
                     f"{grid.height} cells", t1)


def uncertainty_settings(cfg: SurveyConfig) -> dict | None:
    """What the TVU95 band is made with (None: no band): the model (its JSON), the level's standard deviation
    (`cfg.level_sigma`, else the adjustment's where it estimated the level, RUN/water.json, as the water
    stage reports it; else 0: a given level is taken as exact) and n's (`cfg.n_sigma`)."""
    if cfg.uncertainty is None:
        return None
    from ragsplat.export import read_uncertainty

    level = cfg.level_sigma
    if level is None:
        check = json.loads((cfg.out / "water.json").read_text())
        est = check.get("estimated")
        level = 0.0 if est is None else level_sigma(est)[0]
    return {"model": read_uncertainty(cfg.uncertainty).to_json(), "level_sigma": level,
            "n_sigma": float(cfg.n_sigma)}


def _uncertainty_kwargs(band: dict | None) -> dict:  # `export_run`'s arguments for the band
    if band is None:
        return {}
    from ragsplat.uncertainty import UncertaintyModel

    return {"uncertainty": UncertaintyModel.from_json(band["model"]), "level_sigma": band["level_sigma"],
            "n_sigma": band["n_sigma"]}


def _tvu_words(bed) -> str:
    if bed.tvu95 is None:
        return ""
    import numpy as np

    return f"; TVU95 (band 3) median {100 * float(np.median(bed.tvu95)):.1f} cm"


def train_tiles(cfg: SurveyConfig, water: Water, tiling: list[Tile], size: float, overlap: float,
                products: list[Path], stamps: Stamps, progress: Progress, cluster) -> None:
    """A survey of several tiles: each trained and extracted on its own (`_tile_beds`), their beds merged into
    the products (`_merge`), the layout and the seams' agreement in RUN/tiles.json; kept while the tiles and
    the training's settings are the same."""
    from ragsplat.outputs import write_json

    key = _digest(water.key, cfg.variant, cfg.init, cfg.preset, cfg.iterations, cfg.seed, cfg.max_size,
                  cfg.resolution, [t.to_json() for t in tiling],
                  *([] if cfg.surfel_depth is None else [cfg.surfel_depth]))  # (runs from before it stay)
    band = uncertainty_settings(cfg)
    done_key = _bed_key(key, band, cfg.culls)  # the tiles' models and trainings: `key` alone
    if stamps.done("export", done_key, *products, cfg.out / "tiles.json"):
        return
    t0 = time.perf_counter()
    progress.say("tiles", f"{len(tiling)} tiles of at most {size:.1f} m, overlapping by {overlap:.1f} m, of "
                 f"{', '.join(str(len(t.photos)) for t in tiling)} photos ...")
    beds = _tile_beds(cfg, progress, cluster, water.model, water.surface, tiling, key, band)
    made = [k for k, bed in enumerate(beds) if not isinstance(bed, str)]
    merged = _merge(cfg, water.surface, [tiling[k] for k in made], [beds[k] for k in made], products)
    runs = [{"failed": bed} if isinstance(bed, str) else
            json.loads((cfg.out / "tiles" / str(t.index) / "tile.json").read_text())
            for t, bed in zip(tiling, beds)]
    write_json(cfg.out / "tiles.json", {**merged,
                                        "tiles": [t.to_json() | {"run": r} for t, r in zip(tiling, runs)],
                                        "seconds": time.perf_counter() - t0})
    if len(made) == len(tiling):
        stamps.mark("export", done_key)
    else:  # a rerun tries the tiles left out again
        stamps.clear("export")
    progress.say("export", f"{sum(merged['cells'].values())} cells of {cfg.resolution:g} m from "
                 f"{len(made)} tiles; the overlaps agree to {_seams(merged)} (each tile's: "
                 f"{cfg.out / 'tiles.json'})", t0)


def _seams(merged: dict) -> str:
    """The overlaps' agreement in words: the largest rms and p95 of the height difference over the pairs."""
    pairs = merged["overlap"]
    if not pairs:
        return "nothing (no cell made by two tiles)"
    return (f"{100 * max(p['rms_m'] for p in pairs):.1f} cm rms and "
            f"{100 * max(p['p95_abs_m'] for p in pairs):.1f} cm p95 at worst")


def _tiles(cfg: SurveyConfig, model: Path, surface, lo, hi) -> tuple[list, float, float]:
    """(the survey's tiles (`survey.tiles.plan`) over the model's points' box [lo, hi] (CRS, m), from the
    cameras' footprints on the water, their side, their overlap): the side `cfg.tile_size` or `TILE_GSD`
    ground sample distances (the median camera's height above the water over its focal length); without
    `cfg.tile_size`, one tile for at most `ONE_TILE_PHOTOS` photos."""
    import numpy as np
    import pycolmap

    from ragsplat.survey import sfm, tiles

    rec = pycolmap.Reconstruction(str(model))
    ids, names, R, C, K = sfm.cameras(rec)
    sizes = np.array([[rec.images[i].camera.width, rec.images[i].camera.height] for i in ids], float)
    gsd = float(np.median(-surface.depth(C)) / np.median(K[:, 0]))
    size = cfg.tile_size or TILE_GSD * gsd
    overlap = TILE_OVERLAP * size if cfg.tile_overlap is None else cfg.tile_overlap
    if cfg.tile_size is None and len(names) <= ONE_TILE_PHOTOS:
        size = max(size, float(np.max(np.asarray(hi) - np.asarray(lo))))
    return tiles.plan(lo, hi, tiles.footprints(R, C, K, sizes, surface), names, size, overlap), size, overlap


@dataclass(frozen=True)
class TileJob:
    """One tile's training and bed, as a task (`train_tile`): picklable, paths as strings."""

    cfg: SurveyConfig
    folder: str  # RUN/tiles/K: model/ (the tile's photos only), data/, train/, log.txt, bed.npy, key.txt
    water: dict  # the surface (`layout.water_json`) in the CRS
    bounds: tuple[float, float, float, float]  # the tile's outer box in the CRS (+-inf: open)
    key: str
    band: dict | None = None  # `uncertainty_settings`: the bed's TVU95 too (None: none)

    @property
    def bed_key(self) -> str:  # what the tile's bed.npy was made with
        return _bed_key(self.key, self.band, self.cfg.culls)


def _bed_key(key: str, band: dict | None, culls: dict) -> str:
    """The key of a bed extracted from the trainings of `key`: the uncertainty's settings and the culls
    added where given (a rerun with other culls extracts again without training again)."""
    extra = [*([] if band is None else [band]), *([culls] if culls else [])]
    return _digest(key, *extra) if extra else key


def train_tile(job: TileJob) -> str:
    """Imports, trains (resuming) and extracts one tile; returns the path of its bed (bed.npy: cell centres
    and heights [G, 3] in the CRS, float64, and with `job.band` each cell's TVU95 as a fourth column), written
    last and atomically, so a rerun of a finished tile (a
    retried task, a rerun command) only reads it. Its progress goes to its log.txt; its seconds and the
    worker process's peak memory so far (the largest of the tiles it trained) to tile.json."""
    import resource

    import numpy as np

    from ragsplat.export import export_run
    from ragsplat.outputs import atomic_path, write_json
    from ragsplat.refraction import WaterSurface

    folder = Path(job.folder)
    bed_path, stamp = folder / "bed.npy", folder / "key.txt"
    if bed_path.is_file() and stamp.is_file() and stamp.read_text() == job.bed_key:
        return str(bed_path)
    surface = WaterSurface(**{**job.water, "n": job.cfg.n})
    t0 = time.perf_counter()
    with open(folder / "log.txt", "a") as log:
        progress = _Log(log)
        progress.say("tile", f"tile {folder.name} on worker process {os.getpid()}")
        _train(job.cfg, progress, folder / "model", folder / "data", folder / "train", surface)
        bed = export_run(folder / "train", folder / "dem.tif", job.cfg.resolution, bounds=job.bounds,
                         ortho=folder / ORTHOS[0], ortho_apparent=folder / ORTHOS[1],
                         **_uncertainty_kwargs(job.band), **job.cfg.culls)
        progress.say("export", f"{len(bed.grid)} cells{_tvu_words(bed)}", t0)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB on Linux -> GiB
    write_json(folder / "tile.json", {"seconds": time.perf_counter() - t0, "worker_peak_gib": peak,
                                      "cells": len(bed.grid), "pid": os.getpid()})
    with atomic_path(bed_path) as tmp, open(tmp, "wb") as f:
        np.save(f, bed.absolute() if bed.tvu95 is None else np.column_stack([bed.absolute(), bed.tvu95]))
    stamp.write_text(job.bed_key)
    return str(bed_path)


class _Log(Progress):
    """A tile's progress as lines in its log (a task's bars would interleave on a shared terminal)."""

    def __init__(self, file):
        self.file = file

    def say(self, stage: str, text: str, since: float | None = None) -> None:
        print(line(stage, text, since), file=self.file, flush=True)

    def training(self, total: int, desc: str, initial: int):
        def on_step(trainer) -> None:
            if trainer.step % 100 == 0 or trainer.step == total:
                self.say("train",
                         f"{desc}: step {trainer.step} of {total}, {trainer.num_gaussians} Gaussians")

        return _Silent(), on_step


def _tile_beds(cfg: SurveyConfig, progress: Progress, cluster, model: Path, surface, tiling: list, key: str,
               band: dict | None = None) -> list:
    """Every tile's bed [G_t, 3] (CRS; [G_t, 4] with `band`, the TVU95 fourth): the tiles' models written
    here, then `train_tile` for each, as Dask tasks on the client `cluster(len(tiling))` opens, or one after
    another here without one. A tile whose training fails is left out with a line (its bed: the error, in
    words; its core's cells come from its neighbours' overlap where they reach); OutputError when every tile
    fails."""
    import numpy as np
    import pycolmap

    from ragsplat.dataset import layout
    from ragsplat.errors import OutputError

    jobs = []
    for tile in tiling:
        folder = cfg.out / "tiles" / str(tile.index)
        sub = folder / "model"
        if not ((sub / "key.txt").is_file() and (sub / "key.txt").read_text() == key):
            rec = pycolmap.Reconstruction(str(model))  # the survey's, the tile's other photos left out
            keep = set(tile.photos)
            for i in list(rec.reg_image_ids()):
                if rec.images[i].name not in keep:
                    rec.deregister_frame(rec.images[i].frame_id)
            rec.write_text(str(_fresh(sub)))
            (sub / "key.txt").write_text(key)
        jobs.append(TileJob(cfg, str(folder), layout.water_json(surface), tile.outer, key, band))
    beds: list = [None] * len(jobs)

    def failed(k: int, err: BaseException) -> None:
        beds[k] = f"{type(err).__name__}: {err}"
        progress.say("tiles", f"tile {k} ({len(tiling[k].photos)} photos) left out: {beds[k]} (log: "
                     f"{Path(jobs[k].folder) / 'log.txt'}); its neighbours' overlap fills what it "
                     "reaches, a rerun tries it again")

    with progress.bar(len(jobs), "[tiles] trained", "tile") as b:
        if cluster is None:
            for k, job in enumerate(jobs):
                try:
                    beds[k] = np.load(train_tile(job))
                except Exception as err:  # noqa: BLE001 (whatever a tile's structure or training raises)
                    failed(k, err)
                b.update(1)
        else:
            from ragsplat.scheduling import submitted

            with cluster(len(jobs)) as client:
                calls = {f"tile-{k}-{key}": (train_tile, (job,)) for k, job in enumerate(jobs)}
                for name, future in submitted(client, calls):
                    k = int(name.split("-")[1])
                    if future.status != "finished":
                        failed(k, future.exception())
                    else:
                        beds[k] = np.load(future.result())
                    b.update(1)
    if all(isinstance(bed, str) for bed in beds):
        raise OutputError(f"every tile failed, tile 0 with {beds[0]} (log: {Path(jobs[0].folder) / 'log.txt'}"
                          "); give --tile-size larger than the survey to train it as one tile")
    return beds


def _noise_model(tagged, sigma: dict, labels: list[str]) -> dict:
    """georef.json's account of the noise model of positions from the photos (`survey.exif.sigmas`)."""
    import numpy as np

    used = set(labels)
    fixed = [p.name for p in tagged if p.name in used and p.rtk_fixed]
    other = [p.name for p in tagged if p.name in used and not p.rtk_fixed]
    out = {"model": "by source: RTK fixed (DJI RtkFlag 50) to centimetres, anything else (no RTK flag, or a "
                    "single-point or float solution) as consumer GPS to metres"}
    if fixed:
        own = [p.std_horizontal is not None for p in tagged if p.name in fixed]
        out["rtk_fixed"] = {"count": len(fixed),
                            "sigma_m_median": np.median([sigma[n] for n in fixed], 0).tolist(),
                            "from": f"the photos' RtkStdLon / RtkStdLat / RtkStdHgt ({sum(own)} of "
                                    f"{len(fixed)})"
                                    if any(own) else "--rtk-sigma (or its 2 / 3 cm default)"}
    if other:
        out["consumer_gps"] = {
            "count": len(other), "sigma_m": sigma[other[0]].tolist(),
            "bias": "consumer GPS drifts by metres and each flight line can be 1-1.5 m off the others; no "
                    "per-line bias is estimated: the similarity is fitted to every position within the "
                    "threshold (10 sigma), so their scatter leaves no camera out, and a line's bias shows in "
                    "residual_m as residuals of one sign along it; the adjustment holds these cameras only "
                    "to metres (--gps-sigma), the photos decide their relative positions"}
    return out


def _rounded(threshold):
    """A threshold (one or per correspondence) for georef.json: one number when all are the same."""
    import numpy as np

    values = np.atleast_1d(np.asarray(threshold, float))
    return float(values[0]) if np.ptp(values) == 0 else [round(float(v), 4) for v in values]


def _describe(water) -> str:
    if not (water.tilted or water.curved):
        return f"level {water.level:g} m"
    if water.curved:
        return (f"a plane falling {100 * (water.slope[0] ** 2 + water.slope[1] ** 2) ** 0.5:.2f} % with a "
                f"profile of {len(water.profile.stations)} stations along the reach ({water.level:.3f} m at "
                "x = y = 0)")
    return (f"a plane falling {100 * (water.slope[0] ** 2 + water.slope[1] ** 2) ** 0.5:.2f} % (slope "
            f"{water.slope[0]:+.5f}, {water.slope[1]:+.5f}; {water.level:.3f} m at x = y = 0)")


def _check_near(points, frame, source: Path, what: str, crs: str | None) -> None:
    """ConfigError when `points` [N, 3] lie far from the survey `frame` [M, 3] (the positions or targets):
    more than a kilometre, and ten times the frame's extent, from its centre, they are in another frame (e.g.
    a local one beside EXIF positions in UTM)."""
    import numpy as np

    from ragsplat.errors import ConfigError

    centre = frame[:, :2].mean(0)
    extent = float(np.ptp(frame[:, :2], axis=0).max()) if len(frame) > 1 else 0.0
    far = float(np.linalg.norm(points[:, :2].mean(0) - centre))
    if far > max(1000.0, 10 * extent):
        raise ConfigError(f"{source}: its points lie {far:.0f} m from {what}: give them in the same frame"
                          + (f" ({crs})" if crs else ""))


def _check_above(water, centres) -> None:
    """ConfigError unless some camera of centres [V, 3] is above the water surface."""
    import numpy as np

    from ragsplat.errors import ConfigError

    top = int(np.argmin(water.depth(centres)))
    if not water.depth(centres[top]) < 0:
        raise ConfigError(f"the water surface ({_describe(water)}) is not below any camera (the highest "
                          f"above it is at {centres[top, 2]:g} m, the surface "
                          f"{float(water.height(centres[top, :2])):g} m there)")


def _check_sizes(cfg: SurveyConfig, progress: Progress, photos: list[Path], centres, surface,
                 tagged: list[PhotoPosition] | None = None) -> SurveyConfig:
    """Every size refusal before any work, each in one line with advice that works: the training's images
    must fit `IMAGE_MEMORY` of this machine's memory (without --max-size, the largest that fits is chosen,
    said and returned in the config; smaller still where the photos are finer than the DEM needs,
    `dem_size`), and the DEM's grid over the cameras' footprints must pass
    `export.sample_count` at --resolution (the area is known only after structure from motion; here its lower
    bound: the cameras' extent, grown by each one's nadir footprint where the water level is given)."""
    import os

    import numpy as np
    from PIL import Image

    from ragsplat.errors import ConfigError
    from ragsplat.export import sample_count

    sizes = []
    for p in photos:
        with Image.open(p) as im:
            sizes.append(im.size)
    sizes = np.array(sizes, dtype=np.float64)  # [N, 2] width, height
    longest = sizes.max(1)
    asked = cfg.max_size

    def image_bytes(max_size):
        scale = np.minimum(1.0, max_size / longest) if max_size else 1.0
        return float((3 * np.prod(sizes, 1) * scale * scale).sum())

    from ragsplat.survey.exif import focal_pixels

    focal = focal_pixels(photos[0])
    # the cameras' height above the water: the given surface's, else the barometer's above the take-off
    above = float(np.median(-surface.depth(centres))) if surface is not None else None
    heights = [p.relative_altitude for p in tagged or () if p.relative_altitude]
    height = above if above is not None else float(np.median(heights)) if heights else None
    if cfg.max_size is None and height and focal:
        size = dem_size(int(longest.max()), height / focal, cfg.resolution)
        if size is not None:
            cfg = replace(cfg, max_size=size)
            progress.say("check", f"photos of about {100 * height / focal:.1f} cm a pixel for a DEM of "
                         f"{100 * cfg.resolution:g} cm cells: training on them downscaled to at most "
                         f"{size} px ({DEM_SAMPLES} pixels a cell; --max-size to choose)")
    budget = IMAGE_MEMORY * os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    if image_bytes(cfg.max_size) > budget:
        fits = int(longest.max() * (budget / image_bytes(None)) ** 0.5) // 16 * 16  # bytes go as size^2
        while fits > 16 and image_bytes(fits) > budget:
            fits -= 16
        if asked is not None:
            raise ConfigError(f"{len(photos)} photos at --max-size {cfg.max_size} take "
                              f"{image_bytes(cfg.max_size) / 1e9:.1f} GB in training, over "
                              f"{budget / 1e9:.1f} GB ({IMAGE_MEMORY:.0%} of this machine's memory); give "
                              f"--max-size {fits} or less")
        cfg = replace(cfg, max_size=fits)
        progress.say("check", f"{len(photos)} photos of {int(longest.max())} px take "
                     f"{image_bytes(None) / 1e9:.1f} GB: training on them downscaled to at most {fits} px "
                     f"({image_bytes(fits) / 1e9:.1f} GB; --max-size to choose)")
    lo, hi = centres[:, :2].min(0), centres[:, :2].max(0)
    # the nadir footprint's half width: height over the water x half the sensor / focal
    if above is not None and focal:
        reach = above * 0.5 * sizes[0].max() / focal
        lo, hi = lo - max(reach, 0.0), hi + max(reach, 0.0)
    sample_count(lo, hi, cfg.resolution)  # ConfigError with the resolution that passes
    return cfg


def _fresh(folder: Path) -> Path:
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    return folder


def train_config(preset: str, variant: str, seed: int, init: str, iterations: int | None,
                 surfel_depth: str | None, budget: int | None = None):
    """The `TrainConfig` a survey trains with: the preset's, with the variant, seed and start, the iterations
    and surfel depth where given (None: the preset's), and at most `budget` Gaussians (None: the preset's)."""
    from ragsplat.train import preset_config

    given = {"iterations": iterations, "surfel_depth": surfel_depth}
    train = preset_config(preset, variant=variant, seed=seed, init=init,
                          **{k: v for k, v in given.items() if v is not None})
    if budget is None:
        return train
    return replace(train, densify=replace(train.densify, max_gaussians=budget))


def survey_training(ds: Dataset, preset: str, variant: str, seed: int = 0, init: str = INIT,
                    iterations: int | None = None, surfel_depth: str | None = None, area: float | None = None,
                    budget: int | None = None, overrides: dict | None = None):
    """The `TrainConfig` a survey trains its imported photos `ds` with (`train_config`): the surfel depth
    `surfel_depth_for` its ground sample distance; at most `budget` Gaussians, or where None, the budget of
    `area` m^2 (`GAUSSIANS_PER_GSD2`, at least the preset's, at most `MAX_GAUSSIANS`); `overrides` ({field:
    value}, `train.settings.with_value`) on top; at the survey's scene scale (`at_survey_scale`; a scale
    among the overrides stays)."""
    from ragsplat.train.settings import with_value

    given = (preset, variant, seed, init, iterations, surfel_depth_for(preset, variant, surfel_depth, ds.gsd))
    if budget is None:
        preset_cap = train_config(*given).densify.max_gaussians
        budget = min(max(round(GAUSSIANS_PER_GSD2 * area / ds.gsd**2), preset_cap), MAX_GAUSSIANS)
    train = train_config(*given, budget)
    for name, value in (overrides or {}).items():
        train = with_value(train, name, value)
    return at_survey_scale(train, ds.camera_extent(), ds.gsd)


def dem_size(longest: int, gsd: float, resolution: float) -> int | None:
    """The longest side (px, a multiple of 16) to train photos of `longest` px at `gsd` (m a pixel) with for
    a DEM of `resolution` (m), `DEM_SAMPLES` pixels across a cell; None where that would keep more than
    `DEM_KEEP` of their pixels."""
    scale = gsd * DEM_SAMPLES / resolution
    return None if scale * scale > DEM_KEEP else max(16, math.ceil(longest * scale / 16) * 16)


def surfel_depth_for(preset: str, variant: str, given: str | None, gsd: float) -> str | None:
    """The surfel depth a survey trains with: `given` (--surfel-depth) where given; else the centre's z for
    photos coarser than `COARSE_GSD` (m a pixel) where the preset takes the ray's for a surfel variant; else
    None (the preset's)."""
    from ragsplat.train import preset_config

    train = preset_config(preset, variant=variant)
    coarse = given is None and gsd > COARSE_GSD and train.surfels and train.surfel_depth == "ray"
    return "centre" if coarse else given


def points_box(points):
    """[2, 2] the (lo, hi) corners in x, y of points [P, >=2]: their 1 and 99 %, so that a few stray points
    do not stretch it. The survey's extent (`water.json`'s extent_m) and a tile's area (`seen_area`)."""
    import numpy as np

    return np.percentile(points[:, :2], [1, 99], axis=0)


def seen_area(data: Path) -> float:
    """m^2 of the `points_box` of an imported dataset's points (`dataset.colmap.POINTS`): the ground its
    photos see, bounded as the survey's own extent is. 0 for a dataset without points."""
    import numpy as np

    from ragsplat.dataset.colmap import POINTS

    path = Path(data) / POINTS
    if not path.is_file():
        return 0.0
    lo, hi = points_box(np.load(path))
    return float(np.prod(hi - lo))


def at_survey_scale(train, extent: float, gsd: float):
    """`train` at the scene scale a survey trains with: the cameras' `extent` (m), at most `SCENE_SCALE_GSD`
    ground sample distances of `gsd` (m); a scale `train` sets stays."""
    cap = SCENE_SCALE_GSD * gsd
    return train if train.scene_scale is not None or extent <= cap else replace(train, scene_scale=cap)


def _train(cfg: SurveyConfig, progress: Progress, model: Path, data: Path, out: Path, surface,
           area: float | None = None) -> None:
    """The survey (or a tile's) model imported into `data` (`dataset.colmap`), then trained in `out`
    (resumes), with a Gaussian budget for its `area` (m^2) at its ground sample distance
    (`GAUSSIANS_PER_GSD2`). A tile's area (None) is what its photos see: the box of its imported points
    (`seen_area`), not its core, which its photos overlap on every side: on the long reach the middle tile's
    photos see 1 630 m^2 of which its core holds 854, and the development stretch at that density (41 500
    Gaussians for its 1 010 m^2 instead of 79 250) lost 2.0 points at 1 % of depth."""
    from ragsplat.dataset import layout
    from ragsplat.dataset.colmap import import_colmap
    from ragsplat.dataset.load import load_dataset
    from ragsplat.train import Trainer

    done = import_colmap(model, cfg.images, data, surface, cfg.masks, cfg.crs or layout.LOCAL_CRS,
                         cfg.max_size)
    progress.say("train", f"{'reusing the' if done.reused else 'imported'} survey in {done.root}: "
                          f"{done.images} images")
    ds = load_dataset(done.root, splits=("train",), load_dry=False)
    if area is None:
        area = seen_area(done.root)
    coarse = surfel_depth_for(cfg.preset, cfg.variant, cfg.surfel_depth, ds.gsd) != cfg.surfel_depth
    train = survey_training(ds, cfg.preset, cfg.variant, cfg.seed, cfg.init, cfg.iterations, cfg.surfel_depth,
                            area=area)
    budget, extent = train.densify.max_gaussians, ds.camera_extent()
    capped = "" if train.scene_scale is None else \
        f" ({SCENE_SCALE_GSD:g} GSD; the cameras span {extent:.1f} m)"
    progress.say("train", f"at most {budget} Gaussians for {area:.0f} m^2 at a ground sample distance of "
                 f"{100 * ds.gsd:.2f} cm ({GAUSSIANS_PER_GSD2} per GSD^2, at least the {cfg.preset} "
                 f"preset's, at most {MAX_GAUSSIANS}); scene scale "
                 f"{train.scene_scale or extent:.1f} m{capped}")
    if coarse:
        progress.say("train", f"photos of {100 * ds.gsd:.1f} cm a pixel: trained with the surfels' centre z, "
                     "as the long preset does (river-scale photos; --surfel-depth ray for the ray's)")
    t0 = time.perf_counter()
    trainer = Trainer(train, ds, out)  # the start (the refracted tracks: triangulated once, cached in `data`)
    if trainer.step >= train.iterations:
        return
    bar, on_step = progress.training(train.iterations, f"train {train.variant}", trainer.step)
    try:
        trainer.train(on_step=on_step)
    finally:
        bar.close()
    progress.say("train", f"{train.variant}, {train.iterations} iterations from the {train.init} start, "
                 f"{trainer.num_gaussians} Gaussians", t0)


def _merge(cfg: SurveyConfig, surface, tiling: list, beds: list, products: list[Path]) -> dict:
    """The tiles' beds merged (`survey.tiles.merge`: each cell, with its TVU95 where the beds have a fourth
    column, from the tile whose core holds it) and written as the products, in the frame of the first tile's
    import (its offset; the grid's nodes are on multiples of the resolution in the CRS, the same for every
    tile); returns the merge's report."""
    import numpy as np

    from ragsplat.dataset.load import load_dataset
    from ragsplat.export import Bed, merge_orthophotos, write_dem, write_las, write_png
    from ragsplat.survey import tiles

    grid, _, report = tiles.merge(beds, tiling, cfg.resolution)
    georef = load_dataset(cfg.out / "tiles" / str(tiling[0].index) / "data", splits=()).georef
    offset = np.asarray(georef.offset)
    tvu = grid[:, 3] if grid.shape[1] > 3 else None
    bed = Bed(grid[:, :3] - offset, cfg.resolution, surface.shifted(offset), georef, tvu95=tvu)
    for path, write in zip(products, (write_dem, write_las, write_png)):
        write(path, bed)
    for name, path in zip(ORTHOS, products[3:]):
        drawn = [p for t in tiling if (p := cfg.out / "tiles" / str(t.index) / name).is_file()]
        if drawn:
            merge_orthophotos(drawn, path)
    return report

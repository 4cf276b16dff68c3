"""Stage 4, training a survey of one tile (`train_one`) and the training config a survey's dataset
gets (`survey_training`: the Gaussian budget for its area, the scene scale, the surfels' z).
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from ragsplat.train.config import INIT

if TYPE_CHECKING:

    from ragsplat.dataset.load import Dataset
    from ragsplat.survey.stages.base import Progress, SurveyConfig
    from ragsplat.survey.stages.inputs import Survey
    from ragsplat.survey.stages.water import Water

from ragsplat.survey.stages.base import points_box

# The training's Gaussian budget grows with the survey's area in ground sample distances (GSD^2): 0.17 per
# GSD^2 is the `small` preset's 40 000 on the synthetic survey's 127 m^2 (its points' 1-99 % box) at 2.33 cm;
# a smaller survey keeps the preset's budget. MAX_GAUSSIANS bounds memory (about 1 kB each while training).
GAUSSIANS_PER_GSD2 = 0.17


MAX_GAUSSIANS = 3_000_000


# Photos coarser than this (m a pixel) train with the surfels' centre z where neither --surfel-depth nor the
# preset chose it (the `long` preset's choice): the geometric mean of `small`'s pixel, where the ray's z is
# right, and the long reach's, where the centre's z was ahead (tuning/small.json and long.json,
# "surfel_depth"). A consumer drone's mapping flight is such a survey.
COARSE_GSD = 0.033


# 3DGS scales the position rate and the densification's sizes by the cameras' extent, which grows with a
# tile's length. A survey trains at most at the scale the `long`
# preset was chosen at: its development stretch's 19.82 m at 4.654 cm, 426 ground sample distances
# (`small`'s 4.6 m are 198; both keep their own). Larger tiles trained at it like the stretch
# (docs/lab/performance.md).
SCENE_SCALE_GSD = 426


# Photos finer than the DEM needs train downscaled to this many pixels across a DEM cell: two samples a
# cell resolve it, and the training's time goes with the pixels (OpenDroneMap's default dense cloud,
# --pc-quality medium, likewise works on photos at half their size). A downscale that would keep more than
# DEM_KEEP of the pixels is not made: it would save little time for the detail it loses.
DEM_SAMPLES = 2


DEM_KEEP = 0.5


def training_size(survey: Survey, water: Water, progress: Progress) -> SurveyConfig:
    """The survey's config with the size its photos train at: without --max-size, at most `dem_size` where
    the photos are finer than the DEM needs, their ground sample distance taken at the water from the
    adjusted cameras (a barometer's heights are above the take-off, not the water); RUN/survey.json
    rewritten where that changes the size."""
    import numpy as np

    from ragsplat.camera import sample_distance
    from ragsplat.dataset.colmap import read_model
    from ragsplat.survey import sfm
    from ragsplat.survey.stages.inputs import write_config

    cfg = survey.cfg
    if survey.given_size is not None:
        return cfg
    rec = read_model(water.model)
    _, _, R, centres, K = sfm.cameras(rec)
    level = float(water.surface.height(np.median(centres[:, :2], axis=0)[None])[0])
    gsd = sample_distance(R, centres, K[:, 0], level)
    longest = max(max(cam.width, cam.height) for cam in rec.cameras.values())
    size = None if gsd is None else dem_size(longest, gsd, cfg.resolution)
    if size is None or (cfg.max_size is not None and cfg.max_size <= size):
        return cfg
    cfg = replace(cfg, max_size=size)
    write_config(cfg)
    progress.say("train", f"photos of {100 * gsd:.2f} cm a pixel at the water for a DEM of "
                 f"{100 * cfg.resolution:g} cm cells: training on them downscaled to at most {size} px "
                 f"({DEM_SAMPLES} pixels a cell; --max-size to choose)")
    return cfg


def dem_size(longest: int, gsd: float, resolution: float) -> int | None:
    """The longest side (px, a multiple of 16) to train photos of `longest` px at `gsd` (m a pixel) with for
    a DEM of `resolution` (m), `DEM_SAMPLES` pixels across a cell; None where that would keep more than
    `DEM_KEEP` of their pixels."""
    scale = gsd * DEM_SAMPLES / resolution
    return None if scale * scale > DEM_KEEP else max(16, math.ceil(longest * scale / 16) * 16)


def train_one(cfg: SurveyConfig, water: Water, area: float, progress: Progress) -> Path:
    """A survey of one tile imported into RUN/data and trained (resuming) in RUN/train, returned."""
    trained = cfg.out / "train"
    train_survey(cfg, progress, water.model, cfg.out / "data", trained, water.surface, area)
    return trained


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


def surfel_depth_for(preset: str, variant: str, given: str | None, gsd: float) -> str | None:
    """The surfel depth a survey trains with: `given` (--surfel-depth) where given; else the centre's z for
    photos coarser than `COARSE_GSD` (m a pixel) where the preset takes the ray's for a surfel variant; else
    None (the preset's)."""
    from ragsplat.train import preset_config

    train = preset_config(preset, variant=variant)
    coarse = given is None and gsd > COARSE_GSD and train.surfels and train.surfel_depth == "ray"
    return "centre" if coarse else given


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


def train_survey(cfg: SurveyConfig, progress: Progress, model: Path, data: Path, out: Path, surface,
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

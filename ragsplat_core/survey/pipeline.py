"""`ragsplat survey`'s stages as library functions: from a survey's photos to its DEM, every stage cached in
the run folder and skipped by a rerun whose inputs are the same (`run`, one call a stage; the command only
parses arguments). Before any work, everything that can be refused is (`check_inputs`); then

1. structure from motion (`structure_from_motion`, `survey.sfm`: pycolmap SIFT, every pair matched, or each
   photo with its spatial neighbours above `sfm.EXHAUSTIVE_MAX` photos, incremental mapping) -> RUN/sfm/;
2. georeferencing (`georeference`): the similarity that takes the model's camera centres to the RTK
   positions (given, or from the photos' EXIF GPS and DJI XMP, `dataset.exif`), or the ground control points
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

import time
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:

    from ragsplat.survey.stages.base import SurveyConfig
    from ragsplat.survey.stages.inputs import Survey
    from ragsplat.survey.stages.water import Water

from ragsplat.survey.stages.base import PRODUCTS, Progress, Stamps
from ragsplat.survey.stages.georeference import georeference
from ragsplat.survey.stages.inputs import check_inputs
from ragsplat.survey.stages.products import export
from ragsplat.survey.stages.structure import structure_from_motion
from ragsplat.survey.stages.tiled import plan_tiles, train_tiles
from ragsplat.survey.stages.training import train_one, training_size
from ragsplat.survey.stages.water import adjust_through_water


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
    report = write_report(survey.cfg.out, progress.said, len(survey.photos))
    progress.say("report", f"{report}", t0)
    return [*products, report]


def train_and_export(survey: Survey, water: Water, stamps: Stamps, progress: Progress, cluster) -> list[Path]:
    """Stage 4: the DEM's size checked over the model's points, the photos' size chosen (`training_size`),
    then one training and its export (`train_one`, `export`), or the tiles' (`train_tiles`) where the survey
    is larger than a tile."""
    import numpy as np

    from ragsplat.export import sample_count

    cfg = training_size(survey, water, progress)
    lo, hi = water.extent
    sample_count(lo, hi, cfg.resolution)  # the DEM's size over the model's points, before training
    products = [cfg.out / name for name in PRODUCTS]
    tiling, size, overlap = plan_tiles(cfg, water.model, water.surface, lo, hi)
    if len(tiling) == 1:
        trained = train_one(cfg, water, float(np.prod(hi - lo)), progress)
        export(cfg, water, trained, products, stamps, progress)
    else:
        train_tiles(cfg, water, tiling, size, overlap, products, stamps, progress, cluster)
    return products

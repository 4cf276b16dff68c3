"""Stages 4 and 5 for a survey larger than a tile (`train_tiles`): the tiles planned by ground and
photos (`plan_tiles`), each trained and extracted on its own (a Dask task each where a client is
given), their beds and orthophotos merged.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:

    from ragsplat.survey.stages.base import Stamps, SurveyConfig
    from ragsplat.survey.stages.water import Water
    from ragsplat.survey.tiles import Tile

from ragsplat.outputs import Stamp, digest
from ragsplat.survey.stages.base import ORTHOS, Progress, _Silent, fresh_folder, line
from ragsplat.survey.stages.products import bed_key, tvu_words, uncertainty_kwargs, uncertainty_settings
from ragsplat.survey.stages.training import train_survey

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


def train_tiles(cfg: SurveyConfig, water: Water, tiling: list[Tile], size: float, overlap: float,
                products: list[Path], stamps: Stamps, progress: Progress, cluster) -> None:
    """A survey of several tiles: each trained and extracted on its own (`_tile_beds`), their beds merged into
    the products (`merge_tiles`), the layout and the seams' agreement in RUN/tiles.json; kept while the tiles
    and the training's settings are the same."""
    from ragsplat.outputs import write_json

    key = digest(water.key, cfg.variant, cfg.init, cfg.preset, cfg.iterations, cfg.seed, cfg.max_size,
                  cfg.resolution, [t.to_json() for t in tiling],
                  *([] if cfg.surfel_depth is None else [cfg.surfel_depth]))  # (runs from before it stay)
    band = uncertainty_settings(cfg)
    done_key = bed_key(key, band, cfg.culls)  # the tiles' models and trainings: `key` alone
    if stamps.done("export", done_key, *products, cfg.out / "tiles.json"):
        return
    t0 = time.perf_counter()
    progress.say("tiles", f"{len(tiling)} tiles of at most {size:.1f} m, overlapping by {overlap:.1f} m, of "
                 f"{', '.join(str(len(t.photos)) for t in tiling)} photos ...")
    beds = _tile_beds(cfg, progress, cluster, water.model, water.surface, tiling, key, band)
    made = [k for k, bed in enumerate(beds) if not isinstance(bed, str)]
    merged = merge_tiles(cfg, water.surface, [tiling[k] for k in made], [beds[k] for k in made], products)
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


def plan_tiles(cfg: SurveyConfig, model: Path, surface, lo, hi) -> tuple[list, float, float]:
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
    folder: str  # RUN/tiles/K: model/ (the tile's photos only), data/, train/, log.txt, bed.npy, key.json
    water: dict  # the surface (`layout.water_json`) in the CRS
    bounds: tuple[float, float, float, float]  # the tile's outer box in the CRS (+-inf: open)
    key: str
    band: dict | None = None  # `uncertainty_settings`: the bed's TVU95 too (None: none)

    @property
    def bed_key(self) -> str:  # what the tile's bed.npy was made with
        return bed_key(self.key, self.band, self.cfg.culls)


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
    from ragsplat.water_surface import WaterSurface

    folder = Path(job.folder)
    bed_path, stamp = folder / "bed.npy", Stamp(folder / "key.json")
    if bed_path.is_file() and stamp.holds(job.bed_key):
        return str(bed_path)
    surface = WaterSurface(**{**job.water, "n": job.cfg.n})
    t0 = time.perf_counter()
    with open(folder / "log.txt", "a") as log:
        progress = _Log(log)
        progress.say("tile", f"tile {folder.name} on worker process {os.getpid()}")
        train_survey(job.cfg, progress, folder / "model", folder / "data", folder / "train", surface)
        bed = export_run(folder / "train", folder / "dem.tif", job.cfg.resolution, bounds=job.bounds,
                         ortho=folder / ORTHOS[0], ortho_apparent=folder / ORTHOS[1],
                         **uncertainty_kwargs(job.band), **job.cfg.culls)
        progress.say("export", f"{len(bed.grid)} cells{tvu_words(bed)}", t0)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB on Linux -> GiB
    write_json(folder / "tile.json", {"seconds": time.perf_counter() - t0, "worker_peak_gib": peak,
                                      "cells": len(bed.grid), "pid": os.getpid()})
    with atomic_path(bed_path) as tmp, open(tmp, "wb") as f:
        np.save(f, bed.absolute() if bed.tvu95 is None else np.column_stack([bed.absolute(), bed.tvu95]))
    stamp.write(job.bed_key)
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
        stamp = Stamp(sub / "key.json")
        if not stamp.holds(key):
            rec = pycolmap.Reconstruction(str(model))  # the survey's, the tile's other photos left out
            keep = set(tile.photos)
            for i in list(rec.reg_image_ids()):
                if rec.images[i].name not in keep:
                    rec.deregister_frame(rec.images[i].frame_id)
            rec.write_text(str(fresh_folder(sub)))
            stamp.write(key)
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


def merge_tiles(cfg: SurveyConfig, surface, tiling: list, beds: list, products: list[Path]) -> dict:
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

"""`ragsplat survey IMAGES [--positions positions.csv | --gcp gcp.csv --gcp-pixels pixels.csv]
--water-level Z | --water-surface EDGE.csv --out RUN [--crs EPSG:N] [--masks DIR] [--tile-size M] [--jobs N |
--scheduler ADDRESS]`: from the drone's photos to a DEM, by the stages of `ragsplat.survey.pipeline`
(which says each), every stage cached in RUN and skipped by a rerun whose inputs are the same. Without
--positions or --gcp the camera positions come from the photos' own metadata (`dataset.exif`: EXIF GPS, DJI's
XMP with its RTK flag and accuracies), converted to the UTM zone of their mean position (or --crs), in which
the products are then written. A survey larger than a tile trains its tiles as Dask tasks: on --jobs local
worker processes, or on an existing cluster (--scheduler). With --uncertainty MODEL.json (a fitted model,
`python -m tools.fit_uncertainty`) the DEM gets band 3, each cell's TVU95 (docs/uncertainty.md).
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from pathlib import Path

from ragsplat.cli.args import (
    config_option,
    count,
    cull_arguments,
    cull_overrides,
    finite_float,
    non_negative_float,
    out_dir,
    positive_float,
    positive_int,
    refractive_index,
    uncertainty_arguments,
    uncertainty_options,
)


def level_or_auto(text: str) -> float | str:
    from ragsplat.survey.stages.base import AUTO

    return AUTO if text.strip().lower() == AUTO else finite_float(text)


def lens_or_file(text: str) -> str:
    from ragsplat.survey.stages.base import LENSES

    if text in LENSES or Path(text).is_file():
        return text
    raise argparse.ArgumentTypeError(f"{text}: radial, pinhole or a calibration file (JSON with k1, k2)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ragsplat.rasterize_surfels import DEPTHS
    from ragsplat.survey.stages.base import STAGES, SurveyConfig
    from ragsplat.survey.stages.tiled import TILE_GSD
    from ragsplat.survey.stages.training import COARSE_GSD
    from ragsplat.train.config import PRESETS, VARIANTS
    from ragsplat.train.defaults import JOBS, SURVEY_VARIANTS, survey_variant

    def option(group, name, *flags, **kw):  # each option's default and help are its field's
        config_option(group, SurveyConfig, name, *flags, **kw)

    option(parser, "images", "images", type=Path, metavar="IMAGES")
    frame = parser.add_mutually_exclusive_group()
    option(frame, "positions", type=Path, metavar="CSV")
    option(frame, "gcp", type=Path, metavar="CSV")
    option(parser, "gcp_pixels", type=Path, metavar="CSV")
    option(parser, "gcp_sigma", type=positive_float, metavar="M")
    surface = parser.add_mutually_exclusive_group()
    option(surface, "water_level", type=level_or_auto, metavar="Z|auto")
    option(surface, "water_surface", type=Path, metavar="CSV")
    option(parser, "out", required=True, type=out_dir)
    option(parser, "n", type=refractive_index)
    option(parser, "crs", metavar="CRS")
    option(parser, "masks", type=Path, metavar="DIR")
    option(parser, "lens", type=lens_or_file, metavar="radial|pinhole|FILE")
    option(parser, "no_water_adjustment", action="store_true")
    option(parser, "rtk_sigma", type=positive_float, nargs=2, metavar=("H", "V"))
    option(parser, "gps_sigma", type=positive_float, nargs=2, metavar=("H", "V"))
    option(parser, "barometer_sigma", type=positive_float, metavar="M")
    option(parser, "variant", choices=list(VARIANTS),
           more=f" (default: the preset's best, {survey_variant(SurveyConfig.preset)}; "
                + "; ".join(f"with --preset {p} {v}" for p, v in SURVEY_VARIANTS.items()) + ")")
    option(parser, "init", choices=["triangulated", "refracted"])
    option(parser, "preset", choices=list(PRESETS))
    option(parser, "iterations", type=positive_int)
    option(parser, "surfel_depth", choices=DEPTHS,
           more=f"; default: the preset's, the centre's for photos coarser than {100 * COARSE_GSD:g} cm a "
                "pixel")
    option(parser, "seed", type=count)
    option(parser, "resolution", type=positive_float, metavar="M")
    option(parser, "max_size", type=positive_int, metavar="PX")
    option(parser, "stop_after", choices=STAGES[:3], metavar="STAGE")
    option(parser, "tile_size", type=positive_float, metavar="M",
           more=f" (default: {TILE_GSD:,} ground sample distances; a survey that fits is one tile)")
    option(parser, "tile_overlap", type=non_negative_float, metavar="M")
    parser.add_argument("--jobs", type=positive_int, metavar="N",
                        help=f"train the tiles on N local Dask workers at once, each with cores / N threads "
                             f"(default: one per tile up to {2 * JOBS - 1} tiles, the cores shared, else "
                             f"{JOBS}; 1: one after another in this process)")
    parser.add_argument("--scheduler", metavar="ADDRESS",
                        help="train the tiles on the Dask cluster whose scheduler is at ADDRESS "
                             "(tcp://host:8786; its workers need ragsplat and this run's paths)")
    cull_arguments(parser)
    uncertainty_arguments(parser, "the adjustment's estimate where it estimated the level; a given level: 0")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


class _Printed:
    """The pipeline's progress as this command shows it: one line per stage on stderr, tqdm bars."""

    def __init__(self, quiet: bool, check):
        self.quiet, self.check = quiet, check

    def say(self, stage: str, text: str, since: float | None = None) -> None:
        from ragsplat.survey.stages.base import line

        print(line(stage, text, since), file=sys.stderr, flush=True)

    def bar(self, total: int, desc: str, unit: str):
        from ragsplat.cli.progress import bar

        return bar(total, desc, unit, disable=self.quiet)

    def count(self, desc: str, unit: str):
        from ragsplat.cli.progress import count_bar

        return count_bar(desc, unit, self.quiet)

    def training(self, total: int, desc: str, initial: int):
        from ragsplat.cli.progress import training_bar

        return training_bar(total, desc, initial, self.quiet, check=self.check)


def run(args: argparse.Namespace) -> int:
    from dataclasses import fields

    from ragsplat.cli.cluster import client
    from ragsplat.cli.progress import deferred_interrupts
    from ragsplat.survey import pipeline
    from ragsplat.survey.stages.base import SurveyConfig
    from ragsplat.train.defaults import tile_workers

    uncertainty_options(args)  # a sigma without a model, or a file that is not one: refused before any work
    args.culls = cull_overrides(args)  # a rerun with other culls extracts again, without training again
    settings = {f.name: getattr(args, f.name) for f in fields(SurveyConfig)}
    cfg = SurveyConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in settings.items()})

    @contextlib.contextmanager
    def cluster(tasks: int):
        workers = min(args.jobs, tasks) if args.jobs else tile_workers(tasks)
        with client(workers, args.scheduler) as (c, where):
            print(f"[tiles] on {where}; each tile's log: {args.out / 'tiles' / 'K' / 'log.txt'}",
                  file=sys.stderr, flush=True)
            yield c

    with deferred_interrupts() as check:  # Ctrl-C: the trainer checkpoints its finished steps, then stops
        products = pipeline.run(cfg, _Printed(args.no_progress, check),
                                cluster if args.jobs != 1 or args.scheduler else None)
    for path in products:
        print(path)
    return 0

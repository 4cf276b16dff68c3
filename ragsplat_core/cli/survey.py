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


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from dataclasses import fields

    from ragsplat.rasterize_surfels import DEPTHS
    from ragsplat.survey.stages.base import STAGES, SurveyConfig
    from ragsplat.survey.stages.tiled import TILE_GSD
    from ragsplat.survey.stages.training import COARSE_GSD
    from ragsplat.train.config import PRESETS, VARIANTS
    from ragsplat.train.defaults import JOBS, SURVEY_VARIANTS, survey_variant

    default = {f.name: f.default for f in fields(SurveyConfig)}  # each option's default is its field's

    parser.add_argument("images", type=Path, metavar="IMAGES",
                        help="the folder of the survey's photos (JPEG/PNG)")
    frame = parser.add_mutually_exclusive_group()
    frame.add_argument("--positions", type=Path, metavar="CSV",
                       help="camera centres as the drone's RTK recorded them: CSV with header name,x,y,z "
                            "(image file name; metres, z up, the frame of the water level and the products); "
                            "without --positions or --gcp the positions come from the photos' EXIF GPS and "
                            "DJI XMP")
    frame.add_argument("--gcp", type=Path, metavar="CSV",
                       help="ground control points instead: CSV with header name,x,y,z (as surveyed), with "
                            "--gcp-pixels")
    parser.add_argument("--gcp-pixels", type=Path, metavar="CSV",
                        help="where each target is in the photos: CSV with header image,name,u,v (pixels, "
                             "the image's top-left corner at 0,0)")
    parser.add_argument("--gcp-sigma", type=positive_float, default=default["gcp_sigma"], metavar="M",
                        help="ground control accuracy, each axis (m; default %(default)s)")
    surface = parser.add_mutually_exclusive_group()
    surface.add_argument("--water-level", type=level_or_auto, default=default["water_level"],
                         metavar="Z|auto",
                         help="height of the calm, flat water surface in the positions' frame (m), or auto "
                              "(the default without --water-surface): the level estimated from the photos, "
                              "in the adjustment through the water")
    surface.add_argument("--water-surface", type=Path, metavar="CSV",
                         help="points on the water's edge as measured along both banks (RTK): CSV with "
                              "header x,y,z, the positions' frame; a river's sloping surface is fitted to "
                              "them")
    parser.add_argument("--out", required=True, type=out_dir, help="run directory (a rerun resumes)")
    parser.add_argument("--n", type=refractive_index, default=default["n"],
                        help="refractive index of the water (%(default)s)")
    parser.add_argument("--crs", metavar="CRS",
                        help="the positions' CRS for the products, e.g. EPSG:32633; with positions from the "
                             "photos the projected CRS (metres) they are converted to (default: the UTM zone "
                             "of their mean position)")
    parser.add_argument("--masks", type=Path, metavar="DIR",
                        help="masks named <image name>.png, zero where pixels are left out of training")
    parser.add_argument("--lens", choices=["radial", "pinhole"], default=default["lens"],
                        help="radial: the lens's radial distortion k1, k2 estimated in the adjustment "
                             "through the water (one lens for all photos) and the photos undistorted for "
                             "training; pinhole: none (photos already undistorted); default %(default)s")
    parser.add_argument("--no-water-adjustment", action="store_true",
                        help="keep the pinhole structure-from-motion poses (only for comparison: through "
                             "water they are tilted and the bed comes out too deep)")
    parser.add_argument("--rtk-sigma", type=positive_float, nargs=2, metavar=("H", "V"),
                        help="RTK position accuracy, horizontal and vertical (m; default 0.02 0.03, or with "
                             "positions from the photos each RTK-fixed photo's own reported accuracy)")
    parser.add_argument("--gps-sigma", type=positive_float, nargs=2, default=default["gps_sigma"],
                        metavar=("H", "V"),
                        help="accuracy of positions from the photos without RTK fix (consumer GPS), "
                             "horizontal and vertical (m; default %(default)s)")
    parser.add_argument("--barometer-sigma", type=positive_float, default=default["barometer_sigma"],
                        metavar="M",
                        help="accuracy of those photos' heights where they come from the drone's barometer "
                             "(DJI RelativeAltitude, above the take-off point) (m; default %(default)s)")
    parser.add_argument("--variant", choices=list(VARIANTS),
                        help=f"(default: the preset's best, {survey_variant(default['preset'])}; "
                             + "; ".join(f"with --preset {p} {v}" for p, v in SURVEY_VARIANTS.items()) + ")")
    parser.add_argument("--init", default=default["init"], choices=["triangulated", "refracted"],
                        help="(default: %(default)s)")
    parser.add_argument("--preset", default=default["preset"], choices=list(PRESETS),
                        help="training preset (%(default)s; long for river-scale photos of a few cm a "
                             "pixel, whose surfels' centre z the default takes for them)")
    parser.add_argument("--iterations", type=positive_int, help="override the preset's iteration count")
    parser.add_argument("--surfel-depth", choices=DEPTHS,
                        help="a surfel sample's z in training: where the pixel's ray meets it (ray) or its "
                             "centre's (centre, as gsplat does on a GPU); default: the preset's, the "
                             f"centre's for photos coarser than {100 * COARSE_GSD:g} cm a pixel")
    parser.add_argument("--seed", type=count, default=default["seed"],
                        help="training seed (default %(default)s)")
    parser.add_argument("--resolution", type=positive_float, default=default["resolution"], metavar="M",
                        help="DEM cell (%(default)s m)")
    parser.add_argument("--max-size", type=positive_int, metavar="PX",
                        help="downscale images for training so their longer side is at most PX pixels "
                             "(default: full size, or two pixels a DEM cell where that halves the pixels, or "
                             "the largest that fits the memory)")
    parser.add_argument("--stop-after", choices=STAGES[:3], metavar="STAGE",
                        help="stop after this stage (sfm, georef or water: the poses without training)")
    parser.add_argument("--tile-size", type=positive_float, metavar="M",
                        help="split a larger survey into tiles of at most M metres a side, each trained on "
                             f"its own and their DEMs merged (default: {TILE_GSD:,} ground sample "
                             "distances; a survey that fits is one tile)")
    parser.add_argument("--tile-overlap", type=non_negative_float, metavar="M",
                        help="each tile's overlap with its neighbours (m; default: a tenth of the side)")
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

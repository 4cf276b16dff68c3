"""Train a survey's imported photos again as `ragsplat survey` trains them, and export its products as the
survey does, for choices on a development survey (or a lent GPU, which has no pycolmap to run the survey):
`python -m tools.retrain RUN/data OUT --budget N [--iterations N] [--seed S] [--preset small]
[--variant V] [--set PARAM=VALUE ...] [--surfel-depth ray|centre]`.

RUN/data is the folder a survey imported its model into (`dataset.colmap.import_colmap`: the undistorted
photos, the cameras and the cached refracted tracks); `--budget` is the Gaussian budget the survey's log
printed for it ("at most N Gaussians for ..."). OUT gets the training (resumes) and dem.tif, bed.laz and
depth.png with the extraction's defaults, then times.json (start, training and export seconds). Score with
`ragsplat score OUT/dem.tif --truth DATASET`.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from ragsplat.dataset.load import load_dataset
from ragsplat.errors import ConfigError
from ragsplat.export import export_run
from ragsplat.outputs import write_json
from ragsplat.rasterize_surfels import DEPTHS
from ragsplat.survey.stages.training import survey_training
from ragsplat.train import Trainer, settings
from ragsplat.train.config import INIT
from ragsplat.train.defaults import survey_variant


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.retrain", description=__doc__.split("\n\n")[0])
    parser.add_argument("data", type=Path, help="a survey's imported data (RUN/data)")
    parser.add_argument("out", type=Path, help="the training's folder (a rerun resumes)")
    parser.add_argument("--budget", type=int, required=True, help="the survey's Gaussian budget (its log)")
    parser.add_argument("--iterations", type=int, default=None, help="(the preset's)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--preset", default="small")
    parser.add_argument("--variant", default=None, help="(the preset's survey variant)")
    parser.add_argument("--set", nargs="+", default=[], metavar="PARAM=VALUE")
    parser.add_argument("--surfel-depth", choices=DEPTHS, default=None, help="(the preset's)")
    args = parser.parse_args(argv)
    try:
        overrides = settings.parse(args.set)
    except ConfigError as e:
        parser.error(str(e))
    ds = load_dataset(args.data, splits=("train",), load_dry=False)
    train = survey_training(ds, args.preset, args.variant or survey_variant(args.preset), args.seed, INIT,
                            args.iterations, args.surfel_depth, budget=args.budget, overrides=overrides)
    t0 = time.perf_counter()
    trainer = Trainer(train, ds, args.out)
    t1 = time.perf_counter()
    trainer.train()
    t2 = time.perf_counter()
    bed = export_run(args.out, args.out / "dem.tif", 0.05, args.out / "bed.laz", None, args.out / "depth.png")
    t3 = time.perf_counter()
    write_json(args.out / "times.json", {"start_s": t1 - t0, "train_s": t2 - t1, "export_s": t3 - t2,
                                         "gaussians": trainer.num_gaussians, "cells": len(bed.grid)})
    print(f"{args.out}: {train.variant}, {train.iterations} steps in {t2 - t1:.0f} s, export {t3 - t2:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())

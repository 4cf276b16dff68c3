"""`ragsplat train --data DIR --variant full --out DIR [--preset NAME] [--seed S] [--iterations N]`, or from a
survey: `ragsplat train --colmap MODEL --images DIR --water-level Z [--n 1.33] [--masks DIR] [--crs EPSG:N]
--out DIR`.

Trains one variant on a dataset directory, with a progress bar (loss, PSNR on the training view, Gaussian
count, time left); rerunning with the same --out resumes from the last checkpoint. A COLMAP survey is first
imported into --out/data (`dataset.colmap`: undistorted images, the water level, the georeference), once.
Writes config.json, ckpt.pt, point_cloud.ply (3DGS PLY) and train_stats.json into --out.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import fields
from pathlib import Path

from ragsplat.cli.args import (
    config_option,
    count,
    dataset_dir,
    finite_float,
    out_dir,
    positive_float,
    positive_int,
    refractive_index,
)
from ragsplat.errors import TrainingDiverged


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ragsplat.rasterize import BACKENDS
    from ragsplat.rasterize_surfels import DEPTHS
    from ragsplat.train.config import INITS, PRESETS, VARIANTS, TrainConfig

    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--data", type=dataset_dir, help="dataset directory (transforms.json, images/)")
    source.add_argument("--colmap", type=Path, metavar="MODEL",
                        help="a COLMAP model folder (cameras/images/points3D, .bin or .txt): your own survey")
    survey = parser.add_argument_group("survey import (with --colmap)")
    survey.add_argument("--images", type=Path, metavar="DIR",
                        help="the folder the model's image names refer to")
    survey.add_argument("--masks", type=Path, metavar="DIR",
                        help="masks named <image name>.png, zero where pixels are left out (glint, people)")
    survey.add_argument("--crs", metavar="CRS", help="the model's CRS for the products, e.g. EPSG:32633")
    survey.add_argument("--max-size", type=positive_int, metavar="PX",
                        help="downscale images so their longer side is at most PX pixels")
    def option(name, *flags, **kw):  # each option's help is its field's; unset: the preset's value
        config_option(parser, TrainConfig, name, *flags, **{"default": None, **kw})

    option("variant", choices=list(VARIANTS), default=TrainConfig.variant)
    parser.add_argument("--out", required=True, type=out_dir,
                        help="output directory (resumes if it holds a checkpoint)")
    option("preset", choices=list(PRESETS), default=TrainConfig.preset)
    option("seed", type=count, default=TrainConfig.seed)
    option("iterations", type=positive_int)
    option("surfel_depth", choices=DEPTHS)
    option("init", choices=list(INITS), more="; with --colmap: the model's points, else triangulated")
    option("init_depth", type=positive_float)
    option("init_count", type=positive_int, metavar="N")
    option("init_fill", type=finite_float, metavar="M")
    option("init_points", metavar="FILE.npy")
    option("init_robust", action="store_true")
    option("water_level", type=finite_float, metavar="Z", more="; required with --colmap")
    option("water_n", "--n", type=refractive_index, metavar="N")
    option("optimize_water", choices=["level", "level+n"])
    option("checkpoint_every", type=count, metavar="N")
    option("backend", choices=list(BACKENDS))
    option("device")
    option("compile_refraction", action="store_true")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from ragsplat.cli.progress import deferred_interrupts, training_bar
    from ragsplat.dataset.load import load_dataset
    from ragsplat.train import Trainer, preset_config
    from ragsplat.train.config import TrainConfig

    # every TrainConfig field this command has an option for, where given
    overrides = {f.name: getattr(args, f.name) for f in fields(TrainConfig)
                 if f.name != "preset" and getattr(args, f.name, None) is not None}
    data = args.data if args.colmap is None else _import(args, overrides)
    cfg = preset_config(args.preset, **overrides)
    ds = load_dataset(data, splits=("train",), load_dry=False)
    trainer = Trainer(cfg, ds, args.out)
    if trainer.step:
        extended = "" if trainer.extended_from is None else \
            f", extended from {trainer.extended_from} iterations (the schedule stretches to {cfg.iterations})"
        print(f"resumed from step {trainer.step} of {cfg.iterations}{extended} ({args.out})", file=sys.stderr)
    with deferred_interrupts() as check:
        bar, on_step = training_bar(cfg.iterations, f"train {cfg.variant}", trainer.step, args.no_progress,
                                    check=check)
        try:
            stats = trainer.train(on_step=on_step)
        except TrainingDiverged as err:
            raise TrainingDiverged(f"{err}; last checkpoint kept in {args.out}") from None
        finally:
            bar.close()
    print(json.dumps(stats, indent=1))
    return 0


def _import(args: argparse.Namespace, overrides: dict) -> Path:
    """Import the survey into RUN/data (once) and, unless an --init-depth is given, start from the model's
    points, or points triangulated from the images when it has none (depths x n). Returns the dataset
    directory."""
    from ragsplat.dataset import layout
    from ragsplat.dataset.colmap import POINTS, import_colmap
    from ragsplat.errors import ConfigError
    from ragsplat.outputs import claim
    from ragsplat.train.checkpoint import CHECKPOINT
    from ragsplat.water_surface import WaterSurface

    missing = [flag for flag, value in (("--images", args.images), ("--water-level", args.water_level))
               if value is None]
    if missing:
        raise ConfigError(f"--colmap needs {' and '.join(missing)}")
    claim(args.out, "train run", legacy=(CHECKPOINT,))  # before the import writes into it
    # the imported dataset carries the water: not an override of it
    water = WaterSurface(overrides.pop("water_level"), overrides.pop("water_n", 1.33))  # ValueError: one line
    done = import_colmap(args.colmap, args.images, args.out / "data", water, args.masks,
                         args.crs or layout.LOCAL_CRS, args.max_size)
    offset = ", ".join(f"{x:g}" for x in done.georef.offset)
    print(f"{'reusing the' if done.reused else 'imported'} survey in {done.root}: {done.images} images, "
          f"{done.cameras} camera(s), {done.undistorted} resampled, {done.points} points; local origin at "
          f"({offset}) of {args.crs or 'the model frame'}", file=sys.stderr)
    if "init_depth" not in overrides and "init" not in overrides:
        if done.points:
            overrides.update(init="points", init_points=str(done.root / POINTS))
        else:
            print(f"the model has no 3D points: triangulating them from the {done.images} images with their "
                  "known poses (pycolmap, CPU; --init-depth starts from a plane instead)", file=sys.stderr)
            overrides.update(init="triangulated")
    return done.root

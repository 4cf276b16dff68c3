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
from pathlib import Path

from ragsplat.cli.args import (
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
    from ragsplat.train.config import INITS, PRESETS, VARIANTS

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
    parser.add_argument("--variant", default="full", choices=list(VARIANTS), help="refraction correction")
    parser.add_argument("--out", required=True, type=out_dir,
                        help="output directory (resumes if it holds a checkpoint)")
    parser.add_argument("--preset", default="small", choices=list(PRESETS), help="training preset")
    parser.add_argument("--seed", type=count, default=0, help="random seed (written into config.json)")
    parser.add_argument("--iterations", type=positive_int, help="override the preset's iteration count")
    parser.add_argument("--surfel-depth", choices=DEPTHS,
                        help="a surfel sample's z: where the pixel's ray meets it (ray, the preset's) or its "
                             "centre's (centre, as gsplat does on a GPU)")
    parser.add_argument("--init", choices=list(INITS),
                        help="initialisation (default: the preset's, grid; with --colmap: the model's "
                             "points, else triangulated)")
    parser.add_argument("--init-depth", type=positive_float, help="grid depth below the water level (m); "
                        "default: scene.json spec.bed.depth")
    parser.add_argument("--init-count", type=positive_int, metavar="N",
                        help="start from at most N points (a seeded random subset; default: the preset's "
                             "cap)")
    parser.add_argument("--init-fill", type=finite_float, metavar="M",
                        help="fill the gaps of a point start from its TIN: grid nodes M metres apart with no "
                             "point within M; 0: the points alone (default: the preset's)")
    parser.add_argument("--init-points", metavar="FILE.npy", help="point cloud [N, 3] or [N, 6] (xyz, rgb in "
                        "[0, 1]) for --init points; submerged depths are multiplied by n")
    parser.add_argument("--water-level", type=finite_float, metavar="Z",
                        help="height of the calm water surface (m, the model's frame, z up): required with "
                        "--colmap; with --data it replaces the dataset's")
    parser.add_argument("--n", type=refractive_index, dest="water_n", metavar="N",
                        help="refractive index of the water (>= 1); default: the dataset's, else 1.33")
    parser.add_argument("--optimize-water", choices=["level", "level+n"],
                        help="calibrate the water level (and n) from the images, starting from the values "
                        "above, once the first half of the run has settled the Gaussians (experimental: on "
                        "the small reach it did not correct a level 10 cm off; see README)")
    parser.add_argument("--checkpoint-every", type=count, metavar="N",
                        help="write a checkpoint every N steps (default: every 10 %% of the run; 0: only at "
                             "the end)")
    parser.add_argument("--backend", choices=list(BACKENDS), help="rasterizer backend (default: auto)")
    parser.add_argument("--device", help="torch device (default: CUDA when available, else CPU)")
    parser.add_argument("--compile-refraction", action="store_true", default=None,
                        help="fuse the refraction transform's small ops with torch.compile (for a GPU, where "
                             "they are launch-bound; compiles first)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from ragsplat.cli.progress import deferred_interrupts, training_bar
    from ragsplat.dataset.load import load_dataset
    from ragsplat.train import Trainer, preset_config

    overrides = {"variant": args.variant, "seed": args.seed}
    for key in ("iterations", "init", "init_depth", "init_count", "init_fill", "init_points", "water_level",
                "water_n", "optimize_water", "checkpoint_every", "backend", "device", "compile_refraction",
                "surfel_depth"):
        if getattr(args, key) is not None:
            overrides[key] = getattr(args, key)
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

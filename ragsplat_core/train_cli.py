"""`ragsplat train --data DIR --variant full --out DIR [--preset NAME] [--seed S] [--iterations N]`.

Trains one variant on a dataset directory, with a progress bar (loss, PSNR on the training view, Gaussian
count, time left); rerunning with the same --out resumes from the last checkpoint. Writes config.json,
ckpt.pt, point_cloud.ply (3DGS PLY) and train_stats.json into --out.
"""

from __future__ import annotations

import argparse
import json
import sys

from ragsplat_core.cli import UsageError
from ragsplat_core.train import PRESETS, VARIANTS, TrainingDiverged


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True, help="dataset directory (transforms.json, images/)")
    parser.add_argument("--variant", default="full", choices=list(VARIANTS), help="refraction correction")
    parser.add_argument("--out", required=True, help="output directory (resumes if it holds a checkpoint)")
    parser.add_argument("--preset", default="small", choices=list(PRESETS), help="training preset")
    parser.add_argument("--seed", type=int, default=0, help="random seed (written into config.json)")
    parser.add_argument("--iterations", type=int, help="override the preset's iteration count")
    parser.add_argument("--init-depth", type=float, help="grid depth below the water level (m); "
                        "default: scene.json spec.bed.depth")
    parser.add_argument("--backend", choices=["auto", "torch", "cpu", "gsplat"], help="rasterizer backend")
    parser.add_argument("--device", help="torch device (default: CUDA when available, else CPU)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from ragsplat_core.data import load_dataset
    from ragsplat_core.train import Trainer, preset_config

    overrides = {"variant": args.variant, "seed": args.seed}
    for key in ("iterations", "init_depth", "backend", "device"):
        if getattr(args, key) is not None:
            overrides[key] = getattr(args, key)
    try:
        cfg = preset_config(args.preset, **overrides)
    except ValueError as err:
        raise UsageError(str(err)) from None
    ds = load_dataset(args.data, splits=("train",), load_dry=False)
    try:
        trainer = Trainer(cfg, ds, args.out)
    except ValueError as err:
        raise UsageError(str(err)) from None

    bar = tqdm(total=cfg.iterations, initial=trainer.step, disable=args.no_progress, unit="it",
               desc=f"train {cfg.variant}", dynamic_ncols=True)

    def show(tr: Trainer) -> None:
        bar.update(1)
        if tr.step % 10 == 0 or tr.step == cfg.iterations:
            bar.set_postfix(loss=f"{tr.last['loss']:.4f}", psnr=f"{tr.last['psnr']:.2f}", n=tr.num_gaussians)

    try:
        stats = trainer.train(on_step=show)
    except TrainingDiverged as err:
        bar.close()
        print(f"ragsplat train: error: {err}; last checkpoint kept in {args.out}", file=sys.stderr)
        return 1
    bar.close()
    print(json.dumps(stats, indent=1))
    return 0

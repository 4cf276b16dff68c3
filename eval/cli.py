"""`ragsplat ablation --data DIR --out DIR [--preset smoke|small|paper] [--variants ...] [--seeds S ...]`:
every variant trained and evaluated per seed, the reference rows scored, Tables 1-3 printed (mean +- std
over seeds) beside the paper's (`eval.ablation`)."""

from __future__ import annotations

import argparse
from functools import partial

from ragsplat_core.cli.args import count, dataset_dir, out_dir


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from eval.ablation import PRESETS
    from ragsplat_core.train.config import VARIANTS

    parser.add_argument("--data", required=True, type=dataset_dir, help="dataset directory (transforms.json, gt/)")
    parser.add_argument("--out", required=True, type=out_dir, help="output directory (reused rows live here)")
    parser.add_argument("--preset", default="small", choices=list(PRESETS), help="training/eval size")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS), metavar="VARIANT",
                        help=f"subset of {', '.join(VARIANTS)} (default: all)")
    parser.add_argument("--seeds", type=count, nargs="+", default=[0], metavar="SEED",
                        help="training (and extraction) seeds; tables show mean +- std over them (default: 0)")
    parser.add_argument("--init", choices=["grid", "triangulated", "refracted"], default="grid",
                        help="how every variant starts: the paper's plane at the bed depth (grid), or points "
                             "triangulated from the training images with their known poses (no answer given): "
                             "straight rays, depths x n (triangulated), or rays bent at the water (refracted)")
    lpips_arguments(parser)
    parser.add_argument("--device", default=None, help="torch device for training (default: the preset's)")


def lpips_arguments(parser: argparse.ArgumentParser) -> None:
    """--vgg16 and --no-download: where LPIPS's weights come from (`eval.metrics.load_lpips`)."""
    parser.add_argument("--vgg16", default=None, metavar="PATH",
                        help="torchvision's vgg16-397923af.pth for LPIPS (default: torch hub cache, downloaded "
                             "there with its hash check when missing)")
    parser.add_argument("--no-download", action="store_true",
                        help="never download the LPIPS weights (offline: LPIPS prints n/a with the reason)")


def run(args: argparse.Namespace) -> int:
    from eval.ablation import TrainEval, run_ablation
    from ragsplat_core.cli.progress import deferred_interrupts, training_bar

    with deferred_interrupts() as check:  # Ctrl-C: the trainer checkpoints its finished steps, then stops
        train_eval = TrainEval(args.data, args.device, training_bar=partial(training_bar, leave=False, check=check),
                               init=args.init)
        run_ablation(args.data, args.out, args.preset, args.variants, args.seeds, train_eval, vgg16=args.vgg16,
                     download=not args.no_download, log=print)
    return 0

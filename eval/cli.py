"""`ragsplat ablation --data DIR --out DIR [--preset smoke|small|paper] [--variants ...] [--seed S]`:
every variant trained and evaluated, Tables 1 and 2 printed beside the paper's (`eval.ablation`)."""

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
    parser.add_argument("--seed", type=count, default=0, help="training and extraction seed (recorded in every row)")
    parser.add_argument("--vgg16", default=None,
                        help="torchvision's vgg16-397923af.pth for LPIPS (default: torch hub cache)")
    parser.add_argument("--device", default=None, help="torch device for training (default: the preset's)")


def run(args: argparse.Namespace) -> int:
    from eval.ablation import TrainEval, run_ablation
    from ragsplat_core.cli.progress import deferred_interrupts, training_bar

    with deferred_interrupts() as check:  # Ctrl-C: the trainer checkpoints its finished steps, then stops
        train_eval = TrainEval(args.data, args.device, training_bar=partial(training_bar, leave=False, check=check))
        run_ablation(args.data, args.out, args.preset, args.variants, args.seed, train_eval, vgg16=args.vgg16,
                     log=print)
    return 0

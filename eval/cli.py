"""`ragsplat ablation --data DIR --out DIR [--preset smoke|small|paper] [--variants ...] [--seeds S ...]
[--jobs N]`: every variant trained and evaluated per seed, the reference rows scored, Tables 1-3 printed
(mean +- std over seeds) beside the paper's (`eval.ablation`).

`--jobs N` trains the rows in N processes with cores / N threads each, then reuses their rows in this one for
the references and the tables: on the 2-core CPU two single-threaded trainings together did 1.7x the steps of
one with both threads (measured on `small`), because much of a step is small operations that two threads do
not share well.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from functools import partial
from pathlib import Path

from ragsplat_core.cli.args import count, dataset_dir, out_dir, positive_int
from ragsplat_core.errors import RagsplatError


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
    parser.add_argument("--jobs", type=positive_int, default=1, metavar="N",
                        help="train the rows in N processes at once, each with cores / N threads (default: 1)")
    parser.add_argument("--code", default=None, help=argparse.SUPPRESS)  # the digest --jobs started with
    parser.add_argument("--queue", type=Path, default=None, help=argparse.SUPPRESS)  # the rows --jobs' processes take


class JobFailed(RagsplatError):
    """One of `--jobs`' processes failed."""


def spawn(cmd: list[str], env: dict, log: Path) -> subprocess.Popen:
    with open(log, "w") as f:
        return subprocess.Popen(cmd, env=env, stdout=f, stderr=subprocess.STDOUT)


def run_jobs(args: argparse.Namespace) -> None:
    """The rows in `args.jobs` child processes, each logging to OUT/part-k-of-N.log, all
    keyed to the sources as they were when the command started (`--code`), each taking the next row that
    none has taken from a queue folder of this command's own (`--queue`, removed at the end)."""
    from eval.ablation import claim_out

    threads = str(max(1, (os.cpu_count() or 1) // args.jobs))
    env = {**os.environ, "OMP_NUM_THREADS": threads, "MKL_NUM_THREADS": threads, "NUMBA_NUM_THREADS": threads}
    base = [sys.executable, "-m", "ragsplat_core.cli.main", "ablation", "--data", str(args.data), "--out",
            str(args.out), "--preset", args.preset, "--variants", *args.variants, "--seeds",
            *map(str, args.seeds), "--init", args.init, *(["--vgg16", args.vgg16] if args.vgg16 else []),
            *(["--no-download"] if args.no_download else []), *(["--device", args.device] if args.device else []),
            "--code", args.code]
    claim_out(args.out)  # before the logs are written into it
    # this command's own folder: markers a killed run left in another one do not hold back this one's rows
    queue = Path(args.out) / f".queue-{os.getpid()}-{time.time_ns()}"
    base += ["--queue", str(queue)]
    logs = [Path(args.out) / f"part-{k}-of-{args.jobs}.log" for k in range(args.jobs)]
    print(f"training in {args.jobs} processes of {threads} thread(s); logs: {', '.join(map(str, logs))}",
          flush=True)
    procs = [spawn(base, env, log) for log in logs]
    failed = [str(log) for proc, log in zip(procs, logs) if proc.wait() != 0]
    shutil.rmtree(queue, ignore_errors=True)
    if failed:
        raise JobFailed(f"{len(failed)} of {args.jobs} processes failed; see {', '.join(failed)}")


def lpips_arguments(parser: argparse.ArgumentParser) -> None:
    """--vgg16 and --no-download: where LPIPS's weights come from (`eval.metrics.load_lpips`)."""
    parser.add_argument("--vgg16", default=None, metavar="PATH",
                        help="torchvision's vgg16-397923af.pth for LPIPS (default: torch hub cache, downloaded "
                             "there with its hash check when missing)")
    parser.add_argument("--no-download", action="store_true",
                        help="never download the LPIPS weights (offline: LPIPS prints n/a with the reason)")


def run(args: argparse.Namespace) -> int:
    from eval.ablation import CODE, TrainEval, run_ablation
    from ragsplat_core.cli.progress import deferred_interrupts, training_bar
    from ragsplat_core.outputs import source_digest

    if args.code is None:
        args.code = source_digest(*CODE)
    if args.jobs > 1:
        run_jobs(args)  # then every trained row is on disk and is reused below
    with deferred_interrupts() as check:  # Ctrl-C: the trainer checkpoints its finished steps, then stops
        train_eval = TrainEval(args.data, args.device, training_bar=partial(training_bar, leave=False, check=check),
                               init=args.init)
        run_ablation(args.data, args.out, args.preset, args.variants, args.seeds, train_eval, vgg16=args.vgg16,
                     download=not args.no_download, log=print, code=args.code, queue=args.queue)
    return 0

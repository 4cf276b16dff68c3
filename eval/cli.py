"""`ragsplat ablation --data DIR --out DIR [--preset smoke|small|paper] [--variants ...] [--seeds S ...]
[--init ...] [--jobs N] [--one-level]`: every variant trained and evaluated per seed, the reference rows scored,
Tables 1-3 printed (mean +- std over seeds) beside the paper's (`eval.ablation`, which also holds the defaults).

`--one-level` measures what a flat-water tool does on a sloping river: the method and every reference are
given one level, the mean height of the dataset's surveyed water edge (`eval.ablation.one_level_water`),
while every row is still scored against the true surface and bed.

`--jobs N` trains the rows in N processes with cores / N threads each, then reuses their rows in this one for
the references and the tables: on the 2-core CPU two single-threaded trainings together did 1.7x the steps of
one with both threads (measured on `small`), because much of a step is small operations that two threads do
not share well. What the rows share (the triangulated tracks of a dataset) is built here once, before the
processes start; a process that fails stops the others at their next checkpoint and the command names the row
it held; the same command then resumes.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import time
from functools import partial
from pathlib import Path

from ragsplat_core.cli.args import count, dataset_dir, out_dir, positive_int
from ragsplat_core.errors import RagsplatError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from eval.ablation import EDGE_POINTS, INIT, JOBS, JOBS_PER_GPU, PRESETS, SEEDS
    from ragsplat_core.train.config import VARIANTS

    parser.add_argument("--data", required=True, type=dataset_dir, help="dataset directory (transforms.json, gt/)")
    parser.add_argument("--out", required=True, type=out_dir, help="output directory (reused rows live here)")
    parser.add_argument("--preset", default="small", choices=list(PRESETS), help="training/eval size")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS), metavar="VARIANT",
                        help=f"subset of {', '.join(VARIANTS)} (default: all)")
    parser.add_argument("--seeds", type=count, nargs="+", default=list(SEEDS), metavar="SEED",
                        help="training (and extraction) seeds; tables show mean +- std over them "
                             f"(default: {' '.join(map(str, SEEDS))})")
    parser.add_argument("--init", choices=["grid", "triangulated", "refracted"], default=INIT,
                        help="how every variant starts: the paper's plane at the bed depth (grid), or points "
                             "triangulated from the training images with their known poses (no answer given): "
                             "straight rays, depths x n (triangulated), or rays bent at the water (refracted) "
                             f"(default: {INIT})")
    parser.add_argument("--one-level", action="store_true",
                        help=f"give every variant and every reference one flat water level, the mean height of "
                             f"the dataset's {EDGE_POINTS} (the water's edge as surveyed), instead of its "
                             "surface: what a flat-water tool does on a sloping river; scored against the true "
                             "surface and bed as always, its rows keyed apart from those without it")
    lpips_arguments(parser)
    parser.add_argument("--device", default=None, help="torch device for training (default: the preset's)")
    parser.add_argument("--jobs", type=positive_int, default=None, metavar="N",
                        help=f"train the rows in N processes at once, each with cores / N threads, shared out over "
                             f"the GPUs on CUDA (default: {JOBS} on the CPU, {JOBS_PER_GPU} per GPU on CUDA)")
    parser.add_argument("--code", default=None, help=argparse.SUPPRESS)  # the digest --jobs started with
    parser.add_argument("--queue", type=Path, default=None, help=argparse.SUPPRESS)  # the rows --jobs' processes take


class JobFailed(RagsplatError):
    """One of `--jobs`' processes failed."""


def spawn(cmd: list[str], env: dict, log: Path) -> subprocess.Popen:
    # A session of its own: a Ctrl-C at the terminal reaches only this process, which passes it on once (`stop`).
    with open(log, "w") as f:
        return subprocess.Popen(cmd, env=env, stdout=f, stderr=subprocess.STDOUT, start_new_session=True)


def stop(procs: list) -> None:
    """SIGTERM to every process still running (each writes a checkpoint of its finished steps and exits, as on
    Ctrl-C), then wait for them; an interrupt while waiting passes a second SIGTERM on, which stops them at once."""
    def terminate():
        for proc in procs:
            if proc.poll() is None:
                proc.terminate()

    terminate()
    try:
        for proc in procs:
            proc.wait()
    except KeyboardInterrupt:
        terminate()
        for proc in procs:
            proc.wait()
        raise


def last_line(log: Path) -> str:
    lines = [line.strip() for line in log.read_text(errors="replace").splitlines() if line.strip()] \
        if log.is_file() else []
    return lines[-1] if lines else ""


def prepare(args: argparse.Namespace, fingerprint: str) -> None:
    """What every row reads and nothing but one process should make, made here once before the processes
    start: the dataset's triangulated tracks (cached in it), the LPIPS weights (downloaded to the cache) and,
    for training on CUDA, gsplat's CUDA extension (`rasterize.build_gsplat`)."""
    import torch

    from eval import metrics
    from ragsplat_core import rasterize

    cuda = str(args.device).startswith("cuda") or (args.device in (None, "auto") and torch.cuda.is_available())
    if cuda and rasterize.gsplat_available():
        print("gsplat's CUDA extension (built once, here, before the processes start) ...", flush=True)
        rasterize.build_gsplat()

    # a bad path is refused; the weights are not loaded here, only found or fetched
    path, _, reason = metrics.vgg16_weights(args.vgg16, download=not args.no_download, log=print)
    if path is None and not args.no_download:  # a failed download: the processes and the tables do not retry
        print(f"LPIPS n/a: {reason}", flush=True)
        args.no_download = True
    if args.init in ("triangulated", "refracted"):
        from ragsplat_core.dataset.colmap import triangulated_points

        print("the training images' tracks (triangulated once per dataset, cached in it) ...", flush=True)
        print(f"tracks: {triangulated_points(args.data, fingerprint)}", flush=True)


def run_jobs(args: argparse.Namespace, fingerprint: str, check) -> None:
    """The rows in `args.jobs` child processes, each logging to OUT/part-k-of-N.log, all
    keyed to the sources as they were when the command started (`--code`), each taking the next row that
    none has taken from a queue folder of this command's own (`--queue`, removed at the end). `check()`
    raises KeyboardInterrupt once this process was interrupted; the processes are then stopped (`stop`)."""
    from eval.ablation import claim_out, held, visible_gpus

    claim_out(args.out)  # before the logs are written into it
    prepare(args, fingerprint)
    threads = str(max(1, (os.cpu_count() or 1) // args.jobs))
    env = {**os.environ, "OMP_NUM_THREADS": threads, "MKL_NUM_THREADS": threads, "NUMBA_NUM_THREADS": threads}
    gpus = visible_gpus(args.device)  # [] on the CPU
    base = [sys.executable, "-m", "ragsplat_core.cli.main", "ablation", "--data", str(args.data), "--out",
            str(args.out), "--preset", args.preset, "--variants", *args.variants, "--seeds",
            *map(str, args.seeds), "--init", args.init, *(["--vgg16", args.vgg16] if args.vgg16 else []),
            *(["--no-download"] if args.no_download else []), *(["--device", args.device] if args.device else []),
            *(["--one-level"] if args.one_level else []), "--jobs", "1", "--code", args.code]
    # this command's own folder: markers a killed run left in another one do not hold back this one's rows
    queue = Path(args.out) / f".queue-{os.getpid()}-{time.time_ns()}"
    base += ["--queue", str(queue)]
    logs = [Path(args.out) / f"part-{k}-of-{args.jobs}.log" for k in range(args.jobs)]
    print(f"training in {args.jobs} processes of {threads} thread(s); logs: {', '.join(map(str, logs))}",
          flush=True)
    procs = [spawn(base, {**env, **({"CUDA_VISIBLE_DEVICES": gpus[k % len(gpus)]} if gpus else {})}, log)
             for k, log in enumerate(logs)]
    try:  # until all have finished or one has failed
        while any(proc.poll() is None for proc in procs) and not any(proc.poll() for proc in procs):
            check()
            time.sleep(0.2)
    except KeyboardInterrupt:
        stop(procs)
        raise
    dead = [k for k, proc in enumerate(procs) if proc.poll() not in (None, 0)]
    if dead:
        k = dead[0]
        rc = procs[k].returncode
        how = f"was killed by {signal.Signals(-rc).name}" if rc < 0 else f"exited with {rc}"
        rows = ", ".join(name.replace("-seed", " seed ") for name in held(queue, procs[k].pid)) or "no row"
        why = last_line(logs[k]) if rc > 0 else ""
        print(f"process {k + 1} of {args.jobs} {how} while training {rows}; stopping the others at their next "
              "checkpoint", flush=True)
        stop(procs)
        shutil.rmtree(queue, ignore_errors=True)
        raise JobFailed(f"process {k + 1} of {args.jobs} {how} while training {rows} (log: {logs[k]}"
                        f"{': ' + why if why else ''}); finished rows and checkpoints are kept, rerun the same "
                        "command to resume")
    shutil.rmtree(queue, ignore_errors=True)


def lpips_arguments(parser: argparse.ArgumentParser) -> None:
    """--vgg16 and --no-download: where LPIPS's weights come from (`eval.metrics.load_lpips`)."""
    parser.add_argument("--vgg16", default=None, metavar="PATH",
                        help="torchvision's vgg16-397923af.pth for LPIPS (default: torch hub cache, downloaded "
                             "there with its hash check when missing)")
    parser.add_argument("--no-download", action="store_true",
                        help="never download the LPIPS weights (offline: LPIPS prints n/a with the reason)")


def run(args: argparse.Namespace) -> int:
    from eval.ablation import ROW_CODE, TrainEval, default_jobs, run_ablation
    from ragsplat_core.cli.progress import deferred_interrupts, training_bar
    from ragsplat_core.outputs import source_digest

    if args.code is None:
        args.code = source_digest(*ROW_CODE)
    if args.jobs is None:
        args.jobs = default_jobs(args.device)
    with deferred_interrupts() as check:  # Ctrl-C: the trainer checkpoints its finished steps, then stops
        # the dataset and its ground truth are loaded and checked before any process starts
        train_eval = TrainEval(args.data, args.device, training_bar=partial(training_bar, leave=False, check=check),
                               init=args.init, one_level=args.one_level)
        if args.jobs > 1 and args.queue is None:
            run_jobs(args, train_eval.fingerprint, check)  # then every trained row is on disk, reused below
        run_ablation(args.data, args.out, args.preset, args.variants, args.seeds, train_eval, vgg16=args.vgg16,
                     download=not args.no_download, log=print, code=args.code, queue=args.queue)
    return 0

"""`ragsplat ablation --data DIR --out DIR [--preset smoke|small|paper] [--variants ...] [--seeds S ...]
[--init ...] [--jobs N] [--one-level] [--uncertainty MODEL.json] [--no-geotiffs]`: every variant trained
and evaluated per seed, the reference rows scored, Tables 1-3 printed (mean +- std over seeds) beside the
paper's (`ragsplat.eval.ablation`, which also holds its own defaults; those it shares with `ragsplat
survey` are `ragsplat.train.defaults`'). With a fitted uncertainty model each trained row also writes its
TVU95 band and Table 3 reports its coverage and sharpness (`ragsplat.eval.tvu_cells.band_rows`).

`--one-level` measures what a flat-water tool does on a sloping river: the method and every reference are
given one level, the mean height of the dataset's surveyed water edge
(`ragsplat.eval.ablation.one_level_water`), while every row is still scored against the true surface and bed.

`--jobs N` trains the rows as Dask tasks (`dask.distributed`) on a local cluster of N worker processes with
cores / N threads each (on CUDA each worker sees one GPU), then reuses their rows in this one for the
references and the tables: on the 2-core CPU two single-threaded trainings together did 1.7x the steps of one
with both threads (measured on `small`), because much of a step is small operations that two threads do not
share well. `--scheduler ADDRESS` sends the same tasks to an existing Dask cluster instead (its workers need
this package and the paths of `--data` and `--out`). What the rows share (the triangulated tracks of a
dataset, LPIPS's weights, gsplat's build) is made here once, before the tasks start. A worker that dies: Dask
runs its row again on another, which resumes from the row's checkpoint; a row that fails ends the command,
which names it and its log (`OUT/logs/`); the same command then resumes.
"""

from __future__ import annotations

import argparse
from functools import partial
from pathlib import Path

from ragsplat.cli.args import count, dataset_dir, lpips_arguments, out_dir, positive_int
from ragsplat.errors import ConfigError, RagsplatError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ragsplat.eval.ablation import EDGE_POINTS, JOBS_PER_GPU, PRESETS, SEEDS
    from ragsplat.train.config import INIT, VARIANTS, WATER_TERMS
    from ragsplat.train.defaults import CLEAR_VARIANTS, JOBS

    parser.add_argument("--data", required=True, type=dataset_dir,
                        help="dataset directory (transforms.json, gt/)")
    parser.add_argument("--out", required=True, type=out_dir, help="output directory (reused rows live here)")
    parser.add_argument("--preset", default="small", choices=list(PRESETS), help="training/eval size")
    parser.add_argument("--variants", nargs="+", default=list(CLEAR_VARIANTS), choices=list(VARIANTS),
                        metavar="VARIANT",
                        help=f"subset of {', '.join(VARIANTS)} (default: all but {', '.join(WATER_TERMS)})")
    parser.add_argument("--seeds", type=count, nargs="+", default=list(SEEDS), metavar="SEED",
                        help="training (and extraction) seeds; tables show mean +- std over them "
                             f"(default: {' '.join(map(str, SEEDS))})")
    parser.add_argument("--init", choices=["grid", "triangulated", "refracted"], default=INIT,
                        help="how every variant starts: the paper's plane at the bed depth (grid), or points "
                             "triangulated from the training images with their known poses (no answer "
                             "given): straight rays, depths x n (triangulated), or rays bent at the water "
                             f"(refracted) (default: {INIT})")
    parser.add_argument("--one-level", action="store_true",
                        help="give every variant and every reference one flat water level, the mean height "
                             f"of the dataset's {EDGE_POINTS} (the water's edge as surveyed), instead of its "
                             "surface: what a flat-water tool does on a sloping river; scored against the "
                             "true surface and bed as always, its rows keyed apart from those without it")
    lpips_arguments(parser)
    parser.add_argument("--device", default=None, help="torch device for training (default: the preset's)")
    parser.add_argument("--jobs", type=positive_int, default=None, metavar="N",
                        help="train the rows on N local Dask workers at once, each with cores / N threads, "
                             f"shared out over the GPUs on CUDA (default: {JOBS} on the CPU, {JOBS_PER_GPU} "
                             "per GPU on CUDA; 1: in this process)")
    parser.add_argument("--scheduler", default=None, metavar="ADDRESS",
                        help="train the rows on the Dask cluster whose scheduler is at ADDRESS "
                             "(tcp://host:8786) instead of local workers")
    parser.add_argument("--uncertainty", type=Path, metavar="MODEL.json|small|small-field",
                        help="a fitted uncertainty model (`python -m tools.fit_uncertainty`), or a shipped "
                             "one ('small', clear water; 'small-field', field conditions): each trained row "
                             "writes its TVU95 band (tvu95.tif) and Table 3 reports its coverage and "
                             "sharpness (docs/uncertainty.md); refused on a dataset seed the model saw")
    parser.add_argument("--no-geotiffs", action="store_true",
                        help="write each row's bed as bed.npy without its height GeoTIFF bed.tif, for a "
                             "machine without rasterio (a lent GPU); the same command run later where "
                             "rasterio is reuses the rows and writes their GeoTIFFs")


class JobFailed(RagsplatError):
    """A row's task failed."""


def prepare(args: argparse.Namespace, fingerprint: str) -> None:
    """What every row reads and nothing but one process should make, made here once before the processes
    start: the dataset's triangulated tracks (cached in it), the LPIPS weights (downloaded to the cache) and,
    for training on CUDA, gsplat's CUDA extension (`rasterize.build_gsplat`)."""
    from ragsplat import rasterize
    from ragsplat.eval import metrics
    from ragsplat.eval.ablation import trains_on_cuda

    if trains_on_cuda(args.device) and rasterize.gsplat_available():
        print("gsplat's CUDA extension (built once, here, before the processes start) ...", flush=True)
        rasterize.build_gsplat()

    # a bad path is refused; the weights are not loaded here, only found or fetched
    path, _, reason = metrics.vgg16_weights(args.vgg16, download=not args.no_download, log=print)
    if path is None and not args.no_download:  # a failed download: the processes and the tables do not retry
        print(f"LPIPS n/a: {reason}", flush=True)
        args.no_download = True
    if args.init in ("triangulated", "refracted"):
        from ragsplat.dataset.colmap import triangulated_points

        print("the training images' tracks (triangulated once per dataset, cached in it) ...", flush=True)
        print(f"tracks: {triangulated_points(args.data, fingerprint)}", flush=True)


def run_rows(args: argparse.Namespace, fingerprint: str, code: str, check) -> None:
    """The trained rows as Dask tasks (`ragsplat.eval.ablation.train_row`, one per row, the longest first) on
    a local cluster of `args.jobs` worker processes or on the one at `args.scheduler`, with a bar of the rows
    done. `check()` raises KeyboardInterrupt once this process was interrupted; the tasks are then cancelled
    (each row keeps its last checkpoint). A task that fails raises JobFailed naming its row and log."""
    from ragsplat.cli.cluster import client as dask_client
    from ragsplat.cli.progress import bar
    from ragsplat.eval.ablation import RowJob, row_log, row_order, train_row, visible_gpus
    from ragsplat.eval.rows import claim_out
    from ragsplat.scheduling import submitted

    claim_out(args.out)
    prepare(args, fingerprint)
    # local workers share out the GPUs, worker k on GPU k mod their count; a cluster's own workers keep theirs
    gpus = () if args.scheduler else tuple(visible_gpus(args.device))
    job = RowJob(str(args.data), str(args.out), args.preset, args.init, args.one_level, args.device,
                 args.vgg16, code, gpus, not args.no_geotiffs)
    rows = row_order(args.variants, args.seeds)
    with dask_client(args.jobs, args.scheduler) as (client, where):
        print(f"training {len(rows)} row{'s' if len(rows) > 1 else ''} on {where}; each row's log: "
              f"{args.out / 'logs'}", flush=True)
        calls = {f"row-{variant}-seed{seed}": (train_row, (job, variant, seed)) for variant, seed in rows}
        named = dict(zip(calls, rows))
        with bar(len(calls), "rows", "row") as done:
            for key, task in submitted(client, calls, check):
                variant, seed = named[key]
                if task.status != "finished":
                    raise JobFailed(f"training {variant} seed {seed} failed: {_reason(task)} (log: "
                                    f"{row_log(args.out, variant, seed)}); finished rows and checkpoints "
                                    "are kept, rerun the same command to resume")
                done.update(1)


def _reason(task) -> str:
    err = task.exception()
    return f"{type(err).__name__}: {err}" if err is not None else task.status


def run(args: argparse.Namespace) -> int:
    from ragsplat.cli.progress import deferred_interrupts, training_bar
    from ragsplat.eval.ablation import ROW_CODE, TrainEval, default_jobs, run_ablation
    from ragsplat.eval.tvu_cells import band_rows, check_held_out
    from ragsplat.export import read_uncertainty
    from ragsplat.outputs import source_digest

    code = source_digest(*ROW_CODE)  # every row keyed to the code the command started with
    model = None if args.uncertainty is None else read_uncertainty(args.uncertainty)  # before any work
    if model is not None and args.no_geotiffs:
        raise ConfigError("--uncertainty writes each row's TVU95 band as a GeoTIFF; it cannot go with "
                          "--no-geotiffs (run it where rasterio is, reusing the rows)")
    if args.jobs is None:
        args.jobs = default_jobs(args.device)
    with deferred_interrupts() as check:  # Ctrl-C: the trainer checkpoints its finished steps, then stops
        # the dataset and its ground truth are loaded and checked before any task starts
        train_eval = TrainEval(args.data, args.device,
                               training_bar=partial(training_bar, leave=False, check=check),
                               init=args.init, one_level=args.one_level)
        if model is not None:
            check_held_out(model, train_eval.dataset_seed)
        if args.jobs > 1 or args.scheduler:
            # then every trained row is on disk, reused below
            run_rows(args, train_eval.fingerprint, code, check)
        run_ablation(args.data, args.out, args.preset, args.variants, args.seeds, train_eval,
                     vgg16=args.vgg16, download=not args.no_download, log=print, code=code,
                     band=None if model is None else partial(band_rows, model=model, log=print),
                     geotiffs=not args.no_geotiffs)
    return 0

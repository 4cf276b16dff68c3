"""`ragsplat eval RUN [--data DIR] [--out FILE.json] [--min-opacity A] [--max-scale-gsd K] [--despike-radius
M] [--despike-tol M] [--fill-gap-cells K] [--vgg16 PATH] [--no-download]`: a finished training run
scored against its dataset's ground truth with the ablation's measures, without retraining
(`ragsplat.eval.score`); prints the bed's scores beside the reference answers and writes them all as JSON
(default RUN/eval.json)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ragsplat.cli.args import (
    cull_arguments,
    cull_overrides,
    dataset_dir,
    lpips_arguments,
    out_file_ending,
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", type=Path, metavar="RUN", help="a finished `ragsplat train` output directory")
    parser.add_argument("--data", type=dataset_dir, metavar="DIR",
                        help="the run's dataset directory, with its ground truth (default: the one "
                             "RUN/config.json names)")
    parser.add_argument("--truth", type=dataset_dir, metavar="DIR",
                        help="score against this dataset's ground truth and held-out views instead (same "
                             "frame: e.g. the synthetic dataset whose COLMAP model a survey run imported)")
    parser.add_argument("--dem", type=Path, metavar="FILE.tif",
                        help="also score this DEM (`ragsplat export --dem`) and map its error "
                             "(FILE_error.png)")
    parser.add_argument("--out", type=out_file_ending(".json"), metavar="FILE.json",
                        help="the scores as JSON (default: RUN/eval.json)")
    cull_arguments(parser)  # of the volume bed
    lpips_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from ragsplat.eval.report import jsonable
    from ragsplat.eval.score import score_run, table
    from ragsplat.outputs import write_json

    result = score_run(args.run, args.data, args.vgg16, download=not args.no_download, log=print,
                       truth=args.truth, dem=args.dem, extract=cull_overrides(args))
    out = args.out if args.out is not None else args.run / "eval.json"
    write_json(out, jsonable(result), indent=1)
    print(table(result))
    if args.dem is not None:
        print(f"wrote {result['dem']['error_map']}")
    print(f"wrote {out}")
    return 0

"""`ragsplat stability`: the refraction transform's numerical stability report; exits 1 when a target is
missed."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from ragsplat.cli.args import count, out_file, positive_int
from ragsplat.outputs import write_json


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from ragsplat.bench.stability import StabilityConfig

    parser.add_argument("--cases", type=positive_int, default=StabilityConfig.cases_per_regime,
                        help="cases per regime and dtype (8 regimes)")
    parser.add_argument("--dtypes", nargs="+", default=list(StabilityConfig.dtypes),
                        choices=["float64", "float32"], help="floating-point types to sweep (default: both)")
    parser.add_argument("--seed", type=count, default=0, help="random seed of the cases")
    parser.add_argument("--out", type=out_file, default=Path("runs/stability.json"), help="JSON report path")


def run(args: argparse.Namespace) -> int:
    import torch

    from ragsplat.bench.stability import StabilityConfig, format_table, run_sweep

    cfg = StabilityConfig(cases_per_regime=args.cases, dtypes=tuple(args.dtypes), seed=args.seed)
    start = time.perf_counter()
    results = run_sweep(cfg)
    results["seconds"] = time.perf_counter() - start
    results["torch"] = torch.__version__
    print(format_table(results))
    write_json(args.out, results)
    print(f"wrote {args.out} ({results['seconds']:.0f} s)", file=sys.stderr)
    return 0 if results["passed"] else 1

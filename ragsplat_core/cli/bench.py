"""`ragsplat bench TARGET`: benchmarks that print figures and write JSON (never timed assertions).

Targets: `refraction` (Snell solvers: error against run time; the cost of refract_gaussians), `raster`
(rasterizer forward+backward time and peak memory per backend), `surfel` (the surfel rasterizer's
forward+backward time next to the 3DGS one's), `train-step` (median time per training iteration,
refraction overhead full / 3dgs), `export` (a large bed's export: time and peak memory), `bundle` (the
adjustment through the water on a synthetic flight: time and peak memory). The measuring code
lives in `ragsplat.bench`.
"""

from __future__ import annotations

import argparse
import platform
import sys
from pathlib import Path

from ragsplat.cli.args import count, out_file, positive_float, positive_int
from ragsplat.errors import ConfigError
from ragsplat.outputs import write_json


def _refraction_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cases", type=positive_int, default=200_000, help="cases per solver and dtype")
    parser.add_argument("--repeats", type=positive_int, default=5,
                        help="timed repetitions per solver (median reported)")
    parser.add_argument("--seed", type=count, default=0, help="random seed of the cases")
    parser.add_argument("--out", type=out_file, default=Path("runs/bench/refraction.json"),
                        help="JSON output path")


def _refraction(args: argparse.Namespace) -> int:
    import torch

    from ragsplat.bench.refraction import format_tables, solver_table, transform_table

    solvers = solver_table(args.cases, args.repeats, args.seed)
    transform = transform_table([10_000, 100_000], args.repeats, args.seed)
    print(format_tables(solvers, transform))
    write_json(args.out, {"cases": args.cases, "repeats": args.repeats, "seed": args.seed,
                          "threads": torch.get_num_threads(), "torch": torch.__version__,
                          "solvers": solvers, "refract_gaussians": transform})
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


def _raster_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--n", type=positive_int, nargs="+", default=[10_000, 40_000], help="Gaussian counts")
    parser.add_argument("--size", type=positive_int, default=256, help="image width = height in pixels")
    parser.add_argument("--repeats", type=positive_int, default=7, help="timed iterations (median reported)")
    parser.add_argument("--backends", nargs="+", default=None,
                        help="backends to run: cpu, torch, torch-cuda, gsplat (default: every available one)")
    parser.add_argument("--footprint", type=positive_float, nargs="+", default=[1.0],
                        help="in-plane Gaussian size factors (1 = sigma 0.6-1.2x the mean spacing)")
    parser.add_argument("--threads", type=count, nargs="+", default=[0],
                        help="torch/numba threads per run (0 = one per core)")
    parser.add_argument("--out", type=out_file, default=Path("runs/bench/raster.json"),
                        help="JSON output path")


def _raster(args: argparse.Namespace) -> int:
    import os

    from ragsplat.bench.raster import available_backends, bench_rasterizer, format_table

    unknown = [b for b in args.backends or () if b not in available_backends()]
    if unknown:
        raise ConfigError(f"--backends {unknown[0]} is not available here; choose from "
                          f"{', '.join(available_backends())}")
    rows = bench_rasterizer(args.n, args.size, args.repeats, args.backends, args.footprint, args.threads)
    print(format_table(rows))
    write_json(args.out, {"rows": rows, "cpu_count": len(os.sched_getaffinity(0))})
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


def _surfel_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--n", type=positive_int, nargs="+", default=[40_000],
                        help="surfel (Gaussian) counts")
    parser.add_argument("--size", type=positive_int, default=256, help="image width = height in pixels")
    parser.add_argument("--repeats", type=positive_int, default=7, help="timed iterations (median reported)")
    parser.add_argument("--backend", choices=["cpu", "torch"], default="cpu",
                        help="backend of both rasterizers")
    parser.add_argument("--threads", type=count, nargs="+", default=[0],
                        help="torch/numba threads per run (0 = one per core)")
    parser.add_argument("--out", type=out_file, default=Path("runs/bench/surfel.json"),
                        help="JSON output path")


def _surfel(args: argparse.Namespace) -> int:
    import os

    from ragsplat.bench.surfel import bench_surfels, format_table

    rows = bench_surfels(args.n, args.size, args.repeats, args.backend, args.threads)
    print(format_table(rows))
    write_json(args.out, {"rows": rows, "cpu_count": len(os.sched_getaffinity(0))})
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


def _train_step_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--counts", type=positive_int, nargs="+", default=[10_000, 40_000],
                        help="Gaussian counts")
    parser.add_argument("--backends", nargs="+", help="backend:device pairs, e.g. cpu:cpu torch:cuda "
                        "(default: all available)")
    parser.add_argument("--steps", type=positive_int, default=10, help="timed iterations per variant")
    parser.add_argument("--warmup", type=count, default=3, help="untimed iterations first (JIT, caches)")
    parser.add_argument("--compile", action="store_true",
                        help="also full and 2dgs+full with the refraction transform through torch.compile "
                             "(as `ragsplat train --compile-refraction`), timed in the same loop")
    parser.add_argument("--attenuation", action="store_true",
                        help="also 2dgs+full+attenuation (the water's attenuation), timed in the same loop")
    parser.add_argument("--backscatter", action="store_true",
                        help="also 2dgs+full+backscatter (the water column's veil) and 2dgs+full+water "
                        "(attenuation, backscatter and reflection), timed in the same loop")
    parser.add_argument("--reflection", action="store_true",
                        help="also 2dgs+full+reflection (the surface's reflection of the sky), timed in the "
                             "same loop")
    parser.add_argument("--out", type=out_file, default=Path("runs/bench/train_step.json"),
                        help="JSON output path (every timing of every row)")


def _train_step(args: argparse.Namespace) -> int:
    import torch

    from ragsplat.bench import openmp_wait
    from ragsplat.bench.train_step import SIZE, backends_available, bench_train_step

    pairs = None
    if args.backends:
        pairs = [tuple(p.split(":")) for p in args.backends]
        if any(len(p) != 2 for p in pairs):
            raise ConfigError(f"--backends takes backend:device pairs, got {' '.join(args.backends)}")
        for p in pairs:
            if p not in backends_available():
                raise ConfigError(f"backend {p[0]} on {p[1]} is not available here: {backends_available()}")
    print(f"train-step benchmark: {SIZE}x{SIZE}, median of {args.steps} iterations after {args.warmup} "
          f"warm-up; torch {torch.__version__}, {torch.get_num_threads()} threads, "
          f"{platform.processor() or platform.machine()}")
    print(f"{'backend':>6} {'dev':>4} {'N':>6} {'3dgs (s)':>10} {'full (s)':>10} {'full/3dgs':>9} "
          f"{'refr (s)':>10} {'refr/3dgs':>9} {'2dgs+full':>10} {'/full':>9}")
    rows = bench_train_step(args.counts, pairs, args.steps, args.warmup, compiled=args.compile,
                            attenuation=args.attenuation, backscatter=args.backscatter,
                            reflection=args.reflection)
    write_json(args.out, {"rows": rows, "torch": torch.__version__, "threads": torch.get_num_threads(),
                          **openmp_wait()}, indent=1)
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


def _export_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--side", type=positive_float, default=100.0, help="the bed's side (m; default 100)")
    parser.add_argument("--spacing", type=positive_float, default=0.05,
                        help="the model's Gaussian spacing (m; default 0.05: 4 million over 100 x 100 m)")
    parser.add_argument("--resolution", type=positive_float, default=0.05, help="DEM cell (m; default 0.05)")
    parser.add_argument("--out", type=out_file, default=Path("runs/bench/export.json"),
                        help="JSON output path")


def _export(args: argparse.Namespace) -> int:
    from ragsplat.bench.export import bench_export
    from ragsplat.cli.progress import count_bar

    b, on_block = count_bar("export", "block")
    with b:
        row = bench_export(args.side, args.spacing, args.resolution, on_block)
    print(f"export of a {row['side_m']:g} x {row['side_m']:g} m bed at {row['resolution_m']:g} m from "
          f"{row['gaussians']} Gaussians: {row['cells']} cells in {row['blocks']} blocks of "
          f"{row['block_samples']} samples, {row['seconds']:.0f} s, peak memory {row['peak_rss_gb']:.2f} GB "
          f"({row['peak_rss_gb_before']:.2f} before the export), height error median "
          f"{1000 * row['height_error_m']['median']:.1f} mm, p99 "
          f"{1000 * row['height_error_m']['p99']:.1f} mm")
    write_json(args.out, row, indent=1)
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


def _bundle_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--grid", type=int, nargs=2, default=(20, 10), metavar=("COLUMNS", "ROWS"),
                        help="photos along and across the flight (default 20 10)")
    parser.add_argument("--spacing", type=positive_float, default=3.5,
                        help="metres between neighbouring photos (default 3.5: about 16 photos see a point)")
    parser.add_argument("--points", type=int, default=20000, help="bed points (default 20000)")
    parser.add_argument("--iterations", type=int, default=2, help="adjustment iterations timed (default 2)")
    parser.add_argument("--solver", choices=("auto", "dense", "sparse"), default="auto",
                        help="the reduced system's solver (default auto: sparse above bundle.DENSE_MAX "
                             "unknowns)")
    parser.add_argument("--out", type=out_file, default=Path("runs/bench/bundle.json"),
                        help="JSON output path")


def _bundle(args: argparse.Namespace) -> int:
    from ragsplat.bench.bundle import bench_bundle

    row = bench_bundle(*args.grid, args.spacing, args.points, args.iterations,
                       {"auto": None, "dense": False, "sparse": True}[args.solver])
    print(f"adjustment through the water of {row['cameras']} photos, {row['points']} points, "
          f"{row['observations']} observations ({row['observation_pairs']} pairs of observations of a "
          f"point): {row['seconds_per_iteration']:.1f} s per iteration, peak memory {row['peak_rss_gb']:.2f} "
          f"GB ({row['peak_rss_gb_before']:.2f} before the adjustment), camera centres "
          f"{100 * row['centre_error_m_median']:.1f} cm off (median)")
    write_json(args.out, row, indent=1)
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


# target -> (one-line help, add arguments, run)
TARGETS = {
    "refraction": ("Snell solvers: error against run time; refract_gaussians cost", _refraction_arguments,
                   _refraction),
    "raster": ("rasterizer: forward+backward time and peak RSS per backend", _raster_arguments, _raster),
    "surfel": ("surfel (2DGS) rasterizer: forward+backward time next to 3DGS's, same process and scene",
               _surfel_arguments, _surfel),
    "train-step": ("median time per training iteration; refraction overhead full/3dgs", _train_step_arguments,
                   _train_step),
    "export": ("the export of a large synthetic bed: time and peak memory", _export_arguments, _export),
    "bundle": ("the adjustment through the water on a synthetic flight: time and peak memory",
               _bundle_arguments, _bundle),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="target", required=True, metavar="TARGET")
    for name, (text, arguments, _) in TARGETS.items():
        arguments(sub.add_parser(name, help=text, description=text))


def run(args: argparse.Namespace) -> int:
    return TARGETS[args.target][2](args)

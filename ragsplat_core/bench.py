"""`ragsplat bench TARGET`: benchmarks that print figures and write JSON (never timed assertions)."""

from __future__ import annotations

import importlib

# target -> (module with add_arguments/run, one-line help)
TARGETS = {
    "refraction": ("ragsplat_core.bench_refraction", "Snell solvers: error against run time; refract_gaussians cost"),
    "raster": ("ragsplat_core.bench_raster", "rasterizer: forward+backward time and peak RSS per backend"),
    "train-step": ("ragsplat_core.bench_train", "median time per training iteration; refraction overhead full/3dgs"),
}


def add_arguments(parser) -> None:
    sub = parser.add_subparsers(dest="target", required=True, metavar="TARGET")
    for name, (module, text) in TARGETS.items():
        importlib.import_module(module).add_arguments(sub.add_parser(name, help=text, description=text))


def run(args) -> int:
    return importlib.import_module(TARGETS[args.target][0]).run(args)

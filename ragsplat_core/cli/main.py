"""The `ragsplat` console entry: one subcommand per job, each in its own module.

A subcommand module defines `add_arguments(parser)` and `run(args) -> int`. Only the chosen module is
imported, so `ragsplat --help` stays fast and no stage pulls in another stage's heavy dependencies. Every
`RagsplatError` a command raises, and every failure of the file system (no space, no permission), becomes
one line on stderr and exit code 2; an interrupt (Ctrl-C, SIGTERM) one line and exit code 130. `--debug`
shows the traceback instead.
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys

from ragsplat.threads import openmp_waits

# name -> (its module, one line of help), in workflow order: make data, train, look at and score a run, the
# ablation, export; then the diagnostics. Every command is a module of this package (`cli/__init__.py`).
COMMANDS: dict[str, tuple[str, str]] = {
    "generate": ("ragsplat.cli.generate",
                "render the synthetic riverbed dataset (Blender Cycles, resumable, shardable)"),
    "train": ("ragsplat.cli.train", "train one RA-GS variant on a dataset directory (resumable)"),
    "render": ("ragsplat.cli.render",
               "render a trained run at its dataset's views: wet, dry or z-depth"),
    "score": ("ragsplat.cli.score",
              "score a trained run or any bed (DEM, LAS/LAZ, PLY, CSV) against a dataset's ground truth"),
    "ablation": ("ragsplat.cli.ablation",
                 "train every variant, evaluate, and print Tables 1 and 2 beside the paper's"),
    "sweep": ("ragsplat.cli.sweep", "a reach at several turbidities, the method against the references"),
    "export": ("ragsplat.cli.export",
               "a trained run's bed as survey products: DEM GeoTIFF, LAS/LAZ, PLY, PNG"),
    "survey": ("ragsplat.cli.survey", "from a survey's photos, RTK positions and water level to a DEM"),
    "stability": ("ragsplat.cli.stability", "numerical stability report of the refraction transform"),
    "bench": ("ragsplat.cli.bench", "benchmarks: refraction solvers, rasterizer, training step"),
}


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("ragsplat")
    except PackageNotFoundError:  # a source tree that was never installed
        return "unknown"


def main(argv: list[str] | None = None) -> int:
    openmp_waits()
    argv = sys.argv[1:] if argv is None else list(argv)
    top = argparse.ArgumentParser(prog="ragsplat", description="Refraction-aware Gaussian splatting toolkit")
    top.add_argument("--version", action="version", version=f"ragsplat {_version()}")
    sub = top.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, text) in COMMANDS.items():
        sub.add_parser(name, help=text, add_help=False)
    if not argv or argv[0] not in COMMANDS:
        args = top.parse_args(argv)
        top.print_help()
        return 0 if args.command is None and not argv else 2
    name = argv[0]
    debug = "--debug" in argv[1:]
    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        return _run(name, argv[1:])
    except KeyboardInterrupt:  # also while a command's modules are still being imported
        if debug:
            raise
        print(f"ragsplat {name}: interrupted; finished files are kept, rerun the same command to resume",
              file=sys.stderr)
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)


def command(name: str, argv: list[str]):
    """The module of command `name` and its arguments parsed from `argv` (a command that runs others, as
    `ragsplat sweep` does, calls `module.run(args)` itself)."""
    module = importlib.import_module(COMMANDS[name][0])
    parser = argparse.ArgumentParser(prog=f"ragsplat {name}", description=COMMANDS[name][1])
    module.add_arguments(parser)
    parser.add_argument("--debug", action="store_true", help="show the traceback of an error")
    return module, parser.parse_args(argv)


def _run(name: str, argv: list[str]) -> int:
    module, args = command(name, argv)
    from ragsplat.errors import RagsplatError

    try:
        return int(module.run(args) or 0)
    except (RagsplatError, OSError) as err:
        if args.debug:
            raise
        print(f"ragsplat {name}: {_one_line(err)}", file=sys.stderr)
        return 2


def _terminate(signum, frame):  # SIGTERM ends a command like Ctrl-C does
    raise KeyboardInterrupt


def _one_line(err: Exception) -> str:  # a RagsplatError or an OSError
    if isinstance(err, OSError):
        where = f"{err.filename}: " if err.filename else ""
        return f"error: {where}{err.strerror or err}"
    return f"error: {err}"


if __name__ == "__main__":
    sys.exit(main())

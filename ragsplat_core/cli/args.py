"""Argument types shared by the commands: a bad value is refused by argparse before any work starts
(usage line, the option named, exit code 2)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path


def _number(kind, text: str):
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {'an integer' if kind is int else 'a number'}, "
                                         f"got {text!r}") from None
    if kind is float and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def positive_int(text: str) -> int:
    value = _number(int, text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def count(text: str) -> int:
    """An integer >= 0 (a seed, a number of warm-up steps)."""
    value = _number(int, text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, got {value}")
    return value


def finite_float(text: str) -> float:
    return _number(float, text)


def refractive_index(text: str) -> float:
    value = _number(float, text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"a refractive index relative to air is >= 1, got {value:g}")
    return value


def positive_float(text: str) -> float:
    value = _number(float, text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {value:g}")
    return value


def non_negative_float(text: str) -> float:
    value = _number(float, text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, got {value:g}")
    return value


def limit(text: str) -> float:
    """A positive number or inf (no limit)."""
    if text.strip().lower() in ("inf", "infinity"):
        return math.inf
    return positive_float(text)


def out_file(text: str) -> Path:
    """A file to write: not an existing directory."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"{path} is a directory; give a file path (e.g. "
                                         f"{path / 'report.json'})")
    return path


def out_file_ending(*suffixes: str):
    """An `out_file` type whose name must end in one of `suffixes` (the name picks the format)."""

    def check(text: str) -> Path:
        path = out_file(text)
        if path.suffix.lower() not in suffixes:
            raise argparse.ArgumentTypeError(f"{path} must end in {' or '.join(suffixes)}")
        return path

    return check


def out_dir(text: str) -> Path:
    """A directory to create or reuse: not an existing file."""
    path = Path(text)
    if path.exists() and not path.is_dir():
        raise argparse.ArgumentTypeError(f"{path} is a file, not a directory")
    return path


def dataset_dir(text: str) -> Path:
    """A dataset directory; its transforms.json given instead stands for the directory."""
    path = Path(text)
    return path.parent if path.name == "transforms.json" and path.is_file() else path


def config_option(parser, config, name: str, *flags: str, more: str = "", **kw) -> None:
    """The option for the field `name` of the dataclass `config` (flag --name-with-dashes unless `flags`), its
    help the field's (metadata "help", then `more`), its default the field's unless `kw` gives one; `kw` as
    argparse's (type, metavar, ...)."""
    from dataclasses import MISSING, fields

    f = next(f for f in fields(config) if f.name == name)
    if f.default is not MISSING and kw.get("action") != "store_true" and not kw.get("required"):
        kw.setdefault("default", f.default)
    if flags and flags[0].startswith("-"):  # an option under another flag still sets the field
        kw.setdefault("dest", name)
    parser.add_argument(*(flags or ("--" + name.replace("_", "-"),)), help=f.metadata["help"] + more, **kw)


# what a command may change of the bed: each `ExtractConfig` field, its argument type and metavar
CULLS = {"min_opacity": (positive_float, "A"), "max_scale_gsd": (limit, "K"), "max_scale_m": (limit, "M"),
         "despike_radius": (positive_float, "M"), "despike_tol": (limit, "M"),
         "fill_gap_cells": (non_negative_float, "K")}


def cull_arguments(parser: argparse.ArgumentParser) -> None:
    """An option for each of `CULLS`, help from its field (unset: the run's or the evaluation's value); read
    them back with `cull_overrides`."""
    from ragsplat.surface import ExtractConfig

    for name, (kind, metavar) in CULLS.items():
        config_option(parser, ExtractConfig, name, type=kind, metavar=metavar, default=None)


def cull_overrides(args: argparse.Namespace) -> dict:
    """The culls given on the command line, as `ExtractConfig` fields."""
    return {name: getattr(args, name) for name in CULLS if getattr(args, name) is not None}


def lpips_arguments(parser: argparse.ArgumentParser) -> None:
    """--vgg16 and --no-download: where LPIPS's weights come from (`ragsplat.eval.metrics.load_lpips`)."""
    parser.add_argument("--vgg16", default=None, metavar="PATH",
                        help="torchvision's vgg16-397923af.pth for LPIPS (default: torch hub cache, "
                             "downloaded there with its hash check when missing)")
    parser.add_argument("--no-download", action="store_true",
                        help="never download the LPIPS weights (offline: LPIPS prints n/a with the reason)")


def uncertainty_arguments(parser: argparse.ArgumentParser, level_default: str) -> None:
    """--uncertainty, --level-sigma, --n-sigma (`ragsplat export`, `ragsplat survey`)."""
    parser.add_argument("--uncertainty", type=Path, metavar="MODEL.json|small|small-field",
                        help="a fitted uncertainty model (`python -m tools.fit_uncertainty`), or a shipped "
                             "one: 'small' (clear water) or 'small-field' (field conditions): the DEM "
                             "gets band 3, each cell's total vertical uncertainty at 95 %% (TVU95, m, "
                             "described 'tvu95'), the LAS/LAZ an extra dimension tvu95 (docs/uncertainty.md)")
    parser.add_argument("--level-sigma", type=non_negative_float, metavar="M",
                        help="with --uncertainty: the water level's standard deviation (m), added to TVU95 "
                             f"as a systematic term (default: {level_default})")
    parser.add_argument("--n-sigma", type=non_negative_float, default=0.0, metavar="S",
                        help="with --uncertainty: the refractive index's standard deviation, likewise "
                             "(default: 0)")


def uncertainty_options(args: argparse.Namespace):
    """The model --uncertainty names (None without), read before any work. Raises ConfigError for a sigma
    without it, or a file that is not a model."""
    from ragsplat.errors import ConfigError
    from ragsplat.export import read_uncertainty

    if args.uncertainty is None:
        given = [o for o, v in (("--level-sigma", args.level_sigma), ("--n-sigma", args.n_sigma)) if v]
        if given:
            raise ConfigError(f"{' and '.join(given)} without --uncertainty: nothing to add them to")
        return None
    return read_uncertainty(args.uncertainty)


"""`ragsplat score RUN|FILE [--truth DIR] [--out FILE.json] ...`: a bed scored against a dataset's ground
truth by the ablation's own measures, beside the reference rows that need no training. Two kinds of PATH:

- RUN, a finished training run's directory (`ragsplat train`, `ragsplat ablation`'s rows; a survey's
  RUN/train): its bed and its held-out views scored without retraining (`ragsplat.eval.score_run`), beside
  the reference answers, written as JSON (default RUN/eval.json); [--data DIR] [--truth DIR] [--dem FILE.tif]
  and the volume bed's culls [--min-opacity A] [--max-scale-gsd K] ... [--vgg16 PATH] [--no-download].
- FILE, any bed (a DEM GeoTIFF, LAS/LAZ, PLY or CSV points, from any software) on the ground truth's nodes
  (`ragsplat.eval.score_file`), for a survey's product also beside the run's own tracks through the water and
  its pinhole model's depths x n as TINs; --truth DIR [--band K] [--kind elevation|depth] [--crs CRS]
  [--no-filter] [--references] [--tvu-band K]; the scores as JSON and its error map as PNG. A DEM with a
  TVU95 band (`ragsplat export --uncertainty`, or --tvu-band K) also gets that band's calibration over the
  wet cells: coverage, median TVU95, z-score variance, IHO orders' shares (docs/uncertainty.md).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ragsplat.cli.args import (
    CULLS,
    cull_arguments,
    cull_overrides,
    dataset_dir,
    lpips_arguments,
    out_file_ending,
    positive_int,
)

RUN_ONLY = ("data", "dem", "vgg16", "no_download")  # and the culls (`CULLS`)
FILE_ONLY = ("band", "kind", "crs", "no_filter", "tvu_band", "references")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("path", type=Path, metavar="RUN|FILE",
                        help="a finished training run's directory, or a bed file: a DEM GeoTIFF (.tif, "
                             ".tiff), LAS/LAZ, PLY (vertex x y z) or CSV (a header with x,y,z) points; in "
                             "the dataset's CRS or any CRS that converts to it, or in the dataset's local "
                             "frame")
    parser.add_argument("--truth", type=dataset_dir, metavar="DIR",
                        help="the dataset whose ground truth scores it (transforms.json, scene.json, gt/): "
                             "needed for a FILE; for a RUN (default: its own dataset) another in the same "
                             "frame, e.g. the synthetic dataset whose COLMAP model a survey run imported")
    parser.add_argument("--out", type=out_file_ending(".json"), metavar="FILE.json",
                        help="the scores as JSON (default: RUN/eval.json, or FILE_score.json beside FILE, "
                             "its error map beside it as NAME_error.png)")
    run = parser.add_argument_group("a run (RUN)")
    run.add_argument("--data", type=dataset_dir, metavar="DIR",
                     help="the run's dataset directory, with its ground truth (default: the one "
                          "RUN/config.json names)")
    run.add_argument("--dem", type=Path, metavar="FILE.tif",
                     help="also score this DEM (`ragsplat export --dem`) and map its error (FILE_error.png)")
    cull_arguments(run)  # of the volume bed
    lpips_arguments(run)
    bed = parser.add_argument_group("a bed file (FILE)")
    bed.add_argument("--band", type=positive_int, metavar="K", help="a DEM's band (default: 1)")
    bed.add_argument("--kind", choices=("elevation", "depth"),
                     help="what the values are (a DEM's band, the points' z); a depth d is the bed height "
                          "h - d, h the height of the dataset's water surface there (its level, or a "
                          "sloping river's plane) (default: elevation)")
    bed.add_argument("--crs", metavar="CRS",
                     help="the file's CRS (EPSG:32633, WKT...) where it names none (PLY, CSV) or a wrong one")
    bed.add_argument("--no-filter", action="store_true",
                     help="points: no outlier filter before the TIN (default: filtered as ragsplat's own "
                          "references are, `tracks.track_filter`)")
    bed.add_argument("--tvu-band", type=positive_int, metavar="K",
                     help="a DEM's band of TVU95 (m) to check against the truth (default: the band "
                          "described 'tvu95', as `ragsplat export --uncertainty` writes it, where there "
                          "is one)")
    bed.add_argument("--references", action="store_true",
                     help="also the tracks' reference rows (TIN of the triangulated tracks, Dietrich's "
                          "correction): triangulates the dataset if not cached yet, minutes")


def _given(args: argparse.Namespace, names: tuple[str, ...]) -> list[str]:
    """The flags of `names` given on the command line (a value, or a switch turned on; a 0 is a value)."""
    return ["--" + n.replace("_", "-") for n in names if getattr(args, n) is not None and getattr(args, n)
            is not False]


def file_table(result: dict) -> str:
    """The file's row, then the reference rows, in the columns of the ablation's Tables 2 and 3."""
    from ragsplat.eval.references import EXTRACTION
    from ragsplat.eval.report import T2_COLUMNS, T3_COLUMNS, geometry_table

    rows = [([Path(result["file"]).name, "DEM" if result["kind"] == "DEM" else "TIN"], result["geometry"])]
    rows += [([f"{name} (uses GT)" if name in result["uses_ground_truth"] else name,
               EXTRACTION.get(name, "-")],
              geometry) for name, geometry in result["references"].items()]
    return geometry_table(["Row", "bed"], rows, T2_COLUMNS + T3_COLUMNS)


def uncertainty_lines(u: dict) -> list[str]:
    """The TVU95 band's figures (`score_file.tvu_band`) in words."""
    if not u["cells"]:
        return [f"- TVU95 (band {u['band']}): no wet cell of the truth has a value"]
    cover = ", ".join(f"{100 * v:.1f} % in {100 * float(p):g} %" for p, v in u["coverage"].items())
    iho = ", ".join(f"{k} {100 * v:.1f} %" for k, v in u["iho"].items() if k != "5cm")
    return [(f"- TVU95 (band {u['band']}), over {u['cells']} wet cells: |dz| <= TVU95 in "
             f"{100 * u['coverage']['0.95']:.1f} % (target 94-96 %); median TVU95 "
             f"{100 * u['median_tvu95']:.2f} cm; z-score variance {u['z_variance']:.3f} (sigma = TVU95 / "
             f"1.96; target 0.8-1.25); the central intervals' coverage {cover}"),
            (f"- cells whose TVU95 is within each IHO S-44 order's TVU at their depth: {iho}; within 5 cm "
             f"{100 * u['iho']['5cm']:.1f} %")]


def run(args: argparse.Namespace) -> int:
    from ragsplat.errors import ConfigError

    if args.path.is_dir():
        wrong = _given(args, FILE_ONLY)
        if wrong:
            raise ConfigError(f"{', '.join(wrong)}: for a bed file; {args.path} is a run's directory")
        return _score_run(args)
    wrong = _given(args, RUN_ONLY + tuple(CULLS))
    if wrong:
        raise ConfigError(f"{', '.join(wrong)}: for a run's directory; {args.path} is a file")
    if args.truth is None:
        raise ConfigError(f"{args.path}: a bed file is scored against a dataset: add --truth DIR")
    return _score_file(args)


def _score_run(args: argparse.Namespace) -> int:
    from ragsplat.eval.score_run import score_run, table
    from ragsplat.outputs import jsonable, write_json

    result = score_run(args.path, args.data, args.vgg16, download=not args.no_download, log=print,
                       truth=args.truth, dem=args.dem, extract=cull_overrides(args))
    out = args.out if args.out is not None else args.path / "eval.json"
    write_json(out, jsonable(result), indent=1)
    print(table(result))
    if args.dem is not None:
        print(f"wrote {result['dem']['error_map']}")
    print(f"wrote {out}")
    return 0


def _score_file(args: argparse.Namespace) -> int:
    from ragsplat.eval.report import depth_error_map, survey_notes
    from ragsplat.eval.score_file import score_file
    from ragsplat.outputs import jsonable, write_json

    result, grid, truth, _ = score_file(args.path, args.truth, args.references, log=print, tvu=args.tvu_band,
                                     band=args.band or 1, depth=args.kind == "depth",
                                     despike=not args.no_filter, crs=args.crs)
    out = args.out if args.out is not None else args.path.with_name(args.path.stem + "_score.json")
    figure = depth_error_map(grid, truth, out.with_name(out.stem + "_error.png"), args.path.name)
    result["error_map"] = str(figure)
    write_json(out, jsonable(result), indent=1)
    what = "cells" if result["kind"] == "DEM" else "points"
    print(f"{result['file']}: {result['kind']}, {result[what]} {what}, in {result['frame']}; "
          f"{result['wet_nodes_covered']} of the ground truth's {result['wet_nodes']} wet cells covered")
    print(file_table(result))
    print(f"\n- F1 at 10 / 30 cm and at 1 % / 3 % of the maximum depth ({result['max_depth_m']:g} m).")
    print("\n".join(f"- {note}" for note in survey_notes({"max_depth_m": result["max_depth_m"],
                                                          "water": result["water"]})))
    if "uncertainty" in result:
        print("\n".join(uncertainty_lines(result["uncertainty"])))
    if not args.references:
        print("- the tracks' reference rows: add --references (triangulates the dataset if not cached, "
              "minutes)")
    print(f"wrote {figure}\nwrote {out}")
    return 0

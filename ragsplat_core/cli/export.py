"""`ragsplat export RUN --dem FILE.tif [--resolution 0.05] [--min-opacity A] [--max-scale-gsd K]
[--despike-radius M] [--despike-tol M] [--fill-gap-cells K] [--las FILE.las|.laz] [--ply FILE] [--png FILE]`.

Turns a finished training run into survey products (`ragsplat.export`): the DEM GeoTIFF (bed elevation
and water depth), and on request the bed points as LAS/LAZ and PLY and a depth map PNG.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ragsplat.cli.args import (
    cull_arguments,
    cull_overrides,
    dataset_dir,
    out_file_ending,
    positive_float,
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", type=Path, metavar="RUN", help="a finished `ragsplat train` output directory")
    parser.add_argument("--dem", required=True, type=out_file_ending(".tif", ".tiff"), metavar="FILE.tif",
                        help="GeoTIFF to write: band 1 bed elevation, band 2 water depth (m)")
    parser.add_argument("--resolution", type=positive_float, default=0.05, metavar="M",
                        help="DEM cell size in metres (default: 0.05)")
    cull_arguments(parser)
    parser.add_argument("--las", type=out_file_ending(".las", ".laz"), metavar="FILE.las|.laz",
                        help="bed points as LAS, or LAZ (compressed)")
    parser.add_argument("--ply", type=out_file_ending(".ply"), metavar="FILE.ply",
                        help="bed points as a PLY of doubles x, y, z")
    parser.add_argument("--png", type=out_file_ending(".png"), metavar="FILE.png",
                        help="water depth map with a colour bar over a hillshade")
    parser.add_argument("--data", type=dataset_dir, metavar="DIR",
                        help="the run's dataset directory (default: the one RUN/config.json names)")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from ragsplat.export import export_run

    bed = export_run(args.run, args.dem, args.resolution, args.las, args.ply, args.png, args.data,
                     **cull_overrides(args))
    depth = bed.depth()[np.isfinite(bed.depth())]
    deepest = f", deepest {depth.max():.3g} m" if len(depth) else ""
    print(f"{len(bed.grid)} cells of {bed.resolution:g} m, {len(depth)} under water{deepest}")
    for path in (args.dem, args.las, args.ply, args.png):
        if path is not None:
            print(f"wrote {path}")
    return 0

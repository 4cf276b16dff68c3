"""`ragsplat export RUN --dem FILE.tif [--resolution 0.05] [--min-opacity A] [--max-scale-gsd K]
[--despike-radius M] [--despike-tol M] [--fill-gap-cells K] [--las FILE.las|.laz] [--ply FILE] [--png FILE]
[--ortho FILE.tif] [--ortho-apparent FILE.tif] [--uncertainty MODEL.json [--level-sigma M] [--n-sigma S]]`.

Turns a finished training run into survey products (`ragsplat.export`): the DEM GeoTIFF (bed elevation
and water depth), and on request the bed points as LAS/LAZ and PLY, a depth map PNG and, on the DEM's grid,
the bed's orthophoto without the water and the photos' mosaic through it (RGBA GeoTIFFs). With a fitted
uncertainty model (`python -m tools.fit_uncertainty`), each cell's TVU95 too: the DEM's band 3 and the
LAS's extra dimension `tvu95` (docs/uncertainty.md).
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
    uncertainty_arguments,
    uncertainty_options,
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
    parser.add_argument("--ortho", type=out_file_ending(".tif", ".tiff"), metavar="FILE.tif",
                        help="the trained bed rendered straight down without the water, on the DEM's grid")
    parser.add_argument("--ortho-apparent", type=out_file_ending(".tif", ".tiff"), metavar="FILE.tif",
                        help="the photos mosaicked through the water as a refraction-blind orthomosaic does")
    parser.add_argument("--data", type=dataset_dir, metavar="DIR",
                        help="the run's dataset directory (default: the one RUN/config.json names)")
    uncertainty_arguments(parser, "0: the run's water taken as exact")


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from ragsplat.export import export_run

    model = uncertainty_options(args)
    bed = export_run(args.run, args.dem, args.resolution, args.las, args.ply, args.png, args.data,
                     uncertainty=model, level_sigma=args.level_sigma or 0.0, n_sigma=args.n_sigma,
                     ortho=args.ortho, ortho_apparent=args.ortho_apparent, **cull_overrides(args))
    depth = bed.depth()[np.isfinite(bed.depth())]
    deepest = f", deepest {depth.max():.3g} m" if len(depth) else ""
    print(f"{len(bed.grid)} cells of {bed.resolution:g} m, {len(depth)} under water{deepest}")
    if bed.tvu95 is not None:
        wet = np.isfinite(bed.depth())
        where = bed.tvu95[wet] if wet.any() else bed.tvu95
        print(f"TVU95 (band 3): median {100 * np.median(where):.1f} cm, p95 "
              f"{100 * np.percentile(where, 95):.1f} cm over the {'wet' if wet.any() else 'covered'} cells "
              f"({args.uncertainty})")
    for path in (args.dem, args.las, args.ply, args.png, args.ortho, args.ortho_apparent):
        if path is not None:
            print(f"wrote {path}")
    return 0

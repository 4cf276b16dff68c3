"""A slim copy of a dataset: what `ragsplat ablation` reads and nothing else, for a machine that cannot take
the whole of it (the `small` reach is 228 MB; a lent GPU takes 64 MiB, its wheels included).

`python -m tools.slim DATA OUT` copies `transforms.json`, `scene.json`, `manifest.json`,
every frame's wet and dry image (and mask), the COLMAP text model, the cached tracks and the ground truth the
scores read (`bed_grid.npy`, `bank_grid.npy`, `bed_surface.npz`, `waterline.json`; not the mesh, the depth
EXRs or the elevation GeoTIFF). Every score of a row made from the copy equals the row made from the whole
dataset.

The tracks are made in DATA first when they are missing (pycolmap), and the copy's stamp names the copy's
own fingerprint: the copy then never triangulates again, which would need pycolmap and, as the triangulation
is not bit-reproducible from one process to the next (docs/method.md), could start the rows from other
points. The stamp may be carried over because the tracks are made from the wet images and the cameras alone,
which the copy keeps byte for byte.

A machine without rasterio (a lent GPU: its wheel is 39 MB) runs the ablation with `--no-geotiffs`: the rows
keep their beds as arrays, and the same command run here, reusing them, writes their GeoTIFFs."""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

from ragsplat.dataset import layout
from ragsplat.dataset.colmap import STAMP, TRACKS, TRIANGULATED, triangulated_points
from ragsplat.errors import DatasetError, RagsplatError
from ragsplat.outputs import write_json

TRUTH = (layout.GT_GRID, layout.GT_BANKS, layout.GT_SURFACE, layout.GT_WATERLINE)
FRAME_FILES = ("file_path", "dry_file_path", "mask_path")  # not gt_depth_file_path: no score reads the EXRs


def slim_copy(src: Path, dst: Path) -> dict:
    """Copy what the ablation reads from dataset `src` into the new folder `dst` (module docstring).
    Returns {"files", "bytes", "fingerprint" (the copy's), "points" (the tracks')}. Raises DatasetError when
    `src` is no dataset or `dst` is not empty."""
    src, dst = Path(src), Path(dst)
    if not (src / layout.TRANSFORMS).is_file():
        raise DatasetError(f"{src}: no {layout.TRANSFORMS}, not a dataset")
    if dst.exists() and any(dst.iterdir()):
        raise DatasetError(f"{dst}: not empty; a slim copy goes into a new folder")
    triangulated_points(src, layout.fingerprint(src))  # the tracks, made here once if missing
    frames = json.loads((src / layout.TRANSFORMS).read_text())["frames"]
    names = [layout.TRANSFORMS, layout.SCENE, layout.MANIFEST, *TRUTH, TRIANGULATED, TRACKS, STAMP]
    names += [str(p.relative_to(src)) for p in sorted((src / layout.COLMAP).glob("*.txt"))]
    names += [f[k] for f in frames for k in FRAME_FILES if f.get(k)]
    total = 0
    for name in dict.fromkeys(names):
        if (src / name).is_file():  # the optional ones (banks, waterline, masks) may be absent
            (dst / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src / name, dst / name)
            total += (dst / name).stat().st_size
    record = json.loads((dst / STAMP).read_text())
    record["fingerprint"] = layout.fingerprint(dst)
    write_json(dst / STAMP, record)
    return {"files": sum(p.is_file() for p in dst.rglob("*")), "bytes": total,
            "fingerprint": record["fingerprint"], "points": record["points"]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.slim", description=__doc__.split("\n\n")[0])
    parser.add_argument("data", type=Path, help="the dataset (its tracks are made there first if missing)")
    parser.add_argument("out", type=Path, help="a new folder for the copy")
    args = parser.parse_args(argv)
    try:
        made = slim_copy(args.data, args.out)
    except (RagsplatError, OSError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"{args.out}: {made['files']} files, {made['bytes'] / 2**20:.1f} MiB, "
          f"fingerprint {made['fingerprint']}, {made['points']} tracks")
    return 0

if __name__ == "__main__":
    sys.exit(main())

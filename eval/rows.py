"""An ablation row's folder (`row_dir`) and its cache: the finished row kept while its key is the same
(`cached_row`), a killed training resumed only under the same key (`start_row`), and the row written with
its beds, rasters and error maps (`save_row`). A row saved without its height GeoTIFFs (`geotiffs=False`: a
machine without rasterio) gets them from its bed arrays when a run with them reuses it (`cached_row`)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ragsplat.dataset import layout, rasters
from ragsplat.eval.report import depth_error_map
from ragsplat.fusion import height_mesh
from ragsplat.outputs import Stamp, changed, claim, jsonable, write_json


def slug(name: str) -> str:
    return name.replace(" ", "-")


def row_dir(out: Path, name: str, seed: int | None) -> Path:
    return out / slug(name) if seed is None else out / slug(name) / f"seed{seed}"


def claim_out(out: Path) -> None:
    """Make `out` an ablation's directory, or check that it is one (`claim`)."""
    claim(out, "ablation", legacy=("results.json", "*/row.json", "*/seed*/row.json", "*/ckpt.pt"))


def cached_row(folder: Path, key: dict, log: Callable[[str], None], geotiffs: bool = True) -> dict | None:
    """The finished row in `folder` when it was made under `key`, else None (a stale one is reported).
    `geotiffs`: a height GeoTIFF the row was saved without is written now from its bed array."""
    path = folder / "row.json"
    if not path.is_file():
        return None
    try:
        row = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        log(f"{path}: unreadable; recomputing")
        return None
    stale = changed(row.get("key"), key)
    if stale:
        log(f"{path}: made with another {', '.join(stale)}; recomputing")
        return None
    outputs = {}
    for suffix in ("", "_fused"):  # a row brought back without its bed arrays gets none
        bed = folder / f"bed{suffix}.npy"
        if geotiffs and f"geotiff{suffix}" not in row.get("outputs", {}) and bed.is_file():
            outputs.update(write_geotiff(folder, suffix, np.load(bed)))
    if outputs:
        row = {**row, "outputs": {**row.get("outputs", {}), **outputs}}
        write_json(path, jsonable(row), indent=1)
    return row


def start_row(folder: Path, key: dict) -> None:
    """Before training: a checkpoint left by a killed run resumes only under the same key."""
    claim(folder, "train run", legacy=("ckpt.pt", "key.json"))  # the trainer's folder, marked before key.json
    stamp = Stamp(folder / "key.json")
    if stamp.path.is_file() and not stamp.holds(key):
        for name in ("ckpt.pt", "curve.json", "row.json"):
            (folder / name).unlink(missing_ok=True)
    stamp.write(key)


def write_geotiff(folder: Path, suffix: str, bed: np.ndarray) -> dict:
    """A row's bed grid [N, 3] as its height GeoTIFF `bed{suffix}.tif` (nodata where nothing was
    reconstructed; none for an empty bed); returns the row's outputs entry for it."""
    if not len(bed):
        return {}
    rasters.write_elevation(folder / f"bed{suffix}.tif", bed, layout.GT_GRID_STEP)
    return {f"geotiff{suffix}": str(folder / f"bed{suffix}.tif")}


def save_row(folder: Path, row: dict, grid: np.ndarray, truth, fused: np.ndarray | None = None,
             geotiffs: bool = True) -> dict:
    """row.json (atomic: a kill never leaves a half-written row that looks finished) plus the extracted bed
    as an array, a height GeoTIFF (`write_geotiff`; not with `geotiffs` False, which needs no rasterio) and
    the depth-error map; the same for the fused bed when given (`*_fused`), with its triangle mesh as a
    PLY."""
    folder.mkdir(parents=True, exist_ok=True)
    outputs = {}
    for suffix, bed in (("", grid), ("_fused", fused)):
        if bed is None:
            continue
        np.save(folder / f"bed{suffix}.npy", bed)
        outputs[f"bed{suffix}"] = str(folder / f"bed{suffix}.npy")
        if geotiffs:
            outputs.update(write_geotiff(folder, suffix, bed))
        if len(bed):
            title = f"{row['name']} seed {row['seed']}" + (", fused" if suffix else "")
            depth_error_map(bed, truth, folder / f"depth_error{suffix}.png", title=title)
            outputs[f"depth_error{suffix}"] = str(folder / f"depth_error{suffix}.png")
        if suffix and len(bed):
            layout.write_ply(folder / "bed_fused.ply", *height_mesh(bed, layout.GT_GRID_STEP),
                             comment="ragsplat fused bed: height grid as triangles (m, z up)")
            outputs["mesh_fused"] = str(folder / "bed_fused.ply")
    row = {**row, "outputs": {**row.get("outputs", {}), **outputs}}
    write_json(folder / "row.json", jsonable(row), indent=1)
    return row

"""Georeferenced rasters, written and read in this one place: values on a regular lattice as deflated,
Cloud-Optimized GeoTIFFs (tiled, with overviews), RGBA images as such, an image's world file. rasterio is
imported when called (the generator's Blender process imports the data contract without it).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ragsplat.dataset.layout import LOCAL_CRS, NODATA
from ragsplat.errors import DatasetError
from ragsplat.outputs import atomic_path


def write_elevation(path: Path, points: np.ndarray, step: float, nodata: float = NODATA) -> None:
    """Grid points [N, 3] on a regular `step` lattice -> single-band float32 GeoTIFF of their heights
    (`write_raster`)."""
    write_raster(path, points[:, :2],
                 [(points[:, 2], "bed elevation (m, z up, water plane at the scene's level)")],
                 step, nodata=nodata)


def raster(xy: np.ndarray, values: np.ndarray, step: float) -> tuple[np.ndarray, tuple[float, float]]:
    """Values [N] at horizontal points xy [N, 2] on a regular `step` lattice -> image [H, W] float64 (row 0
    is the northern edge, NaN where the lattice has no point) and (west, north), its outer corner."""
    ij = np.round((xy - xy.min(0)) / step).astype(np.int64)  # [N, 2] column, row from south
    width, height = ij.max(0) + 1
    image = np.full((height, width), np.nan)
    image[height - 1 - ij[:, 1], ij[:, 0]] = values
    return image, (xy[:, 0].min() - step / 2, xy[:, 1].max() + step / 2)


def write_raster(path: Path, xy: np.ndarray, bands: list[tuple[np.ndarray, str]], step: float,
                 crs: str = LOCAL_CRS, nodata: float = NODATA) -> None:
    """Values at horizontal points xy [N, 2] (coordinates in `crs`) on a regular `step` lattice -> float32
    GeoTIFF with one band per (values [N], description), north up, pixel centres on the lattice nodes,
    `nodata` where the lattice has no point or the value is NaN."""
    images = [raster(xy, values, step) for values, _ in bands]
    west, north = images[0][1]
    stack = np.stack([np.where(np.isnan(image), nodata, image) for image, _ in images]).astype(np.float32)
    write_image(path, stack, [description for _, description in bands], (step, 0.0, west, 0.0, -step, north),
                crs, nodata)


def write_image(path: Path, bands: np.ndarray, descriptions: list[str], transform: tuple, crs: str,
                nodata: float | None, colours: tuple[str, ...] | None = None) -> None:
    """Bands [B, H, W] (their dtype, `nodata` already in place; None: none) -> a deflated Cloud-Optimized
    GeoTIFF (tiled, with overviews: GIS and web maps open a large one quickly), atomically; `transform`: the
    affine's first six coefficients (a, b, c, d, e, f); `colours`: the bands' colour interpretations
    (rasterio's ColorInterp names, e.g. red, green, blue, alpha), else GDAL's default."""
    import rasterio
    from rasterio.transform import Affine

    with atomic_path(path) as tmp, rasterio.open(
            tmp, "w", driver="COG", width=bands.shape[2], height=bands.shape[1], count=len(bands),
            dtype=str(bands.dtype), crs=crs, transform=Affine(*transform), nodata=nodata,
            compress="deflate", overviews="auto") as r:
        for k, (image, description) in enumerate(zip(bands, descriptions), start=1):
            r.write(image, k)
            r.set_band_description(k, description)
        if colours is not None:
            from rasterio.enums import ColorInterp

            r.colorinterp = [ColorInterp[c] for c in colours]


RGBA = ("red", "green", "blue", "alpha")


def write_rgba(path: Path, rgba: np.ndarray, transform: tuple, crs: str, what: str) -> None:
    """An image [4, H, W] uint8 (red, green, blue, alpha: 0 where nothing is drawn) -> an RGBA
    Cloud-Optimized GeoTIFF (`write_image`), each band described as `what` and its colour."""
    write_image(path, rgba, [f"{what}: {c}" for c in RGBA], transform, crs, None, RGBA)


def write_world_file(path: Path, step: float, west: float, north: float) -> None:
    """An image's world file (ESRI's .pgw / .tfw, what GIS reads beside a PNG): the six lines A, D, B, E, C, F
    of a north-up grid of `step` m pixels whose outer corner is (west, north); C, F name the first pixel's
    centre."""
    values = (step, 0.0, 0.0, -step, west + step / 2, north - step / 2)
    with atomic_path(path) as tmp:
        Path(tmp).write_text("".join(f"{v:.10f}\n" for v in values))


def read_world_file(path: Path) -> tuple[float, float, float]:
    """(step, west, north) of a north-up world file (`write_world_file`). Raises DatasetError otherwise."""
    try:
        a, d, b, e, c, f = (float(v) for v in Path(path).read_text().split())
    except (OSError, ValueError):
        raise DatasetError(f"{path}: not a world file (six numbers)") from None
    if d or b or not a > 0 or abs(e + a) > 1e-9 * a:
        raise DatasetError(f"{path}: not a north-up grid of square pixels")
    return a, c - a / 2, f + a / 2

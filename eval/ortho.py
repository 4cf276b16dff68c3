"""An orthophoto against the generator's orthographic truth (`layout.GT_ORTHO`, the scene without the water
seen straight down): PSNR and SSIM over the wet cells, and the shift between the two.

The orthophoto (an RGBA GeoTIFF: `ragsplat export --ortho`, a survey's `ortho_bed.tif` or
`ortho_apparent.tif`) is brought into the dataset's local frame (its georeference's offset taken off; a
survey's of the synthetic photos, in their geotags' CRS, less the geotags' origin:
`score_file.survey_geotags`) and read at the truth's pixel centres, bilinearly between its own; a cell it does
not draw (alpha 0 at any of the four) is left out. The wet cells are those whose exact bed
(`layout.GT_SURFACE`) lies under the dataset's water. SSIM is `ragsplat.ssim`'s (11 px Gaussian window) over
the image with the cells left out filled from the truth, averaged over the scored cells; the shift is the peak
of the two grey images' cross-correlation over the scored cells' bounding box (their means taken off, the
cells left out at 0, a Hann window; a parabola through the peak and its neighbours for the fraction), in
cells, east and north positive: where the orthophoto draws the bed relative to where it is. (OpenCV's phase
correlation, whose spectrum is whitened, came out up to a third of the shift short on such images.)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ragsplat.dataset import layout, rasters
from ragsplat.errors import DatasetError

# the least share of the truth's wet cells an orthophoto must draw to be scored
MIN_DRAWN = 0.2
# Local shifts: blocks of this many cells a side (1.6 m at 5 cm), each scored where at least half its cells
# are: a mosaic displaced differently in each photo's patch shows no mean shift, and shows here.
SHIFT_BLOCK = 32


def read_truth(root: Path) -> tuple[np.ndarray, float, float, float]:
    """(image [H, W, 3] float in [0, 1], step, west, north) of a dataset's orthographic truth. Raises
    DatasetError where it has none (`ragsplat generate` renders it; a dataset made before renders it on a
    rerun)."""
    root = Path(root)
    png, world = root / layout.GT_ORTHO, root / layout.GT_ORTHO_WORLD
    if not png.is_file() or not world.is_file():
        raise DatasetError(f"{root}: no orthographic truth ({layout.GT_ORTHO}); `ragsplat generate` with the "
                           "dataset's preset and seed renders it (one view)")
    step, west, north = rasters.read_world_file(world)
    return layout.read_png(png).astype(np.float64) / 255.0, step, west, north


def on_grid(path: Path, offset, step: float, west: float, north: float, shape) -> np.ndarray:
    """RGBA [H, W, 4] in [0, 1] of the orthophoto at `path`, read bilinearly at the centres of a north-up
    grid of `shape` (H, W) and `step` m cells whose corner is (west, north) in the local frame (the file's
    coordinates minus `offset`, x0 and y0); alpha 0 where any of the four pixels around a centre is undrawn or
    the centre lies outside."""
    import rasterio

    with rasterio.open(path) as r:
        image = r.read().astype(np.float64) / 255.0  # [4, h, w]
        t = r.transform
    if t.b or t.d:
        raise DatasetError(f"{path}: not a north-up raster")
    x = west + (np.arange(shape[1]) + 0.5) * step + offset[0]
    y = north - (np.arange(shape[0]) + 0.5) * step + offset[1]
    u, v = np.meshgrid((x - t.c) / t.a - 0.5, (y - t.f) / t.e - 0.5)  # [H, W] in the file's pixel centres
    j0, i0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    inside = (j0 >= 0) & (i0 >= 0) & (j0 + 1 < image.shape[2]) & (i0 + 1 < image.shape[1])
    j0, i0 = np.clip(j0, 0, image.shape[2] - 2), np.clip(i0, 0, image.shape[1] - 2)
    a, b = u - j0, v - i0
    corners = [image[:, i0 + di, j0 + dj] for di in (0, 1) for dj in (0, 1)]  # each [4, H, W]
    weights = [(1 - a) * (1 - b), a * (1 - b), (1 - a) * b, a * b]
    out = sum(w * c for w, c in zip(weights, corners)).transpose(1, 2, 0)
    drawn = inside & np.all([c[3] > 0 for c in corners], axis=0)
    out[..., 3] = drawn
    return out


def wet_cells(ds, step: float, west: float, north: float, shape) -> np.ndarray:
    """[H, W] bool: the grid's cells whose exact bed lies under the water of the dataset `ds` (a
    `load.Dataset`)."""
    if ds.water is None:
        raise DatasetError(f"{ds.root}: a dry scene has no wet cells")
    surface = layout.Surface.load(Path(ds.root) / layout.GT_SURFACE)
    x = west + (np.arange(shape[1]) + 0.5) * step
    y = north - (np.arange(shape[0]) + 0.5) * step
    xx, yy = np.meshgrid(x, y)
    xy = np.column_stack([xx.ravel(), yy.ravel()])
    points = np.column_stack([xy, surface.height_at(xy)])
    return (ds.water.depth(points) > 0).reshape(shape)


def ortho_scores(image: np.ndarray, truth: np.ndarray, cells: np.ndarray) -> dict:
    """{psnr (dB), psnr_matched (after each channel's least-squares gain and offset), ssim, shift_cells (east,
    north), local_shift_cells (blocks, median, p90: each
    `SHIFT_BLOCK` block's shift's length), cells}: `image` [H, W, 3] against `truth` [H, W, 3] (both in
    [0, 1]) over `cells` [H, W] bool (see the module's note)."""
    import torch

    from ragsplat.ssim import ssim_map

    if not cells.any():
        raise DatasetError("no cells to score")
    mse = float(np.mean((image[cells] - truth[cells]) ** 2))
    # the same after each channel's best gain and offset onto the truth: what is left once the colours
    # agree (the water's dimming taken out), the geometry and the sharpness
    a, b = image[cells], truth[cells]  # [P, 3]
    matched = np.stack([np.polyval(np.polyfit(a[:, c], b[:, c], 1), a[:, c]) for c in range(3)], -1)
    mse_matched = float(np.mean((matched - b) ** 2))
    filled = np.where(cells[..., None], image, truth)
    smap = ssim_map(torch.tensor(filled, dtype=torch.float32), torch.tensor(truth, dtype=torch.float32))
    ssim = float(smap[0].mean(0).numpy()[cells].mean())
    rows, cols = np.nonzero(cells)
    box = (slice(rows.min(), rows.max() + 1), slice(cols.min(), cols.max() + 1))
    dx, dy = image_shift(truth[box].mean(-1), image[box].mean(-1), cells[box])
    local = []
    for i in range(0, cells.shape[0] - SHIFT_BLOCK + 1, SHIFT_BLOCK):
        for j in range(0, cells.shape[1] - SHIFT_BLOCK + 1, SHIFT_BLOCK):
            block = (slice(i, i + SHIFT_BLOCK), slice(j, j + SHIFT_BLOCK))
            if cells[block].mean() >= 0.5:
                shift = image_shift(truth[block].mean(-1), image[block].mean(-1), cells[block])
                local.append(np.hypot(*shift))
    return {"psnr": 10 * np.log10(1.0 / max(mse, 1e-12)),
            "psnr_matched": 10 * np.log10(1.0 / max(mse_matched, 1e-12)), "ssim": ssim,
            "shift_cells": (dx, -dy),
            "local_shift_cells": {"blocks": len(local), "median": float(np.median(local)) if local else None,
                                  "p90": float(np.percentile(local, 90)) if local else None},
            "cells": int(cells.sum())}


def image_shift(reference: np.ndarray, moved: np.ndarray, cells: np.ndarray) -> tuple[float, float]:
    """(columns, rows) by which `moved` [H, W] is displaced from `reference` [H, W] over `cells` [H, W] bool
    (see the module's note)."""
    window = np.outer(np.hanning(reference.shape[0]), np.hanning(reference.shape[1]))
    a, b = (np.where(cells, g - g[cells].mean(), 0.0) * window for g in (reference, moved))
    xc = np.fft.ifft2(np.fft.fft2(b) * np.conj(np.fft.fft2(a))).real
    i, j = np.unravel_index(np.argmax(xc), xc.shape)
    h, w = xc.shape

    def fraction(before: float, at: float, after: float) -> float:  # the parabola's vertex
        curve = before - 2 * at + after
        return 0.0 if curve == 0 else 0.5 * (before - after) / curve

    di = fraction(xc[(i - 1) % h, j], xc[i, j], xc[(i + 1) % h, j])
    dj = fraction(xc[i, (j - 1) % w], xc[i, j], xc[i, (j + 1) % w])
    return float((j - w if j > w // 2 else j) + dj), float((i - h if i > h // 2 else i) + di)


def score_orthophoto(path: Path, root: Path, wet: bool = True) -> dict:
    """`ortho_scores` of the orthophoto at `path` against the truth of the dataset at `root`, over the wet
    cells it draws (`wet`; else every cell it draws), with `drawn`: the share of those cells it draws. Raises
    DatasetError where it draws fewer than `MIN_DRAWN` of them."""
    import rasterio

    from ragsplat.dataset.load import load_dataset
    from ragsplat.eval.score_file import geodetic, survey_geotags

    truth, step, west, north = read_truth(root)
    ds = load_dataset(root, splits=())
    offset = np.asarray(ds.georef.offset, dtype=np.float64)
    with rasterio.open(path) as r:
        crs = r.crs
    geotags = survey_geotags(root)
    if not offset.any() and geodetic(crs) and geotags is not None:
        offset = np.asarray(geotags.offset, dtype=np.float64)
    ortho = on_grid(path, offset, step, west, north, truth.shape[:2])
    region = wet_cells(ds, step, west, north, truth.shape[:2]) if wet else np.ones(truth.shape[:2], bool)
    cells = region & (ortho[..., 3] > 0)
    drawn = cells.sum() / max(region.sum(), 1)
    if drawn < MIN_DRAWN:
        raise DatasetError(f"{path} draws {100 * drawn:.0f} % of the truth's {'wet ' if wet else ''}cells "
                           f"(at least {100 * MIN_DRAWN:.0f} % to be scored): another dataset's, or another "
                           "frame's?")
    return {**ortho_scores(ortho[..., :3], truth, cells), "drawn": float(drawn)}

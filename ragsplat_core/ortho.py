"""Orthophotos on a DEM's grid: the trained bed as if the water were gone, and the photos mosaicked through
it.

`bed_orthophoto` renders a finished run's true Gaussians straight down, without the water (no refraction, no
surface, no water terms): the bed at its true positions. The rasterizers are pinhole, so the orthographic
view is a far pinhole: a nadir camera `far_height` above the grid's reference height, focal length height /
step, so that one pixel covers one cell at that height. A point dz above or below it, rho from the axis, is
drawn rho |dz| / height off its cell; the height keeps that under `ORTHO_PARALLAX` of a cell over the grid's
extent and relief. The image is drawn in tiles of at most `TILE_PX` pixels a side, all from the one centre.

`apparent_mosaic` is what a plain orthomosaic of the photos gives (OpenDroneMap's, Metashape's, Pix4D's): each
cell coloured from the photo whose centre is horizontally nearest among those that see it, at the cell's
height as a survey that ignores refraction has it: the bed where it is dry, the apparent bed (level - depth /
n, where a nadir view sees it) where it is wet, no ray bent. Through the water that picture is displaced and
blurred by the refraction the bed orthophoto takes out.

Tensors and arrays in, arrays out; no I/O (`export.write_orthophoto` writes them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ragsplat.camera import Camera
from ragsplat.water_surface import WaterSurface

# The orthographic view's largest displacement of a point off its cell, in cells: a far pinhole's parallax.
ORTHO_PARALLAX = 0.1
TILE_PX = 512  # an orthophoto's tiles' side in pixels: one render each
# The far pinhole's least height above the reference (m): a flat grid still needs a camera above it.
MIN_HEIGHT = 100.0
NADIR = np.diag([1.0, -1.0, -1.0])  # world -> OpenCV camera looking straight down: x east, y south, z down
# The mosaic looks at this many photos nearest a cell, nearest first, for one that sees it (an oblique's
# centre can be near a cell it does not see), for this many cells at a time.
NEAREST_PHOTOS = 32
MOSAIC_CHUNK = 65536


@dataclass(frozen=True)
class OrthoGrid:
    """A north-up grid of `height` rows and `width` columns of `step` m cells, its outer corner at (`west`,
    `north`) in the local frame; cell (row i, column j) is centred at (west + (j + 0.5) step, north - (i +
    0.5) step), the DEM's nodes (`rasters.raster`)."""

    west: float
    north: float
    step: float
    width: int
    height: int

    @classmethod
    def of_raster(cls, image: np.ndarray, corner: tuple[float, float], step: float) -> OrthoGrid:
        """The grid of a `rasters.raster` image [H, W] and its (west, north) corner."""
        return cls(float(corner[0]), float(corner[1]), float(step), int(image.shape[1]), int(image.shape[0]))

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """(x [W], y [H]) of the cells' centres, columns west to east, rows north to south."""
        return (self.west + (np.arange(self.width) + 0.5) * self.step,
                self.north - (np.arange(self.height) + 0.5) * self.step)

    def transform(self, offset=(0.0, 0.0)) -> tuple:
        """The affine's six coefficients (a, b, c, d, e, f) with the frame's `offset` (x0, y0) added."""
        return (self.step, 0.0, self.west + offset[0], 0.0, -self.step, self.north + offset[1])


def far_height(grid: OrthoGrid, relief: float) -> float:
    """The far pinhole's height above the reference (m): a point `relief` m above or below it at the grid's
    corner is drawn at most `ORTHO_PARALLAX` of a cell off (rho relief / height)."""
    reach = 0.5 * math.hypot(grid.width, grid.height) * grid.step  # the corner's distance from the axis
    return max(MIN_HEIGHT, reach * max(relief, 0.0) / (ORTHO_PARALLAX * grid.step))


def ortho_tiles(grid: OrthoGrid, reference: float, relief: float) -> list[tuple[slice, slice, Camera]]:
    """(rows, columns, camera) of each tile of the orthographic view: far pinholes (`far_height`) that share
    one centre above the grid's middle at `reference` + height, each with its principal point moved to draw
    its own part of the one image."""
    height = far_height(grid, relief)
    x, y = grid.west + 0.5 * grid.width * grid.step, grid.north - 0.5 * grid.height * grid.step
    centre = np.array([x, y, reference + height])
    f = height / grid.step
    tiles = []
    for i0 in range(0, grid.height, TILE_PX):
        for j0 in range(0, grid.width, TILE_PX):
            h, w = min(TILE_PX, grid.height - i0), min(TILE_PX, grid.width - j0)
            cam = Camera(w, h, f, f, 0.5 * grid.width - j0, 0.5 * grid.height - i0, NADIR, -NADIR @ centre)
            tiles.append((slice(i0, i0 + h), slice(j0, j0 + w), cam))
    return tiles


def bed_orthophoto(render, grid: OrthoGrid, reference: float, relief: float, samples: int = 1) -> np.ndarray:
    """RGBA [H, W, 4] float32 in [0, 1] of the orthographic view without the water: `render(camera)` -> (image
    [h, w, 3], alpha [h, w, 1]) of a camera (a run's `runs.Model.render` with interface=False) for each
    tile of `ortho_tiles`, on the grid refined `samples` times each way and averaged back to its cells (a
    cell's area, not its centre's Gaussians: a model trained on finer pixels than the grid's is sub-cell,
    and the rasterizer's 0.3 px dilation would widen it to the cell)."""
    fine = OrthoGrid(grid.west, grid.north, grid.step / samples, grid.width * samples, grid.height * samples)
    out = np.zeros((fine.height, fine.width, 4), dtype=np.float32)
    for rows, cols, cam in ortho_tiles(fine, reference, relief):
        image, alpha = render(cam)
        out[rows, cols, :3] = image.detach().cpu().numpy()
        out[rows, cols, 3] = alpha[..., 0].detach().cpu().numpy()
    return out.reshape(grid.height, samples, grid.width, samples, 4).mean(axis=(1, 3))


def mosaic_height(bed: np.ndarray, water: WaterSurface | None, xy: np.ndarray) -> np.ndarray:
    """The height [P] a refraction-blind survey puts a cell's bed at: the bed [P] where it is dry, the
    apparent bed at nadir, level - depth / n, where the water surface at `xy` [P, 2] lies above it."""
    if water is None:
        return bed
    points = np.column_stack([xy, bed])
    depth = water.depth(points)
    return np.where(depth > 0, bed + depth * (1.0 - 1.0 / water.n), bed)


def apparent_mosaic(photos: list[tuple[Camera, np.ndarray]], grid: OrthoGrid, bed: np.ndarray,
                    water: WaterSurface | None) -> np.ndarray:
    """RGBA [H, W, 4] float32 in [0, 1]: each cell of `grid` with a bed height (`bed` [H, W], NaN: none)
    coloured bilinearly from the photo (camera, image [h, w, 3] uint8) whose centre is horizontally nearest
    among the `NEAREST_PHOTOS` nearest that see the cell at its `mosaic_height`; alpha 0 where no photo
    does or the cell has no height."""
    from scipy.spatial import cKDTree

    out = np.zeros((grid.height, grid.width, 4), dtype=np.float32)
    x, y = grid.centres()
    xx, yy = np.meshgrid(x, y)  # [H, W]
    have = np.isfinite(bed)
    if not have.any() or not photos:
        return out
    xy = np.column_stack([xx[have], yy[have]])  # [P, 2]
    points = np.column_stack([xy, mosaic_height(bed[have], water, xy)])  # [P, 3]
    centres = np.array([cam.camera_center for cam, _ in photos])  # [C, 3]
    tree, k = cKDTree(centres[:, :2]), min(NEAREST_PHOTOS, len(photos))
    rgba = np.zeros((len(xy), 4), dtype=np.float32)
    for start in range(0, len(xy), MOSAIC_CHUNK):
        part = slice(start, start + MOSAIC_CHUNK)
        order = tree.query(xy[part], k=k)[1].reshape(-1, k)  # [p, k] photos, nearest first
        done = np.zeros(len(order), dtype=bool)
        for rank in range(k):
            for c in np.unique(order[~done, rank]):
                rows = np.flatnonzero(~done & (order[:, rank] == c))
                cam, image = photos[c]
                uv, seen = _project(cam, points[part][rows])
                rgba[start + rows[seen], :3] = _bilinear(image, uv[seen])
                done[rows[seen]] = True
            if done.all():
                break
        rgba[part, 3] = done
    out[have] = rgba
    return out


def _project(cam: Camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(`Camera.project`'s pixels [P, 2], centres at i + 0.5; in front and inside the image [P] bool)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        uv, z = cam.project(points)
    inside = (z > 0) & (uv[:, 0] >= 0.5) & (uv[:, 0] <= cam.width - 0.5) & (uv[:, 1] >= 0.5) \
        & (uv[:, 1] <= cam.height - 0.5)
    return uv, inside


def _bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Colours [P, 3] in [0, 1] of `image` [h, w, 3] uint8 at pixel coordinates `uv` [P, 2] (centres at i +
    0.5, inside the outer centres)."""
    u, v = uv[:, 0] - 0.5, uv[:, 1] - 0.5
    j0 = np.clip(np.floor(u).astype(np.int64), 0, image.shape[1] - 2)
    i0 = np.clip(np.floor(v).astype(np.int64), 0, image.shape[0] - 2)
    a, b = (u - j0)[:, None], (v - i0)[:, None]
    at = [image[i0 + di, j0 + dj].astype(np.float32) / 255.0 for di in (0, 1) for dj in (0, 1)]  # gathered
    return (1 - a) * (1 - b) * at[0] + a * (1 - b) * at[1] + (1 - a) * b * at[2] + a * b * at[3]


def rgba_bytes(rgba: np.ndarray) -> np.ndarray:
    """RGBA [H, W, 4] in [0, 1] -> bands [4, H, W] uint8 (a GeoTIFF's)."""
    return np.round(np.clip(rgba, 0, 1) * 255).astype(np.uint8).transpose(2, 0, 1)


"""Products of a finished training run: the bed surface as a DEM GeoTIFF (elevation and water depth), the bed
points as LAS/LAZ and PLY, a depth map PNG over a hillshade, and on the DEM's grid two orthophotos: the bed
as if the water were gone and the photos mosaicked through it (`ragsplat.ortho`; `ragsplat export`). The run
itself is read back by `ragsplat.runs`.

The bed is `surface.extract_surface` of the trained Gaussians on a grid of `resolution` metres, cropped to
the dataset's evaluation region when it has one. Every product is in one coordinate frame: the run's local
frame (metres, x east, y north, z up) plus a `Georef` offset, in the CRS the `Georef` names (default: the
local frame, zero offset). Depth is level - bed height where the bed lies below the water level; emerged
ground has no depth (nodata in the DEM, grey in the PNG; class 2 instead of 40 in the LAS).

With a fitted uncertainty model (`ragsplat.uncertainty.UncertaintyModel`, `export_run(uncertainty=...)`) each
cell also gets its total vertical uncertainty at 95 % (TVU95, m; `cell_tvu95`): the DEM's band 3 ("tvu95")
and the LAS's extra dimension `tvu95`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ragsplat.dataset import layout, rasters
from ragsplat.dataset.layout import Georef
from ragsplat.dataset.load import View
from ragsplat.errors import ConfigError, OutputError
from ragsplat.ortho import OrthoGrid, apparent_mosaic, bed_orthophoto, rgba_bytes
from ragsplat.outputs import atomic_path
from ragsplat.runs import Model, activated_dict, load_model, read_run, run_water
from ragsplat.surface import ExtractConfig, extract_surface, extract_surface_blocks, max_scale, size_cap_m
from ragsplat.train.config import TrainConfig
from ragsplat.uncertainty import UncertaintyModel, cell_features, tvu95
from ragsplat.water_surface import WaterSurface

TVU_BAND = "tvu95"  # the DEM band's description and the LAS extra dimension's name of the cells' TVU95
BATHYMETRIC, GROUND = 40, 2  # ASPRS classes (LAS 1.4 R15): submerged bed ("bathymetric point"), emerged
LAS_SCALE = 0.001  # metres per integer step of the LAS coordinates
# Extraction samples per cell of the DEM grid inside the region: the evaluation's rule
# (`ragsplat.eval.ablation`'s `extract_config`: samples_per_cell x the ground-truth grid's nodes, 16 for every
# preset but the CI's `smoke`), so that at the evaluation's 5 cm a run exports the bed `ragsplat score` scores
# (on a reach its grid counts the wet nodes only; the export cannot know which are wet before extracting and
# counts them all).
SAMPLES_PER_CELL = 16
# A bed whose samples exceed this is extracted in blocks (`surface.extract_surface_blocks`), each of about
# this many: memory is bounded by a block, not the area (about 200 bytes per sample while filtering).
BLOCK_SAMPLES = 2_000_000
MAX_CELLS = 50_000_000  # the DEM's nodes (the grid and its rasters: about 40 bytes each); more is a typo
# The noise filter's neighbourhood (`ExtractConfig.filter_radius`, 10 cm = 2 cells of the evaluation's 5 cm)
# grows with a coarser DEM cell to stay 2 cells wide: the samples thin out with the cells (16 per cell of
# 50 cm leave about 2 within 10 cm, and the filter, which wants 6, would drop the whole bed).
FILTER_RADIUS_CELLS = 2.0
# Never fewer samples than this per Gaussian, whatever the cell: `surface.largest_remainder` hands them out in
# proportion to volume, floors first, so with fewer samples than Gaussians only the largest (and, among
# equals, the first in the file) are sampled at all. At the evaluation's 5 cm it does not bind (the `small`
# reach: 16 x 30 535 nodes for at most 40 000 Gaussians).
SAMPLES_PER_GAUSSIAN = 4


@dataclass(frozen=True)
class Bed:
    """The extracted bed of one run: grid points [G, 3] in the local frame, one per covered cell (its centre,
    the median height), and the water surface in the same frame (None: a dry scene)."""

    grid: np.ndarray
    resolution: float
    water: WaterSurface | None
    georef: Georef
    # [G] m: each cell's TVU95 (`cell_tvu95`), written as the DEM's band 3 and the LAS's `tvu95`; None: none
    tvu95: np.ndarray | None = None
    # the extraction's per-cell record (`surface.extract_surface(..., cells=True)`: samples, spread, filled),
    # where `extract_bed` was asked for it (the uncertainty's features); None: not kept
    cells: dict | None = None

    def absolute(self) -> np.ndarray:  # [G, 3] in the CRS
        return self.grid + np.asarray(self.georef.offset, dtype=np.float64)

    def depth(self) -> np.ndarray:  # [G] water depth (surface height - bed), NaN on emerged ground, dry scene
        if self.water is None:
            return np.full(len(self.grid), np.nan)
        d = self.water.depth(self.grid)
        return np.where(d > 0, d, np.nan)


def export_run(run: Path, dem: Path, resolution: float = 0.05, las: Path | None = None,
               ply: Path | None = None, png: Path | None = None, data: Path | None = None, on_block=None,
               bounds=None, uncertainty: UncertaintyModel | None = None, level_sigma: float = 0.0,
               n_sigma: float = 0.0, ortho: Path | None = None, ortho_apparent: Path | None = None,
               **extract) -> Bed:
    """Extract the bed of a finished run (`load_run`, `extract_bed`, `extract`: its `ExtractConfig` fields to
    change; the size cap in metres, unless given, the run's training's: `surface.size_cap_m`) and write the
    DEM and each other product given a path, in the dataset's georeference (an imported survey's CRS and
    offset), depths below the water the run ended with (`run_water`). `bounds`
    (xmin, ymin, xmax, ymax in the CRS, +-inf where open: a survey's tile) cuts the bed to that box, within
    what it would cover without. `uncertainty`: a fitted model, whose TVU95 of each cell (`cell_tvu95`, from
    the run's training views; `level_sigma` m and `n_sigma`: the standard deviations of the water's level
    and index, the systematic term) the DEM and the LAS then carry. `ortho`, `ortho_apparent`: the bed's
    and the photos' orthophotos on the DEM's grid (`write_orthophotos`). Returns the bed."""
    meta, ds, splats, seed = read_run(Path(run), data, splits=())
    extract = {"max_scale_m": size_cap_m(TrainConfig.from_dict(meta["config"])), **extract}
    water = run_water(meta, ds)
    gaussians, region = activated_dict(splats), ds.eval_region
    if bounds is not None:
        lo, hi = export_box(gaussians, region, ExtractConfig(**extract).min_opacity)
        off = ds.georef.offset
        region = {"xmin": max(lo[0], bounds[0] - off[0]), "ymin": max(lo[1], bounds[1] - off[1]),
                  "xmax": min(hi[0], bounds[2] - off[0]), "ymax": min(hi[1], bounds[3] - off[1])}
    bed = extract_bed(gaussians, resolution, water, region, ds.georef, seed, ds.gsd, on_block,
                      cells=uncertainty is not None, **extract)
    if uncertainty is not None:
        bed = replace(bed, tvu95=cell_tvu95(bed, ds.train_cameras, uncertainty, level_sigma, n_sigma))
    write_dem(dem, bed)
    for path, write in ((las, write_las), (ply, write_ply), (png, write_png)):
        if path is not None:
            write(path, bed)
    if ortho is not None or ortho_apparent is not None:
        run_orthophotos(run, bed, ortho, ortho_apparent, data)
    return bed


def run_orthophotos(run: Path, bed: Bed, ortho: Path | None, apparent: Path | None,
                    data: Path | None = None) -> OrthoGrid:
    """`write_orthophotos` of a finished run (`load_model`, its training photos) on the grid of its `bed`."""
    model, photos = load_model(Path(run), data, splits=("train",))
    return write_orthophotos(model, photos.train, bed, ortho, apparent, photos.gsd)


def write_orthophotos(model: Model, views: list[View], bed: Bed, ortho: Path | None = None,
                      apparent: Path | None = None, gsd: float | None = None) -> OrthoGrid:
    """The orthophotos on the grid of `bed`'s DEM, as RGBA Cloud-Optimized GeoTIFFs in its georeference
    (alpha 0 where nothing is drawn): `ortho`, the trained bed rendered straight down without the water
    (`ortho.bed_orthophoto`, the far pinhole over the bed's median height and its relief, each cell the
    average of renders at about the photos' ground sample distance `gsd`, m), drawn over the area the bed
    covers, its holes included; `apparent`, the `views`' images mosaicked as a refraction-blind orthomosaic
    does (`ortho.apparent_mosaic`). Returns the grid."""
    from scipy.ndimage import binary_fill_holes

    height, corner = rasters.raster(bed.grid[:, :2], bed.grid[:, 2], bed.resolution)  # [H, W], NaN: no cell
    grid = OrthoGrid.of_raster(height, corner, bed.resolution)
    transform = grid.transform(bed.georef.offset[:2])
    if ortho is not None:
        reference = float(np.nanmedian(height))
        relief = float(np.nanmax(np.abs(height - reference)))
        samples = max(1, math.ceil(bed.resolution / gsd - 1e-6)) if gsd else 1
        rgba = bed_orthophoto(lambda cam: model.render(cam, interface=False)[:2], grid, reference, relief,
                              samples)
        rgba[~binary_fill_holes(np.isfinite(height)), 3] = 0  # the bed's area and its holes, not the floaters
        rasters.write_rgba(ortho, rgba_bytes(rgba), transform, bed.georef.crs, "the bed without the water")
    if apparent is not None:
        photos = [(v.camera, v.rgb.cpu().numpy()) for v in views]
        rgba = apparent_mosaic(photos, grid, height, model.water)
        rasters.write_rgba(apparent, rgba_bytes(rgba), transform, bed.georef.crs,
                          "the photos through the water, mosaicked")
    return grid


def merge_orthophotos(paths: list[Path], out: Path) -> None:
    """RGBA orthophotos of one CRS on one lattice (a survey's tiles'), pasted into one, the first that draws a
    pixel (alpha > 0) giving it, and written as `write_orthophotos` writes each."""
    import rasterio

    images = []
    for path in paths:
        with rasterio.open(path) as r:
            images.append((r.read(), r.transform, r.crs, (r.descriptions[0] or "orthophoto").split(":")[0]))
    step = images[0][1].a
    west = min(tr.c for _, tr, _, _ in images)
    north = max(tr.f for _, tr, _, _ in images)
    cols = [round((tr.c - west) / step) for _, tr, _, _ in images]
    rows = [round((north - tr.f) / step) for _, tr, _, _ in images]
    width = max(c + im.shape[2] for c, (im, *_) in zip(cols, images))
    height = max(r + im.shape[1] for r, (im, *_) in zip(rows, images))
    merged = np.zeros((4, height, width), dtype=np.uint8)
    for r0, c0, (im, *_) in zip(rows, cols, images):
        view = merged[:, r0:r0 + im.shape[1], c0:c0 + im.shape[2]]
        take = (view[3] == 0) & (im[3] > 0)
        view[:, take] = im[:, take]
    _, _, crs, what = images[0]
    rasters.write_rgba(out, merged, (step, 0.0, west, 0.0, -step, north), crs, what)



def grid_origin(resolution: float, georef: Georef | None = None) -> tuple[float, float]:
    """A node of the export grid in the local frame: its nodes lie on multiples of `resolution` in the CRS
    (tiles of two runs line up), so the nearest such node to the local origin, minus the offset."""
    offset = (georef or Georef()).offset
    return tuple(round(x0 / resolution) * resolution - x0 for x0 in offset[:2])


def grid_cells(lo, hi, resolution: float, georef: Georef | None = None) -> int:
    """The number of export grid nodes (`grid_origin`) in the box [lo, hi] ((x, y) each, local frame), edges
    included to the extraction's tolerance (`extract_surface` crops with 1e-6 cell)."""
    origin, tol, count = grid_origin(resolution, georef), 1e-6 * resolution, 1
    for a, b, o in zip(lo, hi, origin):
        count *= max(0, math.floor((b - o + tol) / resolution) - math.ceil((a - o - tol) / resolution) + 1)
    return count


def sample_count(lo, hi, resolution: float, georef: Georef | None = None, gaussians: int = 0) -> int:
    """The extraction's sample count for a DEM of `resolution` m over the box [lo, hi] from a model of
    `gaussians` Gaussians: `SAMPLES_PER_CELL` per cell of its grid there (at least one cell), and at least
    `SAMPLES_PER_GAUSSIAN` per Gaussian. Cheap: callers check a survey's size with it before any work.
    Raises ConfigError above `MAX_CELLS` cells."""
    cells = max(grid_cells(lo, hi, resolution, georef), 1)
    if cells > MAX_CELLS:
        area = float(np.prod(np.asarray(hi, float) - np.asarray(lo, float)))
        need = 1.01 * resolution * math.sqrt(cells / MAX_CELLS)  # the count goes as 1 / resolution^2
        step = 10.0 ** (math.floor(math.log10(need)) - 1)
        raise ConfigError(f"resolution {resolution:g} m over {area:.4g} m^2 is {cells:.3g} cells (at most "
                          f"{MAX_CELLS:.0e}); choose a coarser resolution, "
                          f"{math.ceil(need / step) * step:.2g} m or more")
    return max(SAMPLES_PER_CELL * cells, SAMPLES_PER_GAUSSIAN * gaussians)


def export_box(gaussians: dict, region: dict | None, min_opacity: float) -> tuple[np.ndarray, np.ndarray]:
    """The (lo, hi) corners [2] of what is exported: the region, or without one the 1st to 99th percentile of
    the opaque Gaussians' positions (not floaters')."""
    if region is not None:
        return np.array([region["xmin"], region["ymin"]]), np.array([region["xmax"], region["ymax"]])
    means = gaussians["means"].detach().cpu().numpy()  # [N, 3]
    xy = means[gaussians["opacities"].detach().cpu().numpy() >= min_opacity, :2]
    return np.percentile(xy, [1, 99], axis=0) if len(xy) else (np.zeros(2), np.zeros(2))


def extract_bed(gaussians: dict, resolution: float, water: WaterSurface | None, region: dict | None = None,
                georef: Georef | None = None, seed: int = 0, gsd: float | None = None, on_block=None,
                cells: bool = False, **extract) -> Bed:
    """The bed of activated Gaussians (means [N, 3], scales [N, 3], quats [N, 4], opacities [N]) on a grid
    of `resolution` metres whose nodes lie on multiples of it in the CRS (`grid_origin`), inside `region`
    {xmin, xmax, ymin, ymax} when given, by `surface.extract_surface` with the evaluation's settings
    (`ExtractConfig`; `sample_count` samples, the noise filter `FILTER_RADIUS_CELLS` wide at cells coarser
    than the evaluation's) except the fields in `extract` (e.g. min_opacity, max_scale_gsd in ground sample
    distances `gsd`, `Dataset.gsd`). A bed of more than `BLOCK_SAMPLES` samples is extracted in blocks
    (`surface.extract_surface_blocks`, `on_block(done, total)` after each). `cells`: keep the extraction's
    per-cell record in `Bed.cells` (the same grid). Raises ConfigError (too many cells: before any work),
    OutputError (nothing found)."""
    georef = georef or Georef()  # default: the local frame
    cfg = ExtractConfig(gsd=gsd, cell=resolution, seed=seed, **extract)
    n = sample_count(*export_box(gaussians, region, cfg.min_opacity), resolution, georef,
                     len(gaussians["means"]))
    if "filter_radius" not in extract:
        cfg = replace(cfg, filter_radius=max(cfg.filter_radius, FILTER_RADIUS_CELLS * resolution))
    cfg = replace(cfg, n_samples=n)
    g = (gaussians["means"], gaussians["scales"], gaussians["quats"], gaussians["opacities"])
    if n <= BLOCK_SAMPLES:
        grid, stats = extract_surface(*g, cfg, region, grid_origin(resolution, georef), cells=cells)
        if on_block is not None:
            on_block(1, 1)
    else:  # blocks of about BLOCK_SAMPLES samples each
        side = math.isqrt(BLOCK_SAMPLES // SAMPLES_PER_CELL)
        grid, stats = extract_surface_blocks(*g, cfg, side, grid_origin(resolution, georef), region, on_block,
                                             cells=cells)
    if not len(grid):
        raise OutputError(f"no bed surface: no Gaussian is opaque enough (>= {cfg.min_opacity}) and small "
                          f"enough (<= {max_scale(cfg):.3g} m), or the noise filter removed every sample")
    return Bed(grid, resolution, water, georef, cells=stats["cells"] if cells else None)


def cell_tvu95(bed: Bed, cameras, model: UncertaintyModel, level_sigma: float = 0.0,
               n_sigma: float = 0.0) -> np.ndarray:
    """[G] the TVU95 (m) of each cell of `bed` by `model` (`uncertainty.tvu95`) from its features
    (`uncertainty.cell_features`: the views `cameras` (a run's training cameras) through the bed's water, the
    extraction's per-cell record `bed.cells`, the systematic term of the level's and n's standard deviations
    `level_sigma` (m) and `n_sigma`). Raises ConfigError for a bed extracted without its cells' record or a
    model naming an unknown feature."""
    if bed.cells is None:
        raise ConfigError("the bed's cells were not recorded (extract_bed(..., cells=True)): no uncertainty "
                          "features")
    features = cell_features(bed.grid, cameras, bed.water, bed.cells, level_sigma, n_sigma)
    return tvu95(model, features)


# The fitted models that ship with ragsplat, by name (ragsplat_core/tuning/tvu_<name>.json,
# docs/uncertainty.md): "small", fitted and calibrated on development seeds of the `small` preset (4 m up,
# clear water); "small-field", the same features with the scale calibrated on the `small-field` preset's
# development seed (water that absorbs and scatters, sky, glint and ripples)
SHIPPED_MODELS = ("small", "small-field")


def read_uncertainty(path: Path | str) -> UncertaintyModel:
    """The fitted `UncertaintyModel` in the JSON file `path` (`python -m tools.fit_uncertainty` writes one),
    or the shipped model of that name (`SHIPPED_MODELS`) where no such file exists. Raises ConfigError
    (neither, or not a model)."""
    from ragsplat.tuning import record

    path = Path(path)
    if not path.is_file() and str(path) in SHIPPED_MODELS:
        return UncertaintyModel.from_json(json.dumps(record(f"tvu_{path}")))
    if not path.is_file():
        raise ConfigError(f"{path}: no such uncertainty model file (`python -m tools.fit_uncertainty` fits "
                          f"one) and no shipped model of that name ({', '.join(SHIPPED_MODELS)})")
    try:
        return UncertaintyModel.from_json(path.read_text())
    except ConfigError as err:
        raise ConfigError(f"{path}: {err}") from None


def write_dem(path: Path, bed: Bed) -> None:
    """GeoTIFF, two float32 bands: 1 = bed elevation (m, z up, + z0), 2 = water depth (m, nodata on
    emerged ground), and a third where the bed has its TVU95 (`Bed.tvu95`, m, description `TVU_BAND`);
    nodata (`layout.NODATA`) outside the covered cells. Beside it, the depth band's QGIS style
    (`write_depth_style`, the same name ending .qml)."""
    above = ""
    if bed.water is not None:
        w = bed.water.shifted([-v for v in bed.georef.offset])  # in the CRS
        above = f"; water level {w.level:g} m" + (f" at x = y = 0, slope {w.slope[0]:g}, {w.slope[1]:g}"
                                                  if w.tilted else "")
    bands = [(bed.absolute()[:, 2], f"bed elevation (m, z up{above})"),
             (bed.depth(),
              "water depth (m, surface - bed where the bed is submerged; nodata on emerged ground)")]
    if bed.tvu95 is not None:
        bands.append((bed.tvu95, TVU_BAND))
    rasters.write_raster(path, bed.absolute()[:, :2], bands, bed.resolution, crs=bed.georef.crs)
    depth = bed.depth()[np.isfinite(bed.depth())]
    write_depth_style(Path(path).with_suffix(".qml"), float(depth.max()) if len(depth) else 1.0)


STYLE_STOPS = 6  # colours of the depth band's QGIS ramp


def write_depth_style(path: Path, deepest: float) -> None:
    """A QGIS layer style (.qml; QGIS applies it to the raster of the same name when it opens it): the DEM's
    depth band (2) in the depth map's colours (`write_png`'s viridis, shallow yellow to deep blue) from 0 to
    `deepest` m, nodata transparent."""
    from xml.sax.saxutils import quoteattr

    from matplotlib import colormaps, colors

    ramp = colormaps["viridis_r"]
    items = "\n".join(
        f'          <item alpha="255" value="{v:.4f}" label={quoteattr(f"{v:.2f} m")} '
        f'color="{colors.to_hex(ramp(k / (STYLE_STOPS - 1)))}"/>'
        for k, v in enumerate(np.linspace(0.0, deepest, STYLE_STOPS)))
    text = f"""<!DOCTYPE qgis PUBLIC 'http://mrcc.com/qgis.dtd' 'SYSTEM'>
<qgis version="3.28" styleCategories="Symbology">
  <pipe>
    <rasterrenderer type="singlebandpseudocolor" band="2" opacity="1" alphaBand="-1"
                    classificationMin="0" classificationMax="{deepest:.4f}">
      <rastershader>
        <colorrampshader colorRampType="INTERPOLATED" classificationMode="1" clip="0"
                         minimumValue="0" maximumValue="{deepest:.4f}">
{items}
        </colorrampshader>
      </rastershader>
    </rasterrenderer>
  </pipe>
</qgis>
"""
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)


def write_las(path: Path, bed: Bed) -> None:
    """LAS 1.4 (point format 6), or LAZ when `path` ends in .laz: one point per covered cell, integer
    coordinates of 1 mm, classes `BATHYMETRIC` (submerged) and `GROUND` (emerged), the CRS as a WKT record;
    where the bed has its TVU95 (`Bed.tvu95`) an extra dimension `TVU_BAND` (float32, m)."""
    import laspy
    from laspy.vlrs.known import WktCoordinateSystemVlr

    pts = bed.absolute()
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.full(3, LAS_SCALE)
    header.offsets = np.floor(pts.min(0))  # whole metres: small positive integers fit int32 up to 2000 km
    header.vlrs.append(WktCoordinateSystemVlr(bed.georef.wkt()))
    header.global_encoding.wkt = True
    if bed.tvu95 is not None:
        header.add_extra_dim(laspy.ExtraBytesParams(name=TVU_BAND, type=np.float32,
                                                    description="TVU95 (m), 95 % vertical"))
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    las.classification = np.where(np.isnan(bed.depth()), GROUND, BATHYMETRIC).astype(np.uint8)
    if bed.tvu95 is not None:
        las[TVU_BAND] = bed.tvu95.astype(np.float32)
    # A stream, not the path: laspy picks compression by the name's suffix, and tmp's is .tmp
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        las.write(f, do_compress=Path(path).suffix.lower() == ".laz")


def write_ply(path: Path, bed: Bed) -> None:
    """The same points as a PLY of doubles x, y, z in the CRS."""
    layout.write_ply(path, bed.absolute(), comment=f"ragsplat bed points (m, z up, CRS {bed.georef.crs})")


def hillshade(z: np.ndarray, step: float, azimuth: float = 315.0, altitude: float = 45.0) -> np.ndarray:
    """Heights [H, W] (row 0 north, NaN = none) -> illumination [H, W] in [0, 1] by a sun at `azimuth` degrees
    clockwise from north and `altitude` above the horizon (NaN next to missing cells)."""
    d_row, d_col = np.gradient(z, step)
    normal = np.stack([-d_col, d_row, np.ones_like(z)])  # (-dz/dx, -dz/dy, 1); y grows northwards = -row
    az, alt = np.radians(azimuth), np.radians(altitude)
    sun = np.array([np.sin(az) * np.cos(alt), np.cos(az) * np.cos(alt), np.sin(alt)])
    return np.clip(np.einsum("khw,k->hw", normal, sun) / np.linalg.norm(normal, axis=0), 0, 1)


def draw_depth(fig, ax, height: np.ndarray, depth: np.ndarray, step: float, extent) -> np.ndarray:
    """The depth map on `ax` of `fig`: water depth [H, W] (NaN: none) in colour, with a colour bar, over a
    hillshade of the heights [H, W], `step` m cells over `extent` (west, east, south, north); returns the wet
    cells' depths."""
    ax.imshow(hillshade(height, step), cmap="gray", vmin=0, vmax=1, extent=extent)
    wet = depth[np.isfinite(depth)]
    im = ax.imshow(depth, cmap="viridis_r", alpha=0.65, extent=extent, vmin=0,
                   vmax=float(wet.max()) if len(wet) else 1.0)
    fig.colorbar(im, ax=ax, label="water depth (m); grey: emerged ground", shrink=0.85)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    return wet


def write_png(path: Path, bed: Bed) -> None:
    """Water depth in colour, with a colour bar, over a hillshade of the bed (emerged ground in grey)."""
    from ragsplat.pages import pyplot

    plt = pyplot()

    xy, step = bed.absolute()[:, :2], bed.resolution
    height, (west, north) = rasters.raster(xy, bed.absolute()[:, 2], step)
    depth, _ = rasters.raster(xy, bed.depth(), step)
    extent = (west, west + height.shape[1] * step, north - height.shape[0] * step, north)
    fig, ax = plt.subplots(figsize=(7, 5.5), constrained_layout=True)
    draw_depth(fig, ax, height, depth, step, extent)
    ax.set_title(f"water depth over a hillshade of the bed, {step:g} m cells")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)

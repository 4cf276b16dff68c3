"""RUN/report.html: a finished survey on one self-contained page (its figures inlined as PNG data; it opens
offline), as a photogrammetry package's processing report gives it.

Maps: the bed orthophoto (the trained bed without the water) beside the photos' mosaic through it; the water
depth with a colour bar and contours over a hillshade, the cameras on it; the DEM's cover and its holes; how
many photos see the bed at each cell (through the water where it is submerged); the TVU95 band where the DEM
has one. Then the structure from motion (registered photos, points, each photo's
reprojection error), the georeference (each position's residual), the water (how its level was found and
how sure, the model's points' heights about it) and every line the command said, with each stage's seconds
and the process's peak memory when it said it. Every section reads what its stage wrote (RUN/*.json, the
COLMAP model, the rasters), so the page is the same whatever rerun made it; a stage the run stopped before
has no section.
"""

from __future__ import annotations

import json
import resource
import time
from dataclasses import asdict, dataclass
from itertools import pairwise
from pathlib import Path

import numpy as np

from ragsplat.pages import figure_uri, pyplot, write_page

REPORT = "report.html"
DEPTH_CONTOURS = 8  # about this many contour lines over the depth range
OVERLAP_CELLS = 250_000  # the overlap map's cells at most: the DEM's taken at a stride
FEW_VIEWS = 5  # fewer photos than this see a cell: a nadir grid's depths there are the least sure


@dataclass(frozen=True)
class Said:
    """One line the survey said: its stage, its text, the seconds its step took (None: not timed), when it
    was said (seconds since the command began) and the process's peak resident memory then (GiB)."""

    stage: str
    text: str
    seconds: float | None
    at: float
    peak_gib: float


class Recorder:
    """A `Progress` (`survey.stages.base`) that keeps every line it hears (`said`) and passes all on."""

    def __init__(self, inner):
        self.inner, self.said, self.start = inner, [], time.perf_counter()

    def say(self, stage: str, text: str, since: float | None = None) -> None:
        now = time.perf_counter()
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB on Linux -> GiB
        self.said.append(Said(stage, text, None if since is None else now - since, now - self.start, peak))
        self.inner.say(stage, text, since)

    def bar(self, total: int, desc: str, unit: str):
        return self.inner.bar(total, desc, unit)

    def count(self, desc: str, unit: str):
        return self.inner.count(desc, unit)

    def training(self, total: int, desc: str, initial: int):
        return self.inner.training(total, desc, initial)


def _read(path: Path):
    """(bands [B, H, W] with NaN for nodata (float) or as stored (uint8), extent (west, east, south, north))
    of a raster, or None where there is none."""
    import rasterio

    if not path.is_file():
        return None
    with rasterio.open(path) as r:
        bands = r.read()
        if r.nodata is not None and bands.dtype.kind == "f":
            bands = np.where(bands == r.nodata, np.nan, bands)
        b = r.bounds
        return bands, (b.left, b.right, b.bottom, b.top)


def _local(extent, origin) -> tuple:  # an extent in metres from the map's south-west corner
    return (extent[0] - origin[0], extent[1] - origin[0], extent[2] - origin[1], extent[3] - origin[1])


def _cameras(model: Path) -> tuple[dict[str, np.ndarray], dict[str, float], int, object]:
    """({photo: centre [3] in the CRS}, {photo: mean reprojection error (px)}, points, the
    `pycolmap.Reconstruction`) of a COLMAP model."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(model))
    centres, errors = {}, {}
    for image in rec.images.values():
        centres[image.name] = np.asarray(image.projection_center())
        seen = [rec.points3D[p.point3D_id].error for p in image.points2D if p.has_point3D()]
        errors[image.name] = float(np.mean(seen)) if seen else float("nan")
    return centres, errors, len(rec.points3D), rec


def _maps(out: Path, centres: dict[str, np.ndarray], rec=None, surface=None) -> list[dict]:
    """The map figures: [{title, src, note}]; the overlap map with the model `rec` and the water `surface`."""
    from ragsplat.export import draw_depth

    plt = pyplot()
    dem = _read(out / "dem.tif")
    if dem is None:
        return []
    bands, extent = dem
    origin = (extent[0], extent[2])
    ext = _local(extent, origin)
    step = (extent[1] - extent[0]) / bands.shape[2]
    height, depth = bands[0], bands[1]
    figures = []
    named = (("the bed without the water (ragsplat)", "ortho_bed.tif"),
             ("the photos mosaicked through the water", "ortho_apparent.tif"))
    orthos = [(name, _read(out / f)) for name, f in named]
    orthos = [(name, o) for name, o in orthos if o is not None]
    if orthos:
        fig, axes = plt.subplots(1, len(orthos), figsize=(6.5 * len(orthos), 5.5), constrained_layout=True,
                                 squeeze=False)
        for ax, (name, (rgba, oext)) in zip(axes[0], orthos):
            ax.imshow(rgba.transpose(1, 2, 0), extent=_local(oext, origin))
            ax.set_title(name)
            ax.set_xlabel("x (m)")
            ax.set_ylabel("y (m)")
        figures.append({"title": "Orthophotos", "src": figure_uri(fig),
                        "note": "Left: the trained bed rendered straight down without the water, at "
                                "its true positions. Right: what a refraction-blind orthomosaic of the same "
                                "photos gives (each cell from the nearest photo, at the apparent bed's "
                                "height)."})
    fig, ax = plt.subplots(figsize=(8, 6), constrained_layout=True)
    wet = draw_depth(fig, ax, height, depth, step, ext)
    if len(wet):
        levels = np.linspace(0, float(wet.max()), DEPTH_CONTOURS + 2)[1:-1]
        if len(levels) and levels[-1] > levels[0]:
            x = np.linspace(ext[0] + step / 2, ext[1] - step / 2, depth.shape[1])
            y = np.linspace(ext[3] - step / 2, ext[2] + step / 2, depth.shape[0])
            cs = ax.contour(x, y, np.where(np.isfinite(depth), depth, np.nan), levels=levels, colors="k",
                            linewidths=0.6)
            ax.clabel(cs, fmt="%.2f", fontsize=7)
    if centres:
        c = np.array(list(centres.values()))
        ax.plot(c[:, 0] - origin[0], c[:, 1] - origin[1], "r.", ms=4, label=f"{len(c)} cameras")
        ax.legend(loc="upper right", fontsize=8)
    ax.set_xlim(ext[0], ext[1])
    ax.set_ylim(ext[2], ext[3])
    ax.set_title(f"water depth over a hillshade of the bed, {step:g} m cells, and the cameras")
    figures.append({"title": "Depth", "src": figure_uri(fig),
                    "note": f"{int(np.isfinite(height).sum())} cells, {len(wet)} under water"
                            + (f", deepest {wet.max():.2f} m" if len(wet) else "") + "."})
    covered = np.isfinite(height)
    if covered.any():
        from scipy.ndimage import binary_fill_holes

        inside = binary_fill_holes(covered)
        holes = inside & ~covered
        fig, ax = plt.subplots(figsize=(8, 6), constrained_layout=True)
        image = np.ones(covered.shape + (3,))
        image[covered] = (0.75, 0.75, 0.75)
        image[holes] = (0.85, 0.1, 0.1)
        ax.imshow(image, extent=ext)
        ax.set_title("cover: grey covered, red holes inside the covered area")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        figures.append({"title": "Cover and holes", "src": figure_uri(fig),
                        "note": f"{100 * covered.sum() / inside.sum():.1f} % of the area the DEM encloses is "
                                f"covered; {int(holes.sum())} cells are holes."})
    if covered.any() and rec is not None and surface is not None:
        figures.append(_overlap(height, extent, ext, rec, surface))
    if bands.shape[0] > 2:
        tvu = bands[2]
        fig, ax = plt.subplots(figsize=(8, 6), constrained_layout=True)
        im = ax.imshow(100 * tvu, cmap="magma_r", extent=ext)
        fig.colorbar(im, ax=ax, label="TVU95 (cm)", shrink=0.85)
        ax.set_title("total vertical uncertainty at 95 %")
        figures.append({"title": "TVU95", "src": figure_uri(fig),
                        "note": f"median {100 * np.nanmedian(tvu):.1f} cm over the covered cells."})
    return figures


def _overlap(height: np.ndarray, extent, ext, rec, surface) -> dict:
    """The overlap map: how many of the model's registered photos see the bed at the DEM's cells (the bed
    heights `height` [H, W] over `extent`, taken at a stride to at most `OVERLAP_CELLS`), a submerged cell
    at its apparent position through `surface`, as `refraction.views_through_water` counts them."""
    from matplotlib.colors import BoundaryNorm, ListedColormap

    from ragsplat.refraction import VIEW_BINS, views_through_water
    from ragsplat.survey import sfm

    plt = pyplot()
    stride = max(1, int(np.ceil(np.sqrt(height.size / OVERLAP_CELLS))))
    z = height[::stride, ::stride]
    step = (extent[1] - extent[0]) / height.shape[1]
    rows, cols = np.nonzero(np.isfinite(z))
    x = extent[0] + (cols * stride + 0.5) * step
    y = extent[3] - (rows * stride + 0.5) * step
    points = np.column_stack([x, y, z[rows, cols]])
    ids, _, R, centres, K = sfm.cameras(rec)
    sizes = np.array([[rec.images[i].camera.width, rec.images[i].camera.height] for i in ids]).reshape(-1, 2)
    seen = views_through_water(points, R, centres, K, sizes, surface)
    grid = np.full(z.shape, np.nan)
    grid[rows, cols] = seen
    edges = [lo for lo, _ in VIEW_BINS] + [VIEW_BINS[-1][0] + 1]
    colours = ListedColormap(["#c0392b", "#e67e22", "#f1c40f", "#7dcea0", "#1e8449"][:len(VIEW_BINS)])
    fig, ax = plt.subplots(figsize=(8, 6), constrained_layout=True)
    im = ax.imshow(np.minimum(grid, edges[-1] - 0.5), cmap=colours,
                   norm=BoundaryNorm(np.array(edges) - 0.5, colours.N), extent=ext)
    bar = fig.colorbar(im, ax=ax, shrink=0.85, label="photos that see the bed")
    bar.set_ticks([(a + b) / 2 - 0.5 for a, b in pairwise(edges)],
                  labels=[f"{lo}-{hi}" if hi else f"{lo}+" for lo, hi in VIEW_BINS])
    ax.set_title("overlap: photos that see the bed (through the water where it is submerged)")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    wet = points[:, 2] < surface.height(points[:, :2])
    few = seen < FEW_VIEWS
    note = (f"median {np.median(seen):.0f} photos a cell; {100 * few.mean():.1f} % of the cells are seen by "
            f"fewer than {FEW_VIEWS}")
    if wet.any():
        note += (f", {100 * few[wet].mean():.1f} % of those under water, where a nadir flight's depths are "
                 f"the least sure (obliques or more overlap see them from more photos)")
    return {"title": "Overlap", "src": figure_uri(fig), "note": note + "."}


def _bars(labels: list[str], values: list[np.ndarray], names: list[str], ylabel: str, title: str) -> str:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(max(6.0, 0.12 * len(labels) + 2), 3.5), constrained_layout=True)
    x = np.arange(len(labels))
    width = 0.8 / len(values)
    for k, (v, name) in enumerate(zip(values, names)):
        ax.bar(x + (k - (len(values) - 1) / 2) * width, v, width, label=name)
    ax.set_xticks(x[::max(1, len(x) // 30)], [labels[i] for i in x[::max(1, len(x) // 30)]], rotation=90,
                  fontsize=7)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    if len(values) > 1:
        ax.legend(fontsize=8)
    return figure_uri(fig)


def _structure(errors: dict[str, float], points: int, photos: int) -> dict:
    names = sorted(errors)
    values = np.array([errors[n] for n in names])
    return {"registered": len(names), "photos": photos, "points": points,
            "median_px": float(np.nanmedian(values)) if len(values) else float("nan"),
            "src": _bars(names, [values], ["error"], "mean reprojection error (px)",
                         "each registered photo's mean reprojection error") if names else None}


def _georef(out: Path) -> dict | None:
    path = out / "georef.json"
    if not path.is_file():
        return None
    g = json.loads(path.read_text())
    res = g.get("residual_m", {})
    names = sorted(res)
    r = np.array([res[n] for n in names]) if names else np.zeros((0, 3))
    src = _bars(names, [100 * np.hypot(r[:, 0], r[:, 1]), 100 * np.abs(r[:, 2])], ["horizontal", "vertical"],
                "residual (cm)", f"each position's residual after the similarity to {g.get('to', 'them')}") \
        if names else None
    return {"to": g.get("to"), "inliers": g.get("inliers"), "count": g.get("count"),
            "rms_cm": 100 * g.get("rms_m", float("nan")), "scale": g.get("scale"),
            "scale_uncertainty": g.get("scale_uncertainty"), "src": src}


def _surface(out: Path, n: float):
    """The run's water surface (`WaterSurface`, RUN/water.json's, of index `n`), or None without one."""
    from ragsplat.water_surface import WaterSurface

    path = out / "water.json"
    return WaterSurface(**{**json.loads(path.read_text())["surface"], "n": n}) if path.is_file() else None


def _water(out: Path, rec, surface) -> dict | None:
    """The water's section, of RUN/water.json and its `surface` (`_surface`); None without one."""
    if surface is None:
        return None
    w = json.loads((out / "water.json").read_text())
    src = None
    if rec is not None and len(rec.points3D):
        plt = pyplot()
        xyz = np.array([p.xyz for p in rec.points3D.values()])
        dz = xyz[:, 2] - surface.height(xyz[:, :2])
        lo, hi = np.percentile(dz, [1, 99])
        fig, ax = plt.subplots(figsize=(7, 3.5), constrained_layout=True)
        ax.hist(dz[(dz >= lo) & (dz <= hi)], bins=80, color="steelblue")
        ax.axvline(0, color="k", lw=1)
        ax.set_xlabel("the model's points' height above the water surface (m)")
        ax.set_ylabel("points")
        ax.set_title("the points about the water (below it: the bed seen through the water, refraction taken "
                     "out)", fontsize=9)
        src = figure_uri(fig)
    from ragsplat.survey.stages.water import level_sigma

    est = w.get("estimated")
    by = None if est is None else ("from the shoreline" if est.get("by") == "shoreline"
                                   else "by the adjustment through the water")
    if est is not None:
        by += f", ± {100 * level_sigma(est)[0]:.1f} cm (1 sigma)"
    return {"described": w.get("described"), "by": by,
            "estimated": est, "below": w.get("points_below"), "above": w.get("points_above"), "src": src}


def write_report(out: Path, said: list[Said], photos: int) -> Path:
    """RUN/report.html of the survey in `out` of `photos` photos, with the lines it said (`Recorder.said`).
    Returns its path."""
    from ragsplat.outputs import versions

    out = Path(out)
    survey = json.loads((out / "survey.json").read_text()) if (out / "survey.json").is_file() else {}
    model = out / "model"
    centres, errors, points, rec = (_cameras(model) if (model / "images.txt").is_file()
                                    or (model / "images.bin").is_file() else ({}, {}, 0, None))
    surface = _surface(out, float(survey["n"])) if "n" in survey else None
    return write_page(out / REPORT, "survey.html.j2",
                      title=f"ragsplat survey: {survey.get('images', out)}",
                      out=str(out), settings=survey, maps=_maps(out, centres, rec, surface),
                      structure=_structure(errors, points, photos) if errors else None,
                      georef=_georef(out),
                      water=_water(out, rec, surface),
                      said=[asdict(s) for s in said], versions=versions("torch", "pycolmap"))

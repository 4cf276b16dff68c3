"""Any bed a user brings, on the ground truth's nodes, scored as every row of the tables (`ragsplat score
FILE`).

File kinds, by extension: a DEM GeoTIFF (.tif, .tiff; one band of bed elevation or water depth), LAS/LAZ, PLY
(ascii or binary, a `vertex` element with x, y, z) and CSV points (a header naming x, y and z columns). A
depth is made a bed height below the dataset's water surface: z = its height at the node's x, y - depth (one
level for a lake, a sloping plane's height there for a river).

Frames. A file is brought into the dataset's local frame (`layout.Georef`: absolute = local + offset):
- when both the file and the dataset name a geodetic CRS (projected or geographic), the file is reprojected
  into the dataset's CRS (`rasterio.warp.transform`, horizontally: heights are taken in the dataset's
  vertical datum) and the dataset's offset (x0, y0, z0) is taken off;
- otherwise (a PLY or CSV, a file naming no CRS or a local one, a dataset in its own local frame) the
  coordinates are taken as the dataset's: either local, or absolute (UTM-sized) with the offset to take off;
  of the two, the one that puts more of the ground truth's wet nodes under the bed is used.

Gridding, onto the ground truth's nodes (`GroundTruth.nodes`), so that every bed is scored on the same cells:
- a DEM is read at each node: where the node is a cell centre (a DEM on the truth's lattice), that cell's
  value; elsewhere bilinear between the four cell centres around it, or, where one of them is empty, the
  value of the cell the node lies in. A node in an empty cell is a hole;
- points as ragsplat's own references grid their tracks (`ragsplat.eval.references.gridded`): the outlier
  filter `tracks.track_filter` with the references' settings `TIN_FILTER` (switchable), then linear on their
  Delaunay triangulation (`tracks.tin`). Only the points within the filter's radius of the nodes are read.

A survey run's product (a file in the folder of RUN/survey.json, RUN/water.json and RUN/model/) is scored
beside the run's own points as a TIN, gridded as points are: the tracks adjusted through the water, what the
run's photos give without training, and the field's practice without ragsplat: the pinhole model's depths
times n (`survey_points`).

A file whose bed covers fewer than `MIN_COVER` of the truth's wet nodes is refused (DatasetError).

A DEM with a TVU95 band (`ragsplat export --uncertainty`: described `export.TVU_BAND`, or the band named) is
checked at its own cells, not at the truth's nodes: each covered cell's height against the exact bed at the
cell's centre, inside the truth's region, where the water covers the true bed (`tvu_band`); read bilinearly at
the nodes, as the heights are scored, four cells' errors would be averaged (a DEM's lattice need not fall on
the truth's nodes: `ragsplat export`'s does not) and the band would look wider than it is. Its calibration
is reported over those cells (`calibration.tvu_band_summary`: the coverage of |dz| <= TVU95, the median
TVU95, the z-scores' variance, the IHO orders' shares).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ragsplat.errors import ConfigError, DatasetError
from ragsplat.eval.references import (
    SURVEY_PINHOLE,
    SURVEY_TRACKS,
    TIN_FILTER,
    USES_GROUND_TRUTH,
    depth_times_n,
    gridded,
    oracle_grids,
)

KINDS = {".tif": "DEM", ".tiff": "DEM", ".las": "LAS", ".laz": "LAS", ".ply": "PLY", ".csv": "CSV"}
MIN_COVER = 0.01  # of the ground truth's wet nodes: a bed covering fewer is another place or another frame
SNAP = 1e-6  # cells: a node this close to a cell centre takes that cell's value alone
PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
             "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
             "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
PLY_BINARY = {"binary_little_endian": "<", "binary_big_endian": ">"}


@dataclass(frozen=True)
class Frame:
    """A file's coordinates -> the dataset's local frame: reprojected from the CRS `src` to `dst` (None:
    not), then `offset` [3] taken off."""

    label: str
    offset: np.ndarray
    src: object = None  # rasterio CRSs
    dst: object = None

    def to_local(self, xy: np.ndarray) -> np.ndarray:  # [P, 2] the file's -> [P, 2] local
        return _warp(self.src, self.dst, xy) - self.offset[:2]

    def to_file(self, xy: np.ndarray) -> np.ndarray:  # [N, 2] local -> [N, 2] the file's
        return _warp(self.dst, self.src, xy + self.offset[:2])


def _warp(src, dst, xy: np.ndarray) -> np.ndarray:
    if src is None or not len(xy):
        return xy
    from rasterio.warp import transform

    return np.column_stack(transform(src, dst, xy[:, 0], xy[:, 1]))


def geodetic(crs) -> bool:
    return crs is not None and (crs.is_projected or crs.is_geographic)


def crs_name(crs) -> str | None:
    """"EPSG:N", else the WKT; None for no CRS."""
    return None if crs is None else crs.to_string()


def _label(crs) -> str:  # a CRS in a message
    return "no CRS" if crs is None else crs_name(crs) if geodetic(crs) else "a local frame"


def survey_geotags(data: Path):
    """The frame a synthetic survey's photos were geotagged in: `layout.Georef` of survey.json's "geo" (the
    scene's x, y, z are its CRS's coordinates less `origin_metric`), or None (no such record)."""
    import json

    from ragsplat.dataset import layout

    path = Path(data) / layout.SURVEY_RECORD
    geo = json.loads(path.read_text()).get("geo") if path.is_file() else None
    return None if geo is None else layout.Georef(tuple(geo["origin_metric"]), geo["crs"])


def frames(crs, georef) -> list[Frame]:
    """The candidate frames (module docstring) of a file in `crs` (rasterio CRS or None) for a dataset with
    `georef` (`layout.Georef`)."""
    from rasterio.crs import CRS

    mine, offset = CRS.from_user_input(georef.crs), np.asarray(georef.offset, dtype=np.float64)
    if geodetic(crs) and geodetic(mine):
        if crs == mine:
            return [Frame("the dataset's CRS, its offset taken off", offset)]
        return [Frame(f"reprojected from {crs_name(crs)} to the dataset's CRS, its offset taken off", offset,
                      crs, mine)]
    local = Frame("the dataset's local frame", np.zeros(3))
    absolute = Frame("the dataset's frame with its offset, taken off", offset)
    return [local, absolute] if offset.any() else [local]


def read_points(path: Path, kind: str) -> tuple[np.ndarray, object]:
    """([P, 3] float64 x, y, z as the file has them, its CRS or None) of a LAS/LAZ, PLY or CSV file."""
    from laspy.errors import LaspyException

    try:
        if kind == "LAS":
            return _read_las(path)
        return (read_ply_points(path) if kind == "PLY" else _read_csv(path)), None
    except DatasetError:
        raise
    except (ValueError, KeyError, IndexError, LaspyException) as err:  # not what its name says
        raise DatasetError(f"{path}: not a readable {kind} point file ({err})") from None


def _read_las(path: Path) -> tuple[np.ndarray, object]:
    """The points and the CRS of a LAS/LAZ: its WKT record, else its GeoTIFF keys' EPSG code."""
    import laspy
    from laspy.vlrs.known import GeoKeyDirectoryVlr, WktCoordinateSystemVlr
    from rasterio.crs import CRS

    las = laspy.read(path)
    crs = None
    for vlr in las.header.vlrs:
        if isinstance(vlr, WktCoordinateSystemVlr):
            crs = CRS.from_wkt(vlr.string)
        elif isinstance(vlr, GeoKeyDirectoryVlr) and crs is None:
            codes = {k.id: k.value_offset for k in vlr.geo_keys if k.tiff_tag_location == 0}
            code = codes.get(3072, codes.get(2048))  # ProjectedCSTypeGeoKey, GeographicTypeGeoKey
            crs = CRS.from_epsg(code) if code and code != 32767 else None  # 32767: user-defined
    return np.column_stack([las.x, las.y, las.z]).astype(np.float64), crs


def _read_csv(path: Path) -> np.ndarray:
    with open(path) as f:
        head = [h.strip().lower() for h in f.readline().split(",")]
    if not {"x", "y", "z"} <= set(head):
        raise DatasetError(f"{path}: a CSV of points needs a header naming x, y and z columns (comma "
                           f"separated), got {','.join(head)!r}")
    return np.loadtxt(path, delimiter=",", skiprows=1, usecols=[head.index(c) for c in "xyz"], ndmin=2,
                      dtype=np.float64)


def read_ply_points(path: Path) -> np.ndarray:
    """[P, 3] float64 x, y, z of a PLY's `vertex` element (ascii or binary, scalar properties of any type; the
    first element: a mesh's faces may follow). Trained Gaussians: `ragsplat.ply.load_ply`."""
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise DatasetError(f"{path}: not a PLY file")
        fmt, elements, props = None, [], []
        while (line := f.readline()) and line.strip() != b"end_header":
            words = line.decode("ascii", "replace").split()
            if words[:1] == ["format"]:
                fmt = words[1]
            elif words[:1] == ["element"]:
                elements.append((words[1], int(words[2])))
            elif words[:1] == ["property"] and len(elements) == 1:
                props.append((words[-1], words[1]))
        names = [p for p, _ in props]
        if not elements or elements[0][0] != "vertex" or not {"x", "y", "z"} <= set(names) \
                or any(t not in PLY_TYPES for _, t in props) or fmt not in ("ascii", *PLY_BINARY):
            raise DatasetError(f"{path}: a PLY of points needs a first element 'vertex' with scalar x, y, z "
                               "properties (ascii or binary)")
        count = elements[0][1]
        if fmt == "ascii":
            rows = np.loadtxt(f, max_rows=count, ndmin=2, dtype=np.float64)
            return rows[:, [names.index(c) for c in "xyz"]]
        dtype = np.dtype([(p, PLY_BINARY[fmt] + PLY_TYPES[t]) for p, t in props])
        rows = np.frombuffer(f.read(count * dtype.itemsize), dtype=dtype)
    if len(rows) != count:
        raise DatasetError(f"{path}: truncated ({len(rows)} of {count} vertices)")
    return np.column_stack([rows[c] for c in "xyz"]).astype(np.float64)


def band_named(path: Path, name: str) -> int | None:
    """The first band (1-based) of a GeoTIFF whose description is `name`, None for none."""
    import rasterio

    try:
        with rasterio.open(path) as tif:
            return next((k for k, d in enumerate(tif.descriptions, 1) if d == name), None)
    except rasterio.errors.RasterioIOError as err:
        raise DatasetError(f"{path}: not a readable GeoTIFF ({err})") from None


def read_dem(path: Path, band: int) -> tuple[np.ndarray, object, object]:
    """(values [H, W] float64, NaN where not covered; its affine transform; its CRS or None) of a GeoTIFF's
    `band` (1-based)."""
    import rasterio

    try:
        with rasterio.open(path) as tif:
            if not 1 <= band <= tif.count:
                raise ConfigError(f"{path}: no band {band} (it has {tif.count})")
            return tif.read(band, masked=True).astype(np.float64).filled(np.nan), tif.transform, tif.crs
    except rasterio.errors.RasterioIOError as err:
        raise DatasetError(f"{path}: not a readable GeoTIFF ({err})") from None


def dem_at(values: np.ndarray, transform, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(heights [N], read [N] bool) of the raster `values` [H, W] (NaN: uncovered) at points xy [N, 2] in its
    coordinates: a point on a cell centre (to `SNAP` of a cell) takes that cell's value, any other bilinear
    between the four cell centres around it; where one of those four is uncovered or outside, the value of the
    cell the point lies in (a raster cell stands for its square: a bed's edge keeps its cells on another
    lattice); not read where that cell is uncovered or outside too."""
    col, row = ~transform @ (xy[:, 0], xy[:, 1])
    at = np.column_stack([col, row]) - 0.5  # [N, 2] in cells from the first cell's centre
    at = np.where(np.abs(at - np.round(at)) < SNAP, np.round(at), at)
    first = np.floor(at).astype(np.int64)
    frac = at - first
    z, read = np.zeros(len(xy)), np.ones(len(xy), dtype=bool)
    for dc, dr in ((0, 0), (1, 0), (0, 1), (1, 1)):
        weight = np.abs(1 - dc - frac[:, 0]) * np.abs(1 - dr - frac[:, 1])
        c, r = first[:, 0] + dc, first[:, 1] + dr
        inside = (c >= 0) & (c < values.shape[1]) & (r >= 0) & (r < values.shape[0])
        v = np.full(len(xy), np.nan)
        v[inside] = values[r[inside], c[inside]]
        used = weight > 0
        read &= ~used | np.isfinite(v)
        z += np.where(used, weight * np.nan_to_num(v), 0.0)
    c, r = np.floor(at + 0.5).astype(np.int64).T  # the cell the point lies in
    inside = (c >= 0) & (c < values.shape[1]) & (r >= 0) & (r < values.shape[0])
    own = np.full(len(xy), np.nan)
    own[inside] = values[r[inside], c[inside]]
    z = np.where(read, z, np.nan_to_num(own))
    return z, read | np.isfinite(own)


def points_grid(xyz: np.ndarray, nodes: np.ndarray, despike: bool) -> tuple[np.ndarray, int]:
    """([G', 3] heights at the `nodes` [G, 2+] under the points [P, 3] (local frame), how many points were
    near enough to be read): as the references' tracks (`references.gridded`, filtered when `despike`)."""
    from scipy.spatial import QhullError

    lo, hi = nodes[:, :2].min(0) - TIN_FILTER["radius"], nodes[:, :2].max(0) + TIN_FILTER["radius"]
    near = xyz[((xyz[:, :2] >= lo) & (xyz[:, :2] <= hi)).all(1)]
    try:
        grid = gridded(near, nodes, TIN_FILTER if despike else None)
    except (QhullError, ValueError):  # fewer than 3 points, or all on one line
        grid = np.zeros((0, 3))
    return grid, len(near)


def read_bed(path: Path, truth, georef, band: int = 1, depth: bool = False, despike: bool = True,
             crs: str | None = None, geotags=None) -> tuple[np.ndarray, dict]:
    """([G', 3] the file's bed heights at the ground truth's nodes in the dataset's local frame, a record of
    what was read) for `truth` (`dataset.load.GroundTruth`) of a dataset with `georef` (`layout.Georef`).
    `band`: a DEM's; `depth`: its values (a DEM's band, the points' z) are water depths; `despike`: points
    through the outlier filter; `crs`: the file's CRS where it names none or a wrong one; `geotags`: the frame
    a synthetic survey's photos were geotagged in (`survey_geotags`), a candidate for a file in a CRS (a
    survey run from the photos' EXIF writes its products there). Raises ConfigError (unknown kind, no such
    band, unusable `crs`), DatasetError (unreadable, or not over the ground truth: fewer than `MIN_COVER` of
    its wet nodes covered)."""
    grid, record, _ = _read_bed(path, truth, georef, band, depth, despike, crs, geotags)
    return grid, record


def _read_bed(path: Path, truth, georef, band: int = 1, depth: bool = False, despike: bool = True,
              crs: str | None = None, geotags=None) -> tuple[np.ndarray, dict, Frame]:
    """`read_bed`, and the `Frame` the file was read in."""
    from rasterio.crs import CRS
    from rasterio.errors import CRSError
    from scipy.spatial import cKDTree

    path = Path(path)
    kind = KINDS.get(path.suffix.lower())
    if kind is None:
        raise ConfigError(f"{path}: unknown bed file kind {path.suffix!r}; expected {', '.join(KINDS)}")
    if not path.is_file():
        raise DatasetError(f"{path}: no such file")
    if kind == "DEM":
        values, transform, file_crs = read_dem(path, band)
        count = int(np.isfinite(values).sum())
        corners = np.array([transform @ (0, 0), transform @ values.shape[::-1]])
    else:
        xyz, file_crs = read_points(path, kind)
        count, corners = len(xyz), xyz[:, :2]
    if not count:
        raise DatasetError(f"{path}: no {f'covered cells in band {band}' if kind == 'DEM' else 'points'}")
    try:
        file_crs = file_crs if crs is None else CRS.from_user_input(crs)
    except CRSError as err:
        raise ConfigError(f"--crs {crs!r} is not usable: {err}") from None
    nodes, wet = truth.nodes, cKDTree(truth.grid[:, :2])
    best = None
    candidates = frames(file_crs, georef)
    if geotags is not None and geodetic(file_crs):
        candidates += [replace(f, label=f"{f.label.replace('dataset', 'survey geotags')} (survey.json's geo)")
                       for f in frames(file_crs, geotags)]
    for frame in candidates:
        if kind == "DEM":
            z, read = dem_at(values, transform, frame.to_file(nodes[:, :2]))
            grid, near = np.column_stack([nodes[read, :2], z[read]]), count
        else:
            grid, near = points_grid(np.column_stack([frame.to_local(xyz[:, :2]), xyz[:, 2]]), nodes, despike)
        on_wet = wet.query(grid[:, :2], distance_upper_bound=1e-6)[0] if len(grid) else np.zeros(0)
        landed = int(np.isfinite(on_wet).sum())
        if best is None or landed > best[2]:
            best = frame, grid, landed, near
    frame, grid, landed, near = best
    if landed < max(1, MIN_COVER * len(truth.grid)):
        (x0, y0), (x1, y1) = corners.min(0), corners.max(0)
        lo, hi = nodes[:, :2].min(0) + georef.offset[:2], nodes[:, :2].max(0) + georef.offset[:2]
        raise DatasetError(
            f"{path}: its bed covers {landed} of the ground truth's {len(truth.grid)} wet cells (fewer than "
            f"{MIN_COVER:.0%}): another place or frame? It spans x {x0:.2f}..{x1:.2f}, y {y0:.2f}..{y1:.2f} "
            f"({_label(file_crs)}), the truth x {lo[0]:.2f}..{hi[0]:.2f}, y {lo[1]:.2f}..{hi[1]:.2f} "
            f"({_label(CRS.from_user_input(georef.crs))})")
    grid[:, 2] = _heights(grid, truth, frame, depth)
    if kind == "DEM":
        how = {"band": band, "cells": count,
               "gridding": "bilinear between cell centres, else the cell a node lies in"}
    else:
        how = {"points": count, "points_near": near, "gridding": "TIN",
               "filter": TIN_FILTER if despike else None}
    return grid, {"file": str(path), "kind": kind, "crs": crs_name(file_crs),
                  "values": "depth" if depth else "elevation", "frame": frame.label, **how,
                  "nodes_covered": len(grid), "wet_nodes_covered": landed,
                  "wet_nodes": len(truth.grid)}, frame


def _heights(grid: np.ndarray, truth, frame: Frame, depth: bool) -> np.ndarray:
    """[G'] bed heights in the dataset's local frame of the values grid [G', 3] holds (`depth`: depths)."""
    return truth.water.height(grid[:, :2]) - grid[:, 2] if depth else grid[:, 2] - frame.offset[2]


def survey_points(path: Path, depth: bool) -> dict[str, np.ndarray]:
    """{row name: [P, 3] points} of the survey run whose product `path` is (RUN/model/ beside RUN/survey.json
    and RUN/water.json) in the run's frame, z as the file's values are (`depth`: below the row's water
    surface): `SURVEY_TRACKS`, the model adjusted through the water, each submerged point where refraction
    puts it, below the run's surface; `SURVEY_PINHOLE`, the field's practice without ragsplat, the structure
    from motion's pinhole model (RUN/sfm/model) put in the frame by the same georeferencing (RUN/georef.json)
    and each point's depth below the water times n, the water at the pinhole model's own shore
    (`shore_offset`: a pinhole model of wet photos is bent, its dry land not where the adjusted model's is,
    and a surveyor measures the level in the model the depths come from). Empty for a file no survey run
    wrote."""
    import dataclasses
    import json

    from ragsplat.dataset.colmap import read_model
    from ragsplat.survey.georef import Similarity
    from ragsplat.water_surface import WaterSurface

    run = Path(path).parent
    if not ((run / "survey.json").is_file() and (run / "water.json").is_file() and (run / "model").is_dir()):
        return {}
    surface = WaterSurface(**json.loads((run / "water.json").read_text())["surface"])
    model = read_model(run / "model").points3D
    tracks = {pid: np.asarray(p.xyz, dtype=np.float64) for pid, p in model.items()}
    rows = {SURVEY_TRACKS: (np.array(list(tracks.values())).reshape(-1, 3), surface)}
    if (run / "georef.json").is_file() and (run / "sfm" / "model").is_dir():
        sim = json.loads((run / "georef.json").read_text())
        sim = Similarity(sim["scale"], np.array(sim["R"]), np.array(sim["t"]))
        pinhole = read_model(run / "sfm" / "model").points3D
        ids = sorted(pinhole)
        xyz = sim.apply(np.array([pinhole[i].xyz for i in ids], dtype=np.float64).reshape(-1, 3))
        shared = np.array([i in tracks for i in ids], dtype=bool)
        same = np.array([tracks[i] for i in np.asarray(ids)[shared]]).reshape(-1, 3)
        offset = shore_offset(xyz[shared], same, surface)
        own = dataclasses.replace(surface, level=float(surface.level) + offset)
        rows[SURVEY_PINHOLE] = (depth_times_n(xyz, own), own)
    out = {}
    for name, (xyz, water) in rows.items():
        if depth:
            xyz[:, 2] = water.height(xyz[:, :2]) - xyz[:, 2]
        out[name] = xyz
    return out


SHORE_BAND = 0.5  # metres above the water: the shore a level is read off, dry but not yet the banks' slope


def shore_offset(pinhole: np.ndarray, adjusted: np.ndarray, surface) -> float:
    """The height (m) of the water's edge in a pinhole model less in the model adjusted through the water: the
    median height difference of the same points [P, 3] in each (`pinhole`, `adjusted`: row by row) that lie
    dry within `SHORE_BAND` above `surface` in the adjusted one; 0 where there are none."""
    above = adjusted[:, 2] - surface.height(adjusted[:, :2])
    shore = (above > 0) & (above < SHORE_BAND)
    return float(np.median(pinhole[shore, 2] - adjusted[shore, 2])) if shore.any() else 0.0


def tvu_band(path: Path, frame: Frame, truth, band: int, heights: int = 1, depth: bool = False) -> dict:
    """The DEM `path`'s TVU95 band `band` checked at its own cells (module docstring): each cell with a
    height (band `heights`; `depth`: water depths) and a TVU95, its centre brought into the dataset's frame
    by `frame`, inside the truth's region and over the true bed where that is submerged, its error against
    `truth` (`evaluate.height_error`), summarised by `calibration.tvu_band_summary`."""
    from ragsplat.eval.calibration import tvu_band_summary
    from ragsplat.eval.evaluate import height_error
    from ragsplat.surface import in_region

    tvu, transform, _ = read_dem(path, band)
    z = read_dem(path, heights)[0]
    rows, cols = np.nonzero(np.isfinite(tvu) & np.isfinite(z))
    xy = frame.to_local(np.column_stack(transform * (cols + 0.5, rows + 0.5)))
    cells = np.column_stack([xy, z[rows, cols]])
    cells[:, 2] = _heights(cells, truth, frame, depth)
    inside = in_region(xy, truth.region, tol=1e-6)  # a centre computed a rounding error past an edge
    dz, true_depth = height_error(cells[inside], truth)
    wet = true_depth > 0
    return {"band": band, "checked_at": "the DEM's own cells",
            **tvu_band_summary(tvu[rows, cols][inside][wet], dz[wet], true_depth[wet])}


def score_file(path: Path, data: Path, references: bool = False,
               log: Callable[[str], None] = lambda line: None, tvu: int | None = None,
               **read) -> tuple[dict, np.ndarray, object, dict]:
    """The bed of the file `path` (`read_bed` with `read`) scored against the ground truth of the dataset
    `data` by `ragsplat.eval.evaluate.score_grid`, beside the reference rows that need no training: the oracle
    planes (`references.oracle_grids`), for a survey run's product the run's own tracks and its
    pinhole model's depths x n as TINs (`survey_points`) and, with `references`, the dataset's tracks' grids
    (`TrainEval.track_grids`: it triangulates a dataset without a cached triangulation, minutes). A DEM's
    TVU95 band (`tvu`, else the band described `export.TVU_BAND` where it has one) is scored too, under
    "uncertainty" (`tvu_band`). Returns (the result, the bed grid [G', 3], the ground truth, the reference
    rows' grids by name, each as the bed's). Raises as
    `read_bed`, and ConfigError for `tvu` of a file that is no DEM or the band of the heights themselves."""
    from ragsplat.dataset import layout
    from ragsplat.dataset.load import load_dataset
    from ragsplat.eval.ablation import dataset_seed
    from ragsplat.eval.evaluate import score_grid
    from ragsplat.export import TVU_BAND

    dem = KINDS.get(Path(path).suffix.lower()) == "DEM"
    if tvu is not None and not dem:
        raise ConfigError(f"{path}: a TVU95 band (--tvu-band) is a DEM GeoTIFF's; this file is no DEM")
    if tvu is not None and tvu == read.get("band", 1):
        raise ConfigError(f"band {tvu} is the heights' band: the TVU95 band is another")
    ds = load_dataset(data, splits=(), ground_truth=True)
    truth = ds.ground_truth
    grid, record, frame = _read_bed(path, truth, ds.georef, geotags=survey_geotags(data), **read)
    if tvu is None and dem:
        tvu = band_named(path, TVU_BAND)
        tvu = None if tvu == read.get("band", 1) else tvu  # scoring the band itself (--band K)
    rows = oracle_grids(truth)
    for name, points in survey_points(path, read.get("depth", False)).items():
        near = np.column_stack([frame.to_local(points[:, :2]), points[:, 2]])
        grid_points = points_grid(near, truth.nodes, despike=True)[0]
        grid_points[:, 2] = _heights(grid_points, truth, frame, read.get("depth", False))
        rows[name] = grid_points
    if references:
        from ragsplat.eval.ablation import TrainEval

        rows.update(TrainEval(data, held_out=False).track_grids(log))
    return {**record, "data": str(Path(data).resolve()), "dataset_fingerprint": ds.fingerprint,
            "dataset_seed": dataset_seed(data),
            "georef": ds.georef.to_json(), "max_depth_m": truth.max_depth,
            "water": layout.water_json(truth.water), "geometry": score_grid(grid, truth),
            "references": {name: score_grid(g, truth) for name, g in rows.items()},
            "uses_ground_truth": list(USES_GROUND_TRUTH),
            **({} if tvu is None else {"uncertainty": tvu_band(path, frame, truth, tvu, read.get("band", 1),
                                                               read.get("depth", False))})}, grid, truth, rows

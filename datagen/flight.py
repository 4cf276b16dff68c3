"""UAV flight plan: a pure function of the scene spec.

Training views: a nadir grid whose spacing gives the spec's forward/side overlap of the footprints ON THE BED,
plus obliques at each tilt and the spec's azimuth step, each aimed so that its refracted optical axis hits
the mean bed plane below its aim point: the scene centre (`rings`, one per tilt), or each of the `stations`
along the reach's axis (`strips`: a long reach, where rings about its centre would miss its ends), or taken
from the nadir grid's points (`mapping`: the lawnmower a planning app flies, its rows the flight lines, flown
back and forth with the image's top ahead).
Held-out test views: nadirs between grid points, and obliques at azimuths offset from the training ones
(strips and mapping: one per tilt at each midpoint, the azimuth turning from one to the next).

Refraction shrinks the footprint on the bed (`ragsplat.snell.ground_offset`): the half-footprint is
h tan(a) + d tan(asin(sin(a) / n)) instead of the dry (h + d) tan(a). Using the dry footprint would overstate
the overlap.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ragsplat.camera import Camera
from ragsplat.datagen.spec import SceneSpec
from ragsplat.errors import SpecError
from ragsplat.snell import ground_offset


@dataclass(frozen=True)
class Pose:
    name: str  # "0000": also the image file stem
    kind: str  # "nadir" | "oblique20" | "oblique40" ...
    split: str  # "train" | "test"
    camera: Camera


def _half_angles(spec: SceneSpec) -> tuple[float, float]:
    """Half the field of view (radians) of a nadir along world x and y: a mapping flight's image has its
    width across the flight line (y) and its height along it (x); the other patterns' are north-up."""
    f = spec.flight
    across = math.radians(f.fov_deg / 2)
    along = math.atan(math.tan(across) * f.image_height / f.width)
    return (along, across) if f.pattern == "mapping" else (across, along)


def footprint(spec: SceneSpec) -> tuple[float, float]:
    """Sides (m) along world x and y of a nadir view's footprint on the mean bed plane, through its centre."""
    f = spec.flight
    ax, ay = _half_angles(spec)
    return (2 * ground_offset(ax, f.altitude, spec.bed.depth, spec.n),
            2 * ground_offset(ay, f.altitude, spec.bed.depth, spec.n))


def spacing(spec: SceneSpec) -> tuple[float, float]:
    """Distances (m) along x and y between neighbouring nadir views for the spec's overlaps: `overlap` along
    each row, `side` between the rows."""
    fx, fy = footprint(spec)
    return (1.0 - spec.flight.overlap) * fx, (1.0 - spec.flight.side) * fy


def gsd(spec: SceneSpec) -> float:
    """Ground sample distance (m/px) on the mean bed at the centre of a nadir image.

    d(ground offset)/d(tan a) at a = 0 is h + d / n: the bed looks d / n deep (paraxial apparent depth).
    """
    f = spec.flight
    fx = Camera.intrinsics_from_fov(f.width, f.image_height, f.fov_deg)[0]
    return (f.altitude + spec.bed.depth / spec.n) / fx


def nadir_positions(spec: SceneSpec, between: bool = False) -> np.ndarray:
    """Horizontal camera positions [K, 2] of the nadir grid (or of the midpoints between its points), row by
    row from -y; a mapping flight's rows alternate in direction (the lawnmower's order)."""
    rows, cols = spec.flight.grid
    if between:
        rows, cols = rows - 1, cols - 1
    sx, sy = spacing(spec)
    xs = (np.arange(cols) - (cols - 1) / 2) * sx
    ys = (np.arange(rows) - (rows - 1) / 2) * sy
    gx, gy = np.meshgrid(xs, ys)  # [rows, cols]
    if spec.flight.pattern == "mapping":
        gx[1::2] = gx[1::2, ::-1]
    return np.stack([gx.ravel(), gy.ravel()], -1)


def eval_region(spec: SceneSpec) -> dict[str, float]:
    """The region evaluated for geometry. Gravel bed (the paper's setup): the nadir grid's cells, where
    every point is seen by most nadirs. Reach or shore: everything the nadir strips see of the water plane,
    the union of their footprints at the water line (the narrowest, so every point of it is in view)."""
    rows, cols = spec.flight.grid
    sx, sy = spacing(spec)
    if spec.reach is None:
        return {"xmin": -cols * sx / 2, "xmax": cols * sx / 2, "ymin": -rows * sy / 2, "ymax": rows * sy / 2}
    ax, ay = _half_angles(spec)
    h = spec.flight.altitude
    xs, ys = (cols - 1) * sx / 2 + h * math.tan(ax), (rows - 1) * sy / 2 + h * math.tan(ay)
    return {"xmin": -xs, "xmax": xs, "ymin": -ys, "ymax": ys}


def check_region(spec: SceneSpec) -> None:
    """Raises SpecError where the evaluated region (`eval_region`) reaches the bed's tapered border: a check
    of the flight against the bed, here with the plan rather than in `spec.validate` (the spec imports
    nothing of the flight plan that reads it)."""
    r, inner = eval_region(spec), spec.bed.size / 2 - spec.bed.taper
    if max(-r["xmin"], r["xmax"], -r["ymin"], r["ymax"]) >= inner:
        raise SpecError(f"the evaluated region (x {r['xmin']:.2f} to {r['xmax']:.2f} m, y {r['ymin']:.2f} to "
                        f"{r['ymax']:.2f} m) reaches the {spec.bed.size} m bed's {spec.bed.taper} m border: "
                        "enlarge bed.size or fly fewer nadirs")


def nadir_views_covering(spec: SceneSpec, xy) -> np.ndarray:
    """How many training nadirs see each bed point [N, 2] on the mean plane (rectangular footprints)."""
    half = np.array(footprint(spec)) / 2
    d = np.abs(np.asarray(xy, float)[:, None, :] - nadir_positions(spec)[None])  # [N, K, 2]
    return np.all(d <= half, axis=-1).sum(-1)


def _camera(spec: SceneSpec, eye, target, up) -> Camera:
    f = spec.flight
    return Camera.look_at(eye, target, f.width, f.image_height, f.fov_deg, up=up)


def _nadir(spec: SceneSpec, xy, heading=(0.0, 1.0)) -> Camera:
    """A nadir at horizontal `xy`, its image's top towards `heading` (north-up by default)."""
    z = spec.level + spec.flight.altitude
    return _camera(spec, [xy[0], xy[1], z], [xy[0], xy[1], z - 1.0], (heading[0], heading[1], 0.0))


def _nadirs(spec: SceneSpec, between: bool = False) -> list[Camera]:
    """The nadir grid's cameras in `nadir_positions`' order; a mapping flight's heading is the drone's, +x
    on the rows flown from -x and -x on the others (a held-out one between two rows: the first's)."""
    xy = nadir_positions(spec, between)
    if spec.flight.pattern != "mapping":
        return [_nadir(spec, p) for p in xy]
    cols = spec.flight.grid[1] - int(between)
    return [_nadir(spec, p, (1.0 if (k // cols) % 2 == 0 else -1.0, 0.0)) for k, p in enumerate(xy)]


def stations(spec: SceneSpec, between: bool = False) -> np.ndarray:
    """Horizontal aim points [S, 2] of the `strips` obliques on the reach's axis y = 0, evenly from the
    first nadir column to the last (or the midpoints between them: the held-out obliques')."""
    half = (spec.flight.grid[1] - 1) * spacing(spec)[0] / 2
    xs = np.linspace(-half, half, spec.flight.stations)
    if between:
        xs = (xs[:-1] + xs[1:]) / 2
    return np.column_stack([xs, np.zeros_like(xs)])


def _oblique(spec: SceneSpec, tilt_deg: float, azimuth_deg: float, aim=(0.0, 0.0)) -> Camera:
    """Camera at the flight altitude, `tilt_deg` from the vertical and `azimuth_deg` from the horizontal
    point `aim`, whose refracted optical axis hits the mean bed plane below `aim` (`bed.depth` under the
    water surface there)."""
    top = spec.level + spec.flight.altitude  # the drone holds its altitude over a sloping surface
    surface = spec.level if spec.water is None else float(spec.water.height(np.asarray(aim)))
    h = top - surface
    tilt, az = math.radians(tilt_deg), math.radians(azimuth_deg)
    radius = ground_offset(tilt, h, spec.bed.depth, spec.n)
    direction = np.array([math.cos(az), math.sin(az)])
    eye = [*(aim + radius * direction), top]
    # Aim at the point where the axis enters the water: h tan(tilt) from the camera, towards `aim`.
    target = [*(aim + (radius - h * math.tan(tilt)) * direction), surface]
    return _camera(spec, eye, target, (0.0, 0.0, 1.0))


def _oblique_from(spec: SceneSpec, tilt_deg: float, azimuth_deg: float, xy) -> Camera:
    """The oblique `_oblique` takes from above horizontal `xy` looking towards `azimuth_deg`: aimed at the
    bed point its refracted axis reaches there (under a sloping surface the camera lands within the
    surface's rise over that distance of `xy`)."""
    top = spec.level + spec.flight.altitude
    surface = spec.level if spec.water is None else float(spec.water.height(np.asarray(xy)))
    az = math.radians(azimuth_deg)
    radius = ground_offset(math.radians(tilt_deg), top - surface, spec.bed.depth, spec.n)
    aim = np.asarray(xy, float) + radius * np.array([math.cos(az), math.sin(az)])
    return _oblique(spec, tilt_deg, azimuth_deg + 180.0, aim)


def _azimuths(step: float, offset: float) -> list[float]:
    return [offset + k * step for k in range(math.floor(360.0 / step + 1e-9))]


def _obliques(spec: SceneSpec, split: str) -> list[tuple[str, str, Camera]]:
    """The obliques of `split` by tilt: (kind, split, camera)."""
    f = spec.flight
    train = split == "train"
    if f.pattern == "mapping":  # from the grid's points to every azimuth; held out: the midpoints, one each
        if train:
            shots = [(xy, az) for xy in nadir_positions(spec) for az in _azimuths(f.azimuth_step, 0.0)]
        else:
            held = _azimuths(f.test_azimuth_step, f.test_azimuth_offset)
            shots = [(xy, held[k % len(held)]) for k, xy in enumerate(nadir_positions(spec, between=True))]
        return [(f"oblique{tilt:g}", split, _oblique_from(spec, tilt, az, xy))
                for tilt in f.tilts for xy, az in shots]
    if f.pattern == "rings":
        step, offset = (f.azimuth_step, 0.0) if train else (f.test_azimuth_step, f.test_azimuth_offset)
        aims = [((0.0, 0.0), az) for az in _azimuths(step, offset)]
    elif train:  # every azimuth at every station
        aims = [(xy, az) for xy in stations(spec) for az in _azimuths(f.azimuth_step, 0.0)]
    else:  # one azimuth at each midpoint, the next one's at the next: every held-out azimuth along the reach
        held = _azimuths(f.test_azimuth_step, f.test_azimuth_offset)
        aims = [(xy, held[k % len(held)]) for k, xy in enumerate(stations(spec, between=True))]
    return [(f"oblique{tilt:g}", split, _oblique(spec, tilt, az, xy)) for tilt in f.tilts for xy, az in aims]


def plan(spec: SceneSpec) -> list[Pose]:
    """All poses, training first: nadir grid, obliques by tilt; then test nadirs and test obliques. Raises
    SpecError (`check_region`) for a flight whose evaluated region reaches the bed's border."""
    check_region(spec)
    views = [("nadir", "train", cam) for cam in _nadirs(spec)] + _obliques(spec, "train")
    views += [("nadir", "test", cam) for cam in _nadirs(spec, between=True)]
    views += _obliques(spec, "test")
    return [Pose(f"{i:04d}", kind, split, cam) for i, (kind, split, cam) in enumerate(views)]

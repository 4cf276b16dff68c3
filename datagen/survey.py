"""The survey a surveyor hands over, made from a rendered dataset: the training photos as JPEGs with their
focal length in EXIF (`survey/images/`), the camera centres as an RTK drone records them, with seeded noise
(`survey/positions.csv`, and the same positions in the photos' EXIF GPS and DJI-style XMP, RtkFlag 50, through
a geographic origin of the scene, `GeoOrigin`; the same photos again in `survey/images-gps/` with a consumer
drone's GPS instead: a bias per flight line and scatter, metres, no RTK flag; and in `survey/images-lens/`
the photos the renderer took through a lens with radial distortion, `LENS`), the water level as measured at
the edge, with noise (`survey/water_level.txt`), points on the water's edge along each bank as a surveyor
measures them with RTK (`survey/water_edge.csv`, header x,y,z, with noise on z) and ground control on the
banks with the targets' pixels (`survey/gcp.csv`, `survey/gcp_pixels.csv`). On a sloping surface
water_level.txt holds one level at the mean of the edge points' heights: what a tool that takes one flat water
level would be given. No poses: recovering them is `ragsplat survey`'s job; the dataset's transforms.json
stays the truth that scores it. numpy only (JPEG through Pillow, geodesy through pyproj).

The scene's frame is a UTM grid's, shifted: x, y, z = easting - E0, northing - N0, height - h0, where
(E0, N0) is `GeoOrigin`'s position in its UTM zone and h0 its height (WGS 84 ellipsoidal), all recorded in
survey.json ("geo"); scene.json, transforms.json and gt/ do not change."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ragsplat.dataset import layout, photos
from ragsplat.outputs import write_bytes, write_json

EDGE_POINTS = 15  # edge points measured along each bank
EDGE_SPACING = 2.0  # ... or one every this many metres of the evaluated reach's length where that is more (m)
_EDGE_STREAM = 4  # the edge points' noise: a random stream apart from the survey's and the conditions' (1-3)
_GPS_STREAM = 5  # consumer GPS: each flight line's bias and each photo's scatter
_ANGLE_STREAM = 6  # the gimbal angles' noise
_BAROMETER_STREAM = 7  # consumer photos' barometric heights: the flight's drift and each photo's scatter
# the drone takes off from the bank this far above the water (RelativeAltitude's zero)
TAKEOFF_ABOVE_WATER = 1.0


@dataclass(frozen=True)
class GeoOrigin:
    """Where the synthetic scene's origin is on Earth: the Soca near Kobarid, Slovenia, a clear gravel-bed
    river (the UTM zone 33N, 1.4 degrees west of its central meridian)."""

    lat: float = 46.2470  # degrees north
    lon: float = 13.5830  # degrees east
    height: float = 247.0  # WGS 84 ellipsoidal height of the scene's z = 0 (m): about 200 m above sea level


@dataclass(frozen=True)
class ConsumerGPS:
    """A consumer drone's GPS (metres, no RTK): what `survey/images-gps/` carries."""

    # each flight line's horizontal offset: its length, uniform (m)
    line_bias: tuple[float, float] = (1.0, 1.5)
    line_bias_z: float = 0.5  # each flight line's vertical offset, standard deviation (m)
    jitter: float = 0.5  # each photo's own scatter about its line's offset, each axis (m)
    # the barometer's RelativeAltitude (above the take-off point): a drift growing linearly from the first
    # photo to the last, its end's standard deviation, and each photo's own scatter (m); independent of the
    # GPS's errors
    barometer_drift: float = 0.2
    barometer_jitter: float = 0.03


GIMBAL_NOISE_DEG = (2.0, 0.5, 0.5)  # the recorded gimbal yaw (a compass), pitch and roll, standard deviation


@dataclass(frozen=True)
class SurveyNoise:
    """Standard deviations (metres) of what the field instruments add."""

    horizontal: float = 0.02  # RTK camera centre, x and y
    vertical: float = 0.03  # RTK camera centre, z
    level: float = 0.01  # the water level measured at the edge (each edge point's height too)
    gcp: float = 0.01  # a ground control point's surveyed position, each axis
    gcp_pixel: float = 0.3  # where a target's centre is picked in a photo (pixels, each axis)
    gcp_count: int = 6  # targets on the banks


def write_survey(root: Path, poses, water, seed: int = 0, noise: SurveyNoise = SurveyNoise(),
                 banks: np.ndarray | None = None, targets: np.ndarray | None = None,
                 waterline: list[np.ndarray] | None = None, region: dict | None = None,
                 origin: GeoOrigin = GeoOrigin(), gps: ConsumerGPS = ConsumerGPS()) -> bool:
    """Writes ROOT/survey/ from the dataset ROOT's wet training views `poses` (`flight.plan`: name, camera,
    split) and the true water surface `water` (`WaterSpec`: level, slope; see the module docstring); with
    the banks' ground truth points `banks` [B, 3], also ground control: `noise.gcp_count` points on the
    banks spread apart (`gcp.csv`, with `noise.gcp`) and their pixels in every training photo that holds
    them (`gcp_pixels.csv`, with `noise.gcp_pixel`), as a surveyor who picked the targets' centres would
    give them; where the scene has checkerboard `targets` [T, 3] rendered (field conditions), those are the
    ground control. With the `waterline` polylines [K, >= 2] (a reach), also the edge points
    (`edge_points`, `edge_count` a bank along the evaluated `region`'s x-range). The photos are geotagged
    through `origin`, those of images-gps/ with the consumer GPS `gps` (`write_geotags`). Returns False when
    a survey made with the same seed and noise is already there (nothing written but what older surveys
    lack: water_edge.csv, the photos' geotags and images-gps/, `write_geotags`)."""
    root = Path(root)
    record = {"seed": seed, "noise": asdict(noise), "views": "the training views, wet"}
    path = root / layout.SURVEY_RECORD
    edge = None
    if waterline is not None:
        xmin, xmax = (region["xmin"], region["xmax"]) if region else (-np.inf, np.inf)
        xy = edge_points(waterline, xmin, xmax, edge_count(xmax - xmin) if region else EDGE_POINTS)
        edge = np.column_stack([xy, water.height(xy)])  # on the surface: the waterline's true heights
    train = [p for p in poses if p.split == "train"]
    names = [f"{p.name}.jpg" for p in train]
    lens = all(layout.output_path(root, "lens", p.name).is_file() for p in train)  # rendered through `LENS`
    old = json.loads(path.read_text()) if path.is_file() else None
    if old is not None and {k: old.get(k) for k in record} == record:
        if edge is not None and not (root / layout.SURVEY_EDGE).is_file():
            _write_edge(root, edge, seed, noise)
        if old.get("geo") != geo_record(train, names, water, seed, noise, origin, gps, lens):  # older photos
            write_json(path, {**old, "geo": write_geotags(root, train, names, water, seed, noise, origin, gps,
                                                          lens)})
        return False
    rng = np.random.default_rng(seed)
    sigma = np.array([noise.horizontal, noise.horizontal, noise.vertical])
    centres = np.array([p.camera.camera_center for p in train])
    layout.write_positions(root / layout.SURVEY_POSITIONS, names,
                           centres + rng.normal(size=centres.shape) * sigma)
    record["geo"] = write_geotags(root, train, names, water, seed, noise, origin, gps, lens)
    level = float(edge[:, 2].mean()) if water.sloping and edge is not None else water.level  # one level
    write_bytes(root / layout.SURVEY_LEVEL, f"{level + rng.normal() * noise.level:.4f}\n".encode())
    if edge is not None:
        _write_edge(root, edge, seed, noise)
    if targets is None and banks is not None:
        dry = banks[banks[:, 2] > water.height(banks[:, :2]) + 0.05]
        targets = spread(dry, noise.gcp_count, rng) if len(dry) >= 3 else None
    if targets is not None:
        gcps = [f"GCP{k + 1}" for k in range(len(targets))]
        layout.write_positions(root / layout.SURVEY_GCP, gcps,
                               targets + rng.normal(size=targets.shape) * noise.gcp)
        rows = []
        for p, name in zip(train, names):
            uv, z = p.camera.project(targets)
            uv = uv + rng.normal(size=uv.shape) * noise.gcp_pixel
            inside = ((z > 0) & (uv >= 2).all(1) & (uv[:, 0] <= p.camera.width - 2)
                      & (uv[:, 1] <= p.camera.height - 2))
            rows += [(name, gcps[k], *uv[k]) for k in np.flatnonzero(inside)]
        layout.write_gcp_pixels(root / layout.SURVEY_GCP_PIXELS, rows)
    write_json(path, record)  # last: its presence marks a finished survey
    return True


def geo_record(train, names: list[str], water, seed: int, noise: SurveyNoise,
               origin: GeoOrigin = GeoOrigin(), gps: ConsumerGPS = ConsumerGPS(), lens: bool = True) -> dict:
    """survey.json's "geo": the origin, its UTM zone and the scene's frame in it, and how the folders of
    geotagged photos were made (each flight line's consumer-GPS bias; with `lens`, the lens photos')."""
    from ragsplat.dataset import exif

    epsg = exif.utm_epsg(origin.lat, origin.lon)
    e0, n0, _ = exif.to_metric(origin.lat, origin.lon, origin.height, f"EPSG:{epsg}")[0]
    lines = flight_lines(train)
    bias = _line_bias(len(set(lines)), seed, gps)
    return {"origin": asdict(origin), "crs": f"EPSG:{epsg}",
            "origin_metric": [float(e0), float(n0), origin.height],
            "frame": "scene x, y, z = easting - E0, northing - N0, height - h0 (the UTM grid; heights WGS 84 "
                     "ellipsoidal, as the photos' GPSAltitude and AbsoluteAltitude hold them)",
            "takeoff_z": water.level + TAKEOFF_ABOVE_WATER, "gimbal_noise_deg": list(GIMBAL_NOISE_DEG),
            layout.SURVEY_IMAGES: {"positions": layout.SURVEY_POSITIONS, "rtk_flag": exif.RTK_FIXED,
                                   "rtk_std_m": [noise.horizontal, noise.horizontal, noise.vertical]},
            layout.SURVEY_IMAGES_GPS: {"noise": asdict(gps), "lines": [
                {"photos": [n for n, k in zip(names, lines) if k == line],
                 "bias_m": bias[line].round(4).tolist()}
                for line in range(len(bias))]},
            **({layout.SURVEY_IMAGES_LENS: {"geotags": layout.SURVEY_IMAGES, "lens": {
                "model": "COLMAP RADIAL / OpenCV k1, k2 (no tangential terms): x_d = x (1 + k1 r^2 + k2 r^4) "
                         "in normalised coordinates, the principal point and the focal length the pinhole "
                         "photos'; rendered through it (Cycles' polynomial lens, `lens_polynomial`)",
                "k1": LENS[0], "k2": LENS[1]}}} if lens else {})}


def write_geotags(root: Path, train, names: list[str], water, seed: int, noise: SurveyNoise,
                  origin: GeoOrigin = GeoOrigin(), gps: ConsumerGPS = ConsumerGPS(),
                  lens: bool = True) -> dict:
    """The training photos (`train`: poses, `names`: their JPEG names) written again into `survey/images/`
    with the positions.csv centres as EXIF GPS and DJI-style XMP (AbsoluteAltitude, RelativeAltitude, gimbal
    and flight angles, RtkFlag 50 with RtkStdLon / RtkStdLat / RtkStdHgt), and into `survey/images-gps/`
    with a consumer drone's GPS instead (the true centres plus a bias per flight line and scatter, `gps`;
    no RTK tags; the RelativeAltitude its barometer's, the true height plus a drift and scatter), and with
    `lens` into `survey/images-lens/`: the photos rendered through a lens with radial distortion (`LENS`;
    the dataset's images/lens/), with the RTK tags. Returns survey.json's "geo" (`geo_record`)."""
    from ragsplat.dataset import exif

    record = geo_record(train, names, water, seed, noise, origin, gps, lens)
    crs, shift = record["crs"], np.array(record["origin_metric"])
    rtk = layout.read_positions(root / layout.SURVEY_POSITIONS)
    rtk = np.array([rtk[n] for n in names])
    lines = flight_lines(train)
    scatter = np.random.default_rng([seed, _GPS_STREAM]).normal(size=(len(train), 3)) * gps.jitter
    consumer = (np.array([p.camera.camera_center for p in train])
                + _line_bias(len(set(lines)), seed, gps)[lines])
    consumer += scatter
    baro = np.random.default_rng([seed, _BAROMETER_STREAM]).normal(size=len(train) + 1)
    barometer = (np.array([p.camera.camera_center[2] for p in train])
                 + baro[0] * gps.barometer_drift * np.linspace(0.0, 1.0, len(train))
                 + baro[1:] * gps.barometer_jitter)  # the consumer photos' heights for RelativeAltitude
    angles = gimbal_angles([p.camera for p in train], shift, crs)
    angles += np.random.default_rng([seed, _ANGLE_STREAM]).normal(size=angles.shape) * GIMBAL_NOISE_DEG
    angles[:, 0] = (angles[:, 0] + 180) % 360 - 180
    angles[:, 1] = np.clip(angles[:, 1], -90, 30)  # a gimbal's range
    rtk_tags = {"RtkFlag": exif.RTK_FIXED, "RtkStdLon": noise.horizontal, "RtkStdLat": noise.horizontal,
                "RtkStdHgt": noise.vertical}
    # (folder, positions, heights for RelativeAltitude, tags)
    folders = [(layout.SURVEY_IMAGES, rtk, rtk[:, 2], rtk_tags),
               (layout.SURVEY_IMAGES_GPS, consumer, barometer, {})]
    for folder, xyz, heights, tags in folders + ([(layout.SURVEY_IMAGES_LENS, rtk, rtk[:, 2], rtk_tags)]
                                                 if lens else []):
        geographic = exif.to_geographic(xyz + shift, crs)
        for p, name, (lat, lon, h), z, (yaw, pitch, roll) in zip(train, names, geographic, heights, angles):
            xmp = {"AbsoluteAltitude": round(h, 3), "RelativeAltitude": round(z - record["takeoff_z"], 3),
                   "GimbalRollDegree": round(roll, 2), "GimbalYawDegree": round(yaw, 2),
                   "GimbalPitchDegree": round(pitch, 2), "FlightRollDegree": 0.0,
                   "FlightYawDegree": round(yaw, 2), "FlightPitchDegree": 0.0, **tags}
            kind = "lens" if folder == layout.SURVEY_IMAGES_LENS else "wet"
            image = layout.read_png(layout.output_path(root, kind, p.name))
            photos.write_jpeg(root / folder / name, image, p.camera.fx, gps=(lat, lon, h), xmp=xmp)
    return record


# survey/images-lens/'s radial distortion: barrel, as a drone's wide lens (about 6 % at the corners of a
# 70-degree view), in normalised coordinates
LENS = (-0.08, 0.02)


def lens_polynomial(camera, k1: float, k2: float, sensor_mm: float = 36.0) -> list[float]:
    """Cycles' FISHEYE_LENS_POLYNOMIAL coefficients [k0, ..., k4] that render `camera` (square pixels, the
    principal point centred) through a lens with radial distortion k1, k2 (COLMAP's RADIAL: a ray at
    undistorted normalised radius r lands at r_d = r (1 + k1 r^2 + k2 r^4) focal lengths from the centre).
    Cycles sends the sensor point r_s millimetres from the centre (`sensor_mm` over the larger side) along the
    ray theta = -(k0 + k1 r_s + ... + k4 r_s^4) from the axis; theta(r_s) = atan(r) with r_d = r_s / (mm per
    pixel) / f, fitted by least squares from the centre to past the corners (k0 = 0: the axis stays the
    axis). The fit's error is under 0.05 px for `LENS` at small's 70-degree view
    (tests/test_survey_exif.py)."""
    mm = sensor_mm / max(camera.width, camera.height)  # millimetres per pixel
    corner = np.hypot(camera.width, camera.height) / 2 * mm * 1.02
    r_s = np.linspace(0.0, corner, 400)
    r_d = r_s / mm / camera.fx
    r = r_d.copy()
    for _ in range(50):  # the undistorted radius: fixed-point iterations, contracting for a gentle lens
        r = r_d / (1 + k1 * r * r + k2 * r**4)
    powers = np.stack([r_s**k for k in range(1, 5)], axis=1)  # [400, 4]
    coeffs = np.linalg.lstsq(powers, np.arctan(r), rcond=None)[0]
    return [0.0, *(-coeffs).tolist()]


def flight_lines(train) -> np.ndarray:
    """[V] the flight line of each training pose: the nadirs by grid row (one y), each oblique ring (or pass
    along the reach, `strips`) one."""
    keys = [(p.kind, round(float(p.camera.camera_center[1]), 2) if p.kind == "nadir" else None)
            for p in train]
    order = list(dict.fromkeys(keys))
    return np.array([order.index(k) for k in keys], dtype=int)


def _line_bias(count: int, seed: int, gps: ConsumerGPS) -> np.ndarray:
    """[count, 3] each flight line's consumer-GPS offset: a horizontal length in gps.line_bias in a random
    direction, a vertical one with gps.line_bias_z (its own random stream, drawn before the scatter)."""
    rng = np.random.default_rng([seed, _GPS_STREAM, 1])
    turn = rng.uniform(0, 2 * np.pi, count)
    length = rng.uniform(*gps.line_bias, count)
    return np.column_stack([length * np.cos(turn), length * np.sin(turn),
                            rng.normal(size=count) * gps.line_bias_z])


def gimbal_angles(cameras, shift: np.ndarray, crs: str) -> np.ndarray:
    """[V, 3] each camera's gimbal yaw, pitch, roll as DJI records them (degrees): yaw the heading of the
    view (the optical axis, or for a nadir the image's top) clockwise from true north, pitch the optical
    axis above the horizon (-90: straight down), roll about the optical axis, positive with the image's
    right side down (0 for a nadir, whose turn about its axis is its yaw). The scene
    frame is the UTM grid shifted by `shift` (its grid north is not true north: the heading is measured on
    the ellipsoid)."""
    from pyproj import Geod

    from ragsplat.dataset import exif

    R = np.array([c.R for c in cameras])  # rows: right, down, forward in the world
    forward, up, right = R[:, 2], -R[:, 1], R[:, 0]
    level = np.linalg.norm(forward[:, :2], axis=1) > 1e-6  # not straight down (or up)
    ahead = np.where(level[:, None], forward[:, :2], up[:, :2])  # a nadir's heading: its image's top
    ahead /= np.linalg.norm(ahead, axis=1, keepdims=True)
    flat = np.cross(forward, [0.0, 0.0, 1.0])  # the image's right at no roll (horizontal)
    flat /= np.maximum(np.linalg.norm(flat, axis=1, keepdims=True), 1e-12)
    lifted = np.cross(flat, forward)  # the image's top at no roll
    roll = np.where(level, np.degrees(np.arctan2(-(right * lifted).sum(1), (right * flat).sum(1))), 0.0)
    centre = np.array([c.camera_center for c in cameras]) + shift
    a = exif.to_geographic(centre, crs)
    b = exif.to_geographic(centre + np.column_stack([10 * ahead, np.zeros(len(ahead))]), crs)
    yaw = Geod(ellps="WGS84").inv(a[:, 1], a[:, 0], b[:, 1], b[:, 0])[0]
    pitch = np.degrees(np.arcsin(np.clip(forward[:, 2], -1, 1)))
    return np.column_stack([yaw, pitch, roll])


def edge_count(length: float) -> int:
    """Edge points measured along each bank of a reach `length` metres long: `EDGE_POINTS` on a short one,
    one every `EDGE_SPACING` metres on a long one."""
    return max(EDGE_POINTS, math.ceil(length / EDGE_SPACING))


def edge_points(lines: list[np.ndarray], xmin: float, xmax: float, count: int = EDGE_POINTS) -> np.ndarray:
    """[B count, 2] points on the water's edge, `count` along each bank: the banks are the (at most two)
    waterline polylines [K, >= 2] that run along x at least half as far as the farthest (a river's two, a
    lake shore's one; the others ring bars and boulders); each is cut to its longest stretch within
    xmin..xmax and the vertices nearest `count` even steps along it are taken (the polylines' vertices lie
    exactly on the waterline, on the mesh's edges)."""
    lines = [np.asarray(line, np.float64)[:, :2] for line in lines]
    if not lines:
        raise ValueError("the waterline has no polyline: no bank")
    longest = max(np.ptp(line[:, 0]) for line in lines)
    banks = [line for line in sorted(lines, key=lambda line: -np.ptp(line[:, 0]))[:2]
             if np.ptp(line[:, 0]) >= longest / 2]
    banks.sort(key=lambda line: line[:, 1].mean())  # the -y bank first
    out = []
    for line in banks:
        inside = np.concatenate([[0], (line[:, 0] >= xmin) & (line[:, 0] <= xmax), [0]]).astype(int)
        starts, ends = np.flatnonzero(np.diff(inside) == 1), np.flatnonzero(np.diff(inside) == -1)
        k = int(np.argmax(ends - starts))
        part = line[starts[k]:ends[k]]
        along = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(part, axis=0), axis=1))])
        steps = (np.arange(count) + 0.5) / count * along[-1]
        out.append(part[np.abs(along[None] - steps[:, None]).argmin(1)])
    return np.concatenate(out)


def _write_edge(root: Path, edge: np.ndarray, seed: int, noise: SurveyNoise) -> None:
    """layout.SURVEY_EDGE from the true edge points [P, 3], with `noise.level` on each height (its own
    random stream)."""
    z = edge[:, 2] + np.random.default_rng([seed, _EDGE_STREAM]).normal(size=len(edge)) * noise.level
    layout.write_points(root / layout.SURVEY_EDGE, np.column_stack([edge[:, :2], z]))


def spread(points: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """[count, 3] of `points` [P, 3] far apart: farthest-point sampling from a random start."""
    chosen = [int(rng.integers(len(points)))]
    far = np.linalg.norm(points[:, :2] - points[chosen[0], :2], axis=1)
    while len(chosen) < min(count, len(points)):
        chosen.append(int(far.argmax()))
        far = np.minimum(far, np.linalg.norm(points[:, :2] - points[chosen[-1], :2], axis=1))
    return points[chosen]

"""Camera positions from the photos' own metadata, as a drone writes them: the EXIF GPS block (GPSLatitude /
GPSLatitudeRef, GPSLongitude / GPSLongitudeRef, GPSAltitude / GPSAltitudeRef) and, where present, DJI's XMP
packet (namespace `drone-dji`: AbsoluteAltitude, RelativeAltitude, GimbalYawDegree / GimbalPitchDegree /
GimbalRollDegree, FlightYawDegree / FlightPitchDegree / FlightRollDegree, RtkFlag, RtkStdLon / RtkStdLat /
RtkStdHgt; GpsLatitude / GpsLongitude where the EXIF has none), and their conversion to a metric CRS with
pyproj (the UTM zone of the photos' mean position unless another is chosen).

DJI's RtkFlag is the GNSS solution's type: 0 no position, 16 single point (metres), 34 float (decimetres),
50 fixed (centimetres); only 50 is RTK-grade. Heights are kept as the photos give them: DJI's AbsoluteAltitude
where the XMP has it (the WGS 84 ellipsoidal height on RTK drones; on consumer drones a GPS / barometric
height, often metres off), else the EXIF GPSAltitude (above sea level by the EXIF standard); nothing is
converted between height systems. numpy, Pillow and pyproj; no torch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ragsplat.errors import ConfigError, DatasetError

DJI_NS = "http://www.dji.com/drone-dji/1.0/"
RDF_NS = "http://www.w3.org/1999/02/22-rdf-syntax-ns#"
RTK_FIXED = 50  # DJI RtkFlag of a fixed (integer ambiguity) solution: centimetre-level
GPS_IFD = 0x8825  # the EXIF pointer to the GPS block
WGS84 = "EPSG:4326"


@dataclass(frozen=True)
class PhotoPosition:
    """Where one photo was taken, as its metadata says (degrees, metres)."""

    name: str  # the photo's file name
    lat: float  # degrees north
    lon: float  # degrees east
    altitude: float  # metres, as the photo gives it (see `altitude_source`)
    source: str  # where lat / lon came from: "EXIF GPS" or "DJI XMP"
    altitude_source: str  # "DJI XMP AbsoluteAltitude" or "EXIF GPSAltitude"
    relative_altitude: float | None = None  # DJI RelativeAltitude: above the take-off point (m)
    rtk_flag: int | None = None  # DJI RtkFlag (50: fixed); None: no RTK
    std_horizontal: float | None = None  # DJI max(RtkStdLon, RtkStdLat) (m)
    std_vertical: float | None = None  # DJI RtkStdHgt (m)
    # DJI gimbal yaw, pitch, roll (degrees; pitch -90: nadir)
    gimbal: tuple[float, float, float] | None = None
    flight: tuple[float, float, float] | None = None  # DJI aircraft yaw, pitch, roll (degrees)

    @property
    def rtk_fixed(self) -> bool:
        return self.rtk_flag == RTK_FIXED

    @property
    def barometric(self) -> bool:
        """Whether its height is the barometer's (`barometric_heights`): no RTK fix, a RelativeAltitude."""
        return not self.rtk_fixed and self.relative_altitude is not None


def xmp_packet(data: bytes) -> bytes | None:
    """The first XMP packet (`<x:xmpmeta ...>...</x:xmpmeta>`) among a file's bytes, or None."""
    start = data.find(b"<x:xmpmeta")
    end = data.find(b"</x:xmpmeta>", start)
    return None if start < 0 or end < 0 else data[start:end + len(b"</x:xmpmeta>")]


def dji_tags(packet: bytes | None) -> dict[str, str]:
    """{local name: text} of the `drone-dji` properties in an XMP packet, written as attributes of an
    rdf:Description (as DJI's cameras do) or as its child elements. Empty when there are none or the packet
    is not XML."""
    import xml.etree.ElementTree as ET

    if not packet:
        return {}
    try:
        root = ET.fromstring(packet)
    except ET.ParseError:
        return {}
    out: dict[str, str] = {}
    prefix = "{" + DJI_NS + "}"
    for desc in root.iter("{" + RDF_NS + "}Description"):
        for key, value in desc.attrib.items():
            if key.startswith(prefix):
                out.setdefault(key[len(prefix):], value.strip())
        for child in desc:
            if child.tag.startswith(prefix) and child.text is not None:
                out.setdefault(child.tag[len(prefix):], child.text.strip())
    return out


def _number(text: str | None) -> float | None:
    try:
        value = float(text) if text is not None else None
    except ValueError:
        return None
    return value if value is not None and math.isfinite(value) else None


def _rational(value) -> float | None:
    try:
        value = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return value if math.isfinite(value) else None


def _degrees(dms, ref) -> float | None:
    """Decimal degrees from EXIF (degrees, minutes, seconds) rationals and a reference letter (N/S/E/W)."""
    try:
        d, m, s = (float(v) for v in dms)
    except (TypeError, ValueError):
        return None
    value = d + m / 60 + s / 3600
    if not math.isfinite(value):
        return None
    ref = ref.decode(errors="replace") if isinstance(ref, bytes) else str(ref or "")
    return -value if ref.strip().upper()[:1] in ("S", "W") else value


def _angles(tags: dict[str, str], kind: str) -> tuple[float, float, float] | None:
    values = [_number(tags.get(f"{kind}{axis}Degree")) for axis in ("Yaw", "Pitch", "Roll")]
    return None if any(v is None for v in values) else tuple(values)


def read_photo(path: Path) -> PhotoPosition:
    """The position in a photo's EXIF GPS block (or, without one, DJI's XMP GpsLatitude / GpsLongitude), its
    height (DJI's AbsoluteAltitude, else the EXIF GPSAltitude) and DJI's RTK flag, accuracies and angles
    where the XMP has them. Raises DatasetError, in one line naming the photo, when it has no position."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    try:
        data = path.read_bytes()
        with Image.open(path) as im:
            gps = dict(im.getexif().get_ifd(GPS_IFD))
    except (OSError, UnidentifiedImageError, SyntaxError) as err:
        raise DatasetError(f"{path}: cannot read its metadata ({err})") from None
    tags = dji_tags(xmp_packet(data))
    lat, lon = _degrees(gps.get(2), gps.get(1)), _degrees(gps.get(4), gps.get(3))
    source = "EXIF GPS"
    if lat is None or lon is None:
        lat = _number(tags.get("GpsLatitude", tags.get("Latitude")))
        lon = _number(tags.get("GpsLongitude", tags.get("GpsLongtitude", tags.get("Longitude"))))
        source = "DJI XMP"
    altitude, altitude_source = _number(tags.get("AbsoluteAltitude")), "DJI XMP AbsoluteAltitude"
    if altitude is None and gps.get(6) is not None:
        altitude, altitude_source = _rational(gps[6]), "EXIF GPSAltitude"
        ref = gps.get(5)
        if altitude is not None and (ref[:1] == b"\x01" if isinstance(ref, bytes) else ref == 1):
            altitude = -altitude  # below sea level
    if lat is None or lon is None or altitude is None or not (-90 <= lat <= 90 and -180 <= lon <= 180):
        missing = "latitude / longitude" if lat is None or lon is None else (
            "altitude" if altitude is None else f"a position on Earth (latitude {lat}, longitude {lon})")
        raise DatasetError(f"{path}: no GPS position in its metadata ({missing} missing from the EXIF GPS "
                           "block and DJI's XMP); give the camera positions with --positions or ground "
                           "control with --gcp")
    flag = _number(tags.get("RtkFlag"))
    std = [_number(tags.get(k)) for k in ("RtkStdLon", "RtkStdLat", "RtkStdHgt")]
    return PhotoPosition(
        path.name, lat, lon, altitude, source, altitude_source,
        relative_altitude=_number(tags.get("RelativeAltitude")),
        rtk_flag=None if flag is None else int(flag),
        std_horizontal=None if None in std[:2] else max(std[:2]),
        std_vertical=std[2],
        gimbal=_angles(tags, "Gimbal"), flight=_angles(tags, "Flight"))


def read_photos(paths: list[Path]) -> list[PhotoPosition]:
    """`read_photo` of each; a DatasetError names the first photo without a position and how many others
    lack one."""
    out, missing = [], []
    for path in paths:
        try:
            out.append(read_photo(path))
        except DatasetError as err:
            missing.append(err)
    if missing:
        others = f" ({len(missing) - 1} other photos have none either)" if len(missing) > 1 else ""
        raise DatasetError(f"{missing[0]}{others}")
    return out


def utm_epsg(lat: float, lon: float) -> int:
    """EPSG code of the WGS 84 UTM zone holding (lat, lon): 326zz north of the equator, 327zz south, with the
    standard exceptions (zone 32V over south-west Norway; 31X, 33X, 35X, 37X over Svalbard)."""
    lon = (lon + 180) % 360 - 180
    zone = min(int((lon + 180) // 6) + 1, 60)
    if 56 <= lat < 64 and 3 <= lon < 12:
        zone = 32
    elif 72 <= lat < 84 and 0 <= lon < 42:
        zone = 31 if lon < 9 else 33 if lon < 21 else 35 if lon < 33 else 37
    return (32600 if lat >= 0 else 32700) + zone


def metric_crs(text: str | None, lat: float, lon: float):
    """The pyproj CRS positions are converted to: `text` (e.g. "EPSG:32633") when given, else the UTM zone
    of (lat, lon). Raises ConfigError for a CRS that is not projected in metres."""
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    try:
        crs = CRS.from_user_input(text if text else f"EPSG:{utm_epsg(lat, lon)}")
    except CRSError as err:
        raise ConfigError(f"--crs {text}: not a coordinate reference system pyproj knows ({err})") from None
    units = {axis.unit_name for axis in crs.axis_info[:2]}
    if not crs.is_projected or not units <= {"metre", "meter"}:
        raise ConfigError(f"--crs {text}: {crs.name} is not a projected CRS in metres (the positions must be "
                          "metres, e.g. a UTM zone: EPSG:326zz north, EPSG:327zz south)")
    return crs


def crs_label(crs) -> str:
    """"EPSG:N" where the CRS has an EPSG code, else its WKT (what the products' CRS is given as)."""
    code = crs.to_epsg()
    return f"EPSG:{code}" if code else crs.to_wkt()


def to_metric(lat, lon, height, crs) -> np.ndarray:
    """[N, 3] (easting, northing, height) in `crs` of WGS 84 degrees; heights unchanged."""
    from pyproj import Transformer

    to = Transformer.from_crs(WGS84, crs, always_xy=True)
    x, y = to.transform(np.asarray(lon, float), np.asarray(lat, float))
    return np.column_stack([np.atleast_1d(x), np.atleast_1d(y), np.atleast_1d(np.asarray(height, float))])


def to_geographic(xyz, crs) -> np.ndarray:
    """[N, 3] (latitude, longitude, height) of (easting, northing, height) [N, 3] in `crs`; heights
    unchanged."""
    from pyproj import Transformer

    xyz = np.atleast_2d(np.asarray(xyz, float))
    back = Transformer.from_crs(crs, WGS84, always_xy=True)
    lon, lat = back.transform(xyz[:, 0], xyz[:, 1])
    return np.column_stack([lat, lon, xyz[:, 2]])


def barometric_heights(photos: list[PhotoPosition]) -> np.ndarray:
    """[N] each photo's height: a photo without RTK fix that has DJI's RelativeAltitude (the barometer's
    height above the take-off point) is put at the take-off point's height plus it, the take-off point's
    height the median of those photos' height as given less their relative altitude; any other photo keeps
    its height. A consumer drone's GPS heights scatter by metres from photo to photo and tilt a frame fitted
    to them; its barometer holds the heights along a flight to decimetres (`BAROMETER_SIGMA`)."""
    heights = np.array([p.altitude for p in photos], float)
    baro = np.array([p.barometric for p in photos])
    if baro.any():
        relative = np.array([p.relative_altitude if p.barometric else np.nan for p in photos])
        takeoff = float(np.median(heights[baro] - relative[baro]))
        heights[baro] = takeoff + relative[baro]
    return heights


def positions(photos: list[PhotoPosition], crs: str | None = None) -> tuple[dict[str, np.ndarray], object]:
    """({photo name: [3] easting, northing, height}, the pyproj CRS) of the photos' positions, in `crs` or
    the UTM zone of their mean position; the heights `barometric_heights`."""
    lat = np.array([p.lat for p in photos])
    lon = np.array([p.lon for p in photos])
    mean_lon = math.degrees(math.atan2(np.sin(np.radians(lon)).mean(), np.cos(np.radians(lon)).mean()))
    target = metric_crs(crs, float(lat.mean()), mean_lon)
    xyz = to_metric(lat, lon, barometric_heights(photos), target)
    return {p.name: xyz[k] for k, p in enumerate(photos)}, target


def describe_crs(crs) -> str:
    """"EPSG:32633, WGS 84 / UTM zone 33N" and the like."""
    return f"{crs_label(crs)}, {crs.name}" if crs.to_epsg() else crs.name


CONSUMER_SIGMA = (2.0, 3.0)  # a consumer drone's GPS, horizontal and vertical (m): see `sigmas`
# A drone's barometric height along one flight, relative to its take-off (m): DJI's RelativeAltitude holds
# decimetres (docs/survey.md, "A consumer drone's nadir flight").
BAROMETER_SIGMA = 0.15
MIN_STD = 0.005  # the smallest RTK accuracy taken from a photo's own report (m)


def sigmas(photos: list[PhotoPosition], rtk: tuple[float, float] | None,
           consumer: tuple[float, float] = CONSUMER_SIGMA, barometer: float = BAROMETER_SIGMA) -> np.ndarray:
    """[N, 2] accuracy (m; horizontal per axis, vertical) of each photo's position, by its source. RTK fixed
    (RtkFlag 50): `rtk` when given, else the photo's own RtkStdLon / RtkStdLat / RtkStdHgt (at least
    MIN_STD), else 2 / 3 cm. Anything else (no RTK flag, or a single-point or float solution): `consumer`,
    metres: a consumer drone's single-point GNSS is good to 1-2 m horizontally within a flight and each
    flight line can be 1-1.5 m off the others (the strip offsets of a real Phantom 3 flight), worse
    vertically; its height `barometer` where it is the barometer's (`barometric_heights`)."""
    out = np.empty((len(photos), 2))
    for k, p in enumerate(photos):
        if not p.rtk_fixed:
            out[k] = (consumer[0], barometer if p.barometric else consumer[1])
        elif rtk is not None:
            out[k] = rtk
        else:
            out[k] = [max(MIN_STD, s) if s is not None else d
                      for s, d in ((p.std_horizontal, 0.02), (p.std_vertical, 0.03))]
    return out


MM_PER_UNIT = {2: 25.4, 3: 10.0, 4: 1.0, 5: 1e-3}  # EXIF FocalPlaneResolutionUnit: inch, cm, mm, um


def focal_pixels(path: Path) -> float | None:
    """A photo's focal length in pixels from its EXIF: FocalLength (mm) x FocalPlaneXResolution (pixels per
    unit), else FocalLengthIn35mmFilm x the longer side / 36 mm; None without either (or unreadable)."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            tags, longest = dict(im.getexif().get_ifd(0x8769)), max(im.size)
    except (OSError, UnidentifiedImageError, SyntaxError):
        return None
    focal, per_unit, unit = (_rational(tags.get(k)) for k in (0x920A, 0xA20E, 0xA210))
    if focal and per_unit and unit in MM_PER_UNIT:
        return focal * per_unit * MM_PER_UNIT[int(unit)]
    f35 = _rational(tags.get(0xA405))
    return f35 * longest / 36.0 if f35 else None

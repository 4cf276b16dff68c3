"""A survey's photos as a drone writes them: JPEG with the focal length in EXIF, GPS tags and DJI's XMP
(gimbal, flight angles, relative altitude, RTK flag and accuracies). Reading them back is `dataset.exif`'s.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ragsplat.outputs import write_bytes


def write_jpeg(path: Path, image: np.ndarray, focal_px: float, quality: int = 95,
               gps: tuple[float, float, float] | None = None, xmp: dict[str, object] | None = None) -> None:
    """[H, W, 3] uint8 RGB as a JPEG whose EXIF gives the focal length as a camera does (FocalLength in mm
    with FocalPlaneX/YResolution in pixels per mm, a nominal 0.01 mm pixel), which structure from motion
    reads as its focal length prior. With `gps` (latitude, longitude in degrees, altitude in metres), also
    the EXIF GPS block as a drone writes it (degrees, minutes, seconds to 1e-6 arc seconds; altitude to the
    millimetre, GPSAltitudeRef 1 below zero); with `xmp` ({property: value}), an XMP packet of DJI's
    `drone-dji` properties (e.g. AbsoluteAltitude, GimbalPitchDegree, RtkFlag; numbers written signed, as DJI
    does) after the EXIF. Without either the bytes are those of a plain call."""
    import io

    from PIL import Image
    from PIL.TiffImagePlugin import IFDRational

    pitch_mm = 0.01
    exif = Image.Exif()
    exif[0x010F], exif[0x0110] = "ragsplat", "synthetic survey camera"  # Make, Model
    sub = exif.get_ifd(0x8769)
    sub[0x920A] = IFDRational(round(focal_px * pitch_mm * 1e6), 1_000_000)  # FocalLength (mm)
    sub[0xA20E] = sub[0xA20F] = IFDRational(round(1e6 / pitch_mm), 1_000_000)  # FocalPlaneX/YResolution
    sub[0xA210] = 4  # FocalPlaneResolutionUnit: millimetres
    if gps is not None:
        lat, lon, alt = (float(v) for v in gps)
        block = exif.get_ifd(0x8825)
        block[0x0000] = b"\x02\x03\x00\x00"  # GPSVersionID 2.3
        block[0x0001], block[0x0002] = "N" if lat >= 0 else "S", _dms(lat)
        block[0x0003], block[0x0004] = "E" if lon >= 0 else "W", _dms(lon)
        block[0x0005] = b"\x01" if alt < 0 else b"\x00"  # GPSAltitudeRef: below / above sea level
        block[0x0006] = IFDRational(round(abs(alt) * 1000), 1000)
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image)).save(buf, "JPEG", quality=quality, exif=exif)
    data = buf.getvalue()
    if xmp:
        data = _with_app1(data, b"http://ns.adobe.com/xap/1.0/\x00" + _dji_xmp(xmp))
    write_bytes(path, data)


def _dms(degrees: float) -> tuple:
    """EXIF (degrees, minutes, seconds) rationals of |degrees|, the seconds to 1e-6 arc seconds (3e-5 m)."""
    from PIL.TiffImagePlugin import IFDRational

    micro = round(abs(degrees) * 3600e6)  # whole micro arc seconds
    d, rest = divmod(micro, 3600 * 10**6)
    m, s = divmod(rest, 60 * 10**6)
    return IFDRational(d, 1), IFDRational(m, 1), IFDRational(s, 10**6)


def _dji_xmp(properties: dict[str, object]) -> bytes:
    """An XMP packet with the `drone-dji` properties as attributes of one rdf:Description, as DJI writes
    it."""
    from xml.sax.saxutils import quoteattr

    def text(value) -> str:
        if isinstance(value, bool) or not isinstance(value, int | float):
            return str(value)
        return str(value) if isinstance(value, int) else f"{value:+.6f}".rstrip("0").rstrip(".")

    attrs = "".join(f"\n    drone-dji:{key}={quoteattr(text(value))}" for key, value in properties.items())
    return ('<?xpacket begin="\ufeff" id="W5M0MpCehiHzreSzNTczkc9d"?>\n'
            '<x:xmpmeta xmlns:x="adobe:ns:meta/">\n'
            ' <rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">\n'
            '  <rdf:Description rdf:about="DJI Meta Data"\n'
            f'    xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/"{attrs}/>\n'
            ' </rdf:RDF>\n</x:xmpmeta>\n<?xpacket end="w"?>').encode()


def _with_app1(jpeg: bytes, payload: bytes) -> bytes:
    """The JPEG with an APP1 segment holding `payload` after its leading application segments (JFIF, EXIF)."""
    if len(payload) > 65533:
        raise ValueError(f"an APP1 segment holds at most 65533 bytes, got {len(payload)}")
    at = 2  # after SOI
    while jpeg[at] == 0xFF and 0xE0 <= jpeg[at + 1] <= 0xEF:
        at += 2 + int.from_bytes(jpeg[at + 2:at + 4], "big")
    return jpeg[:at] + b"\xff\xe1" + (len(payload) + 2).to_bytes(2, "big") + payload + jpeg[at:]

"""A stand-in for rasterio copied by `python -m tools.slim --stand-ins` (see there): it parses no CRS, and its
"GeoTIFF" is a numpy .npz of the bands and the profile, which `python -m tools.slim --unpack` turns into a
GeoTIFF where rasterio is (a lent GPU has no GDAL and no wheel small enough to carry). It reads no raster.
Never beside a real rasterio."""
import builtins

import numpy as np

from rasterio import crs, errors, transform  # noqa: F401 (the submodules the project imports)

PROFILE = ("driver", "width", "height", "count", "dtype", "crs", "transform", "nodata")


class _NpzTiff:
    def __init__(self, path, profile):
        self.path, self.profile, self.bands, self.descriptions = path, profile, {}, {}

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if exc[0] is None:
            p = self.profile
            extra = {"transform": np.asarray(p["transform"], dtype=np.float64), "crs": str(p["crs"]),
                     "nodata": np.float64(p["nodata"]), "dtype": str(p["dtype"]),
                     "descriptions": np.array([self.descriptions.get(k, "") for k in sorted(self.bands)])}
            with builtins.open(self.path, "wb") as f:
                np.savez(f, bands=np.stack([self.bands[k] for k in sorted(self.bands)]), **extra)
        return False

    def write(self, image, band):
        self.bands[band] = np.asarray(image)

    def set_band_description(self, band, text):
        self.descriptions[band] = text


def open(path, mode="r", **kwargs):
    if mode != "w":
        raise errors.RasterioIOError(f"{path}: the rasterio stand-in reads no raster")
    return _NpzTiff(path, {k: kwargs.get(k) for k in PROFILE})

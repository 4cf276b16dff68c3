"""A stand-in for rasterio copied by `python -m tools.slim --stand-ins` (see there): it parses no CRS and
writes empty GeoTIFFs. Only for scoring an ablation on a machine without GDAL; never beside a real
rasterio."""
import builtins

from rasterio import crs, errors, transform  # noqa: F401 (the submodules the project imports)


class _EmptyTiff:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def write(self, image, band):
        pass

    def set_band_description(self, band, text):
        pass


def open(path, mode="r", **kwargs):
    if mode != "w":
        raise errors.RasterioIOError(f"{path}: the rasterio stand-in reads no raster")
    builtins.open(path, "wb").close()
    return _EmptyTiff()

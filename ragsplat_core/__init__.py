"""ragsplat's core: refraction-aware Gaussian splatting (RA-GS) for photogrammetric bathymetry.

The public API, imported on first use (so that `ragsplat.dataset.layout`, `ragsplat.camera`
and `ragsplat.snell` stay importable without torch, for the dataset generator and Blender):

    Camera            pinhole camera, OpenCV world-to-camera (the conventions in one place)
    WaterSurface      the plane z = level with refractive index n
    refract_gaussians true -> apparent Gaussians for one camera
    rasterize         differentiable Gaussian rasterizer (torch / numba CPU / gsplat backends)
    rasterize_surfels differentiable 2D Gaussian surfel (2DGS) rasterizer, same backends
    load_dataset      a dataset directory -> Dataset (cameras, images, bed info, ground truth)
    Trainer           one RA-GS training run (with TrainConfig and preset_config)
    RagsplatError     base of the errors raised for bad inputs (see `errors`)
"""

_API = {
    "Camera": "ragsplat.camera",
    "WaterSurface": "ragsplat.refraction",
    "refract_gaussians": "ragsplat.refraction",
    "rasterize": "ragsplat.rasterize",
    "rasterize_surfels": "ragsplat.rasterize_surfels",
    "load_dataset": "ragsplat.dataset.load",
    "Dataset": "ragsplat.dataset.load",
    "Trainer": "ragsplat.train.trainer",
    "TrainConfig": "ragsplat.train.config",
    "preset_config": "ragsplat.train.config",
    "RagsplatError": "ragsplat.errors",
}
__all__ = list(_API)


def __getattr__(name: str):
    if name in _API:
        import importlib

        return getattr(importlib.import_module(_API[name]), name)
    raise AttributeError(f"module 'ragsplat' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + __all__)

"""ragsplat's core: refraction-aware Gaussian splatting (RA-GS) for photogrammetric bathymetry.

The public API, imported on first use (so that `ragsplat_core.dataset.layout`, `ragsplat_core.camera`
and `ragsplat_core.snell` stay importable without torch, for the dataset generator and Blender):

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
    "Camera": "ragsplat_core.camera",
    "WaterSurface": "ragsplat_core.refraction",
    "refract_gaussians": "ragsplat_core.refraction",
    "rasterize": "ragsplat_core.rasterize",
    "rasterize_surfels": "ragsplat_core.rasterize_surfels",
    "load_dataset": "ragsplat_core.dataset.load",
    "Dataset": "ragsplat_core.dataset.load",
    "Trainer": "ragsplat_core.train.trainer",
    "TrainConfig": "ragsplat_core.train.config",
    "preset_config": "ragsplat_core.train.config",
    "RagsplatError": "ragsplat_core.errors",
}
__all__ = list(_API)


def __getattr__(name: str):
    if name in _API:
        import importlib

        return getattr(importlib.import_module(_API[name]), name)
    raise AttributeError(f"module 'ragsplat_core' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + __all__)

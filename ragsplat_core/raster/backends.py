"""The rasterizer's backends in one table: what each one runs at each stage of `rasterize` (3DGS),
`rasterize_surfels` (2DGS) and the trainer's per-view colours, and which one a `backend=` name means.

| field            | torch (the reference)       | cpu (numba kernels)          | gsplat (CUDA)              |
|------------------|-----------------------------|------------------------------|----------------------------|
| colors (SH)      | gaussians.colors_for_view   | cpu/sh.colors_for_view       | gaussians.colors_for_view  |
| covariance       | gaussians.covariance        | cpu/rotation.covariance_cpu  | gaussians.covariance       |
| tangents         | gaussians.surfel_tangents   | cpu/rotation.tangents_cpu    | gaussians.surfel_tangents  |
| project          | reference/project.project   | cpu/project.project          | -                          |
| bin_tiles        | reference/project.bin_tiles | cpu/project.bin_tiles        | -                          |
| composite        | reference/composite         | cpu/composite                | -                          |
| render           | -                           | -                            | cuda/render (fused 3DGS)   |
| surfel_composite | reference/surfel_composite  | cpu/surfel_composite         | cuda/surfel_composite      |

`rasterize` runs covariance, project, bin_tiles and composite, or render where the backend has it (gsplat
takes the quaternions and scales itself). Every backend projects surfels with
`reference/surfel_project.project_surfels` (PyTorch) before its surfel_composite. The cpu and gsplat
modules are imported when their backend is first asked for, so ragsplat imports without numba and
without gsplat; `gaussians` (the model) imports nothing of this folder.
"""

from __future__ import annotations

import functools
import importlib.util
from collections.abc import Callable
from dataclasses import dataclass

import torch

from ragsplat import gaussians
from ragsplat.errors import ConfigError


@dataclass(frozen=True)
class Backend:
    """One backend's function for each stage (the table above); None where gsplat fuses stages."""

    name: str
    colors: Callable  # (splats, camera_center [3], degree) -> RGB [N, 3]
    covariance: Callable  # (quats [N, 4], scales [N, 3]) -> [N, 3, 3]
    tangents: Callable  # (quats [N, 4], scales [N, 2]) -> scaled tangents [N, 3, 2]
    project: Callable | None  # (means, covars, opacities, camera) -> Projected
    bin_tiles: Callable | None  # (Projected or SurfelsProjected, width, height) -> Bins
    composite: Callable | None  # (proj, opacities, colors, bins, width, height, median) -> per-pixel sums
    render: Callable | None  # fused 3DGS rasterization: `rasterize`'s arguments -> its outputs
    surfel_composite: Callable  # torch, cpu: (proj, opacities, colors, bins, width, height) -> sums;
    # gsplat (bins None): (proj, opacities, colors, background, width, height) -> outputs, background in


def _torch() -> Backend:
    from ragsplat.raster.reference import composite, project, surfel_composite

    return Backend("torch", colors=gaussians.colors_for_view, covariance=gaussians.covariance,
                   tangents=gaussians.surfel_tangents, project=project.project, bin_tiles=project.bin_tiles,
                   composite=composite.composite, render=None, surfel_composite=surfel_composite.composite)


def _cpu() -> Backend:
    # numba is imported here, when the cpu backend is first asked for
    from ragsplat.raster.cpu import composite, project, rotation, sh, surfel_composite

    return Backend("cpu", colors=sh.colors_for_view, covariance=rotation.covariance_cpu,
                   tangents=rotation.tangents_cpu, project=project.project, bin_tiles=project.bin_tiles,
                   composite=composite.composite, render=None, surfel_composite=surfel_composite.composite)


def _gsplat() -> Backend:
    from ragsplat.raster.cuda import render, surfel_composite  # they import gsplat when called

    return Backend("gsplat", colors=gaussians.colors_for_view, covariance=gaussians.covariance,
                   tangents=gaussians.surfel_tangents, project=None, bin_tiles=None, composite=None,
                   render=render.render, surfel_composite=surfel_composite.composite)


_TABLE = {"torch": _torch, "cpu": _cpu, "gsplat": _gsplat}
BACKENDS = ("auto", *_TABLE)  # the names `backend=` takes


@functools.cache
def backend(name: str) -> Backend:
    """The table's row `name` ("torch", "cpu" or "gsplat"), its modules imported on first use."""
    return _TABLE[name]()


def choose_backend(name: str, device: torch.device) -> Backend:
    """The backend that `name` ("auto" or a name) means for tensors on `device`; ConfigError if it cannot
    run there."""
    if name not in BACKENDS:
        raise ConfigError(f"unknown rasterizer backend {name!r}; choose one of {', '.join(BACKENDS)}")
    if name == "auto":
        if device.type == "cuda":
            name = "gsplat" if gsplat_available() else "torch"
        else:
            name = "cpu" if device.type == "cpu" else "torch"
    if name == "cpu" and device.type != "cpu":
        raise ConfigError(f"backend 'cpu' needs CPU tensors, got {device}; use 'torch' or 'gsplat'")
    if name == "gsplat" and not (device.type == "cuda" and gsplat_available()):
        raise ConfigError("backend 'gsplat' needs the gsplat package and CUDA tensors")
    return backend(name)


def gsplat_available() -> bool:
    return importlib.util.find_spec("gsplat") is not None


def build_gsplat() -> None:
    """Build gsplat's CUDA extension (JIT, a minute or more the first time on a machine) or load it, in this
    process. A process that finds no built library deletes the build folder before building, so processes
    that first use gsplat at once delete each other's build (gsplat 1.5.3; seen with six on an H100): a
    parent builds it before it starts them."""
    importlib.import_module("gsplat.cuda._backend")

"""Differentiable Gaussian rasterizer: one call, several backends with the same semantics.

`rasterize(means, quats, scales, opacities, colors, camera, background, covars=None, backend="auto",
median=False)`
renders Gaussians (3DGS / gsplat "classic" semantics, see `raster/project.py` for the projection):
EWA projection with a 0.3 px dilation, Gaussians with camera z < 0.01 culled, front-to-back compositing in
depth order, alpha = min(0.99, o exp(power)), alpha < 1/255 skipped, a pixel stops before the Gaussian that
would take its transmittance below 1e-4. Outputs:
- image [H, W, 3] = sum_i w_i c_i + T background, with w_i = alpha_i T_i;
- alpha [H, W, 1] = 1 - T (T = final transmittance);
- depth [H, W, 1] = sum_i w_i z_i / alpha, the expected camera z-depth; 0 where nothing was composited;
- meta: `means2d` [N, 2] pixels (its `.grad` holds the screen-space gradient after backward when the
  inputs require grad: densification statistics), `radii` [N] int32 (0 = not rendered), `depths` [N]
  camera z, `conics` [N, 3], `visible` [N] bool, `tiles_touched` [N] int32, `backend` (name used),
  `width`, `height` (pixels), `median_depth` [H, W, 1] with `median=True` (else None): the camera z of the
  Gaussian at which the pixel's transmittance first falls to <= 0.5, 0 where it never does (2DGS's median
  depth; forward only, no gradient; opt-in because training does not need it and it costs the cpu kernel
  about 6 % of its forward). gsplat's 3DGS rasterizer has none: with gsplat it comes from a separate no-grad
  pass of the torch backend on the same device (alpha clamped at 0.99 there, 0.999 in gsplat).
  With gsplat, `means2d` is a detached tensor whose `.grad` is filled by a hook during backward (call no
  `retain_grad` on it).

Backends: "torch" (plain PyTorch, autograd, any device: the reference), "cpu" (numba kernels with a
hand-written backward, float32 compositing, CPU tensors only), "gsplat" (gsplat's CUDA `rasterization`,
optional, CUDA tensors only; it clamps alpha at 0.999 instead of 0.99), "auto" (gsplat on CUDA when
installed, else torch on CUDA, else cpu). Gradients flow to means, quats, scales, opacities, colors,
covars and background.
"""

from __future__ import annotations

import importlib.util

import torch

from ragsplat_core.camera import Camera
from ragsplat_core.errors import ConfigError
from ragsplat_core.gaussians import covariance
from ragsplat_core.raster.project import bin_tiles, project

BACKENDS = ("auto", "torch", "cpu", "gsplat")


def rasterize(means, quats, scales, opacities, colors, camera: Camera, background, covars=None,
              backend: str = "auto", median: bool = False):
    """Renders Gaussians; returns (image [H, W, 3], alpha [H, W, 1], depth [H, W, 1], meta dict).

    means [N, 3] world; quats [N, 4] (w, x, y, z), normalised here; scales [N, 3] linear; opacities [N] in
    [0, 1]; colors [N, 3]; background [3] (tensor or sequence); covars [N, 3, 3] world covariances which,
    when given, replace quats and scales (those may then be None).
    """
    n = means.shape[0]
    _check(means, quats, scales, opacities, colors, covars, n)
    background = torch.as_tensor(background, dtype=colors.dtype, device=colors.device).reshape(3)
    backend = choose_backend(backend, means.device)
    if backend == "gsplat":
        out = _rasterize_gsplat(means, quats, scales, opacities, colors, camera, background, covars)
        if median:  # a forward pass of the reference on the same device: gsplat has no median depth
            with torch.no_grad():
                out[3]["median_depth"] = rasterize(means, quats, scales, opacities, colors, camera, background,
                                                   covars, backend="torch", median=True)[3]["median_depth"]
        return out
    if covars is None:
        covars = covariance(quats, scales, fast=backend == "cpu")  # [N, 3, 3]
    if backend == "cpu":
        from ragsplat_core.raster.project_cpu import project as project_fast

        proj = project_fast(means, covars, opacities, camera)
    else:
        proj = project(means, covars, opacities, camera)
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    bins = bin_tiles(proj, camera.width, camera.height, fast=backend == "cpu")
    if backend == "torch":
        from ragsplat_core.raster.torch_backend import composite
    else:
        from ragsplat_core.raster.cpu_backend import composite
    color_sum, trans, z_sum, med = composite(proj, opacities, colors, bins, camera.width, camera.height, median)
    image, alpha, depth = resolve(color_sum, trans, z_sum, background)
    meta = {"means2d": means2d, "radii": proj.radii, "depths": proj.depths, "conics": proj.conics,
            "visible": proj.visible, "tiles_touched": bins.tiles_touched, "backend": backend,
            "width": camera.width, "height": camera.height, "median_depth": None if med is None else med[..., None]}
    return image, alpha[..., None], depth[..., None], meta


def resolve(color_sum, trans, z_sum, background):
    """Per-pixel sums of the compositing (colour [H, W, 3] without background, final transmittance [H, W],
    weighted camera z [H, W]) -> (image [H, W, 3], alpha [H, W], expected z-depth [H, W], 0 where empty)."""
    image = color_sum + trans[..., None] * background
    alpha = 1 - trans
    hit = alpha > 0  # exactly 0 where nothing was composited (each splat adds at least 1/255)
    depth = torch.where(hit, z_sum / torch.where(hit, alpha, torch.ones_like(alpha)), torch.zeros_like(alpha))
    return image, alpha, depth


def gsplat_available() -> bool:
    return importlib.util.find_spec("gsplat") is not None


def build_gsplat() -> None:
    """Build gsplat's CUDA extension (JIT, a minute or more the first time on a machine) or load it, in this
    process. A process that finds no built library deletes the build folder before building, so processes
    that first use gsplat at once delete each other's build (gsplat 1.5.3; seen with six on an H100): a
    parent builds it before it starts them."""
    importlib.import_module("gsplat.cuda._backend")


def choose_backend(backend: str, device: torch.device) -> str:
    """The backend that `backend` ("auto" or a name) means for tensors on `device`; ConfigError if it
    cannot run there."""
    if backend not in BACKENDS:
        raise ConfigError(f"unknown rasterizer backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    if backend == "auto":
        if device.type == "cuda":
            return "gsplat" if gsplat_available() else "torch"
        return "cpu" if device.type == "cpu" else "torch"
    if backend == "cpu" and device.type != "cpu":
        raise ConfigError(f"backend 'cpu' needs CPU tensors, got {device}; use 'torch' or 'gsplat'")
    if backend == "gsplat" and not (device.type == "cuda" and gsplat_available()):
        raise ConfigError("backend 'gsplat' needs the gsplat package and CUDA tensors")
    return backend


def _check(means, quats, scales, opacities, colors, covars, n):
    shapes = {"means": (means, (n, 3)), "opacities": (opacities, (n,)), "colors": (colors, (n, 3))}
    if covars is None:
        shapes.update(quats=(quats, (n, 4)), scales=(scales, (n, 3)))
    else:
        shapes.update(covars=(covars, (n, 3, 3)))
    check_shapes("rasterize", shapes)


def check_shapes(caller: str, shapes: dict) -> None:
    """ValueError naming the first of `shapes` ({name: (value, shape)}) that is not a tensor of its shape."""
    for name, (value, shape) in shapes.items():
        if not torch.is_tensor(value) or tuple(value.shape) != shape:
            got = tuple(value.shape) if torch.is_tensor(value) else type(value).__name__
            raise ValueError(f"{caller}: {name} must be a tensor of shape {list(shape)}, got {got}")


def _rasterize_gsplat(means, quats, scales, opacities, colors, camera, background, covars):
    """gsplat's fused CUDA rasterizer (unpacked, so meta["means2d"] is per input Gaussian)."""
    from gsplat import rasterization

    dtype, device = means.dtype, means.device
    viewmat = torch.tensor(camera.w2c, dtype=torch.float32, device=device)[None]  # [1, 4, 4]
    K = torch.tensor(camera.K, dtype=torch.float32, device=device)[None]  # [1, 3, 3]
    renders, alphas, info = rasterization(
        means.float(), _f32(quats), _f32(scales), opacities.float(), colors.float(), viewmat, K, camera.width,
        camera.height, near_plane=0.01, eps2d=0.3, packed=False, tile_size=16,
        backgrounds=background.float()[None], render_mode="RGB+ED", rasterize_mode="classic",
        covars=_f32(covars))
    renders, alphas = renders.to(dtype), alphas.to(dtype)
    full = info["means2d"]  # [1, N, 2], a non-leaf tensor of the graph
    means2d = full[0].detach()
    if full.requires_grad:  # same contract as the other backends: meta["means2d"].grad after backward
        full.register_hook(lambda grad: setattr(means2d, "grad", grad[0]))
    radii = info["radii"][0]
    if radii.dim() == 2:  # newer gsplat: per-axis radii [N, 2]
        radii = radii.max(-1).values
    meta = {"means2d": means2d, "radii": radii.to(torch.int32), "depths": info["depths"][0],
            "conics": info["conics"][0], "visible": radii > 0, "tiles_touched": info["tiles_per_gauss"][0],
            "backend": "gsplat", "width": camera.width, "height": camera.height, "median_depth": None}
    return renders[0, ..., :3], alphas[0], renders[0, ..., 3:4], meta


def _f32(x):
    return None if x is None else x.float()  # gsplat's kernels are float32 only

"""Differentiable Gaussian rasterizer: one call, several backends with the same semantics.

`rasterize(means, quats, scales, opacities, colors, camera, background, covars=None, backend="auto",
median=False)`
renders Gaussians (3DGS / gsplat "classic" semantics, see `raster/reference/project.py` for the projection):
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

Backends (`raster/backends.py`: which function runs each stage): "torch" (plain PyTorch, autograd, any
device: the reference), "cpu" (numba kernels with a hand-written backward, float32 compositing, CPU tensors
only), "gsplat" (gsplat's CUDA `rasterization`, optional, CUDA tensors only; it clamps alpha at 0.999 instead
of 0.99), "auto" (gsplat on CUDA when installed, else torch on CUDA, else cpu). Gradients flow to means,
quats, scales, opacities, colors, covars and background.
"""

from __future__ import annotations

import torch

from ragsplat.camera import Camera
from ragsplat.raster.backends import BACKENDS, build_gsplat, choose_backend, gsplat_available

# the rasterizer's public API: the backend names and choice are defined in raster/backends.py
__all__ = ["BACKENDS", "build_gsplat", "check_shapes", "choose_backend", "gsplat_available", "rasterize",
           "resolve"]


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
    b = choose_backend(backend, means.device)
    if b.render is not None:
        out = b.render(means, quats, scales, opacities, colors, camera, background, covars)
        if median:  # a forward pass of the reference on the same device: gsplat has no median depth
            with torch.no_grad():
                out[3]["median_depth"] = rasterize(means, quats, scales, opacities, colors, camera,
                                                   background, covars, backend="torch",
                                                   median=True)[3]["median_depth"]
        return out
    if covars is None:
        covars = b.covariance(quats, scales)  # [N, 3, 3]
    proj = b.project(means, covars, opacities, camera)
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    bins = b.bin_tiles(proj, camera.width, camera.height)
    color_sum, trans, z_sum, med = b.composite(proj, opacities, colors, bins, camera.width, camera.height,
                                               median)
    image, alpha, depth = resolve(color_sum, trans, z_sum, background)
    meta = {"means2d": means2d, "radii": proj.radii, "depths": proj.depths, "conics": proj.conics,
            "visible": proj.visible, "tiles_touched": bins.tiles_touched, "backend": b.name,
            "width": camera.width, "height": camera.height,
            "median_depth": None if med is None else med[..., None]}
    return image, alpha[..., None], depth[..., None], meta


def resolve(color_sum, trans, z_sum, background):
    """Per-pixel sums of the compositing (colour [H, W, 3] without background, final transmittance [H, W],
    weighted camera z [H, W]) -> (image [H, W, 3], alpha [H, W], expected z-depth [H, W], 0 where empty)."""
    image = color_sum + trans[..., None] * background
    alpha = 1 - trans
    hit = alpha > 0  # exactly 0 where nothing was composited (each splat adds at least 1/255)
    depth = torch.where(hit, z_sum / torch.where(hit, alpha, torch.ones_like(alpha)), torch.zeros_like(alpha))
    return image, alpha, depth


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

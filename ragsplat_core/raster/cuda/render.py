"""3D Gaussians rasterized by gsplat's fused CUDA `rasterization` (projection, tiles and compositing in one
call), with the outputs and meta of `rasterize`. gsplat's "classic" mode has the reference's semantics
(`reference/project.py`) but for the alpha clamp, 0.999 instead of 0.99, and it has no median depth.
"""

from __future__ import annotations

import torch

from ragsplat.camera import Camera
from ragsplat.raster.reference.project import EPS2D, NEAR, TILE


def render(means, quats, scales, opacities, colors, camera: Camera, background, covars):
    """(image [H, W, 3], alpha [H, W, 1], depth [H, W, 1], meta) of `rasterize`, by gsplat's fused CUDA
    rasterizer (unpacked, so meta["means2d"] is per input Gaussian)."""
    from gsplat import rasterization

    dtype, device = means.dtype, means.device
    viewmat = camera.tensor("w2c", torch.float32, device)[None]  # [1, 4, 4]
    K = camera.tensor("K", torch.float32, device)[None]  # [1, 3, 3]
    renders, alphas, info = rasterization(
        means.float(), _f32(quats), _f32(scales), opacities.float(), colors.float(), viewmat, K, camera.width,
        camera.height, near_plane=NEAR, eps2d=EPS2D, packed=False, tile_size=TILE,
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

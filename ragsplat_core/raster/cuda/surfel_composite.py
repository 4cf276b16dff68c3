"""Surfel compositing by gsplat's CUDA 2DGS rasterization stage, fed with this package's own projection.

gsplat's `rasterization_2dgs` builds each surfel from a quaternion and two scales; RA-GS's refracted surfel is
a pair of tangents t' = J t (neither orthogonal nor of equal length), which no quaternion and scales give.
Only gsplat's projection needs them, though: its rasterization stage (`rasterize_to_pixels_2dgs`) reads
each surfel as a ray transform T = K [a b p] (`project_surfels(..., transforms=True)`), a projected centre
for the low-pass filter, an opacity, features and a normal. So the surfels are projected here, exactly as for
the torch and cpu backends (same means2d, same per-axis pixel reach for the tiles), and gsplat composites.

Semantics against the torch twin (`reference/surfel_composite.py`), gsplat 1.5: alpha is clamped at 0.999 (not
0.99); a sample's depth, and with it the depth, median depth and distortion, is its surfel's centre z (gsplat
composites depth as a per-surfel feature), not the z of the pixel's ray-plane intersection; median depth is
0 where the transmittance never reaches 0.5 (gsplat keeps the last surfel's there). Image, alpha and normals
are the same up to float32 round-off.
"""

from __future__ import annotations

import torch

from ragsplat.raster.reference.project import TILE
from ragsplat.raster.reference.surfel_project import SurfelsProjected


def composite(proj: SurfelsProjected, opacities: torch.Tensor, colors: torch.Tensor, background: torch.Tensor,
              width: int, height: int):
    """(image [H, W, 3] with background, alpha [H, W], depth [H, W] (0 where empty), normals [H, W, 3],
    distortion [H, W], median depth [H, W], tiles touched [N]); CUDA tensors, float32 inside."""
    from gsplat.cuda._wrapper import isect_offset_encode, isect_tiles, rasterize_to_pixels_2dgs

    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    means2d = proj.means2d.float()[None]  # [1, N, 2]
    depths = proj.depths.float()  # [N]: the tiles' sort key, and composited as the last feature
    tiles, isect_ids, flatten_ids = isect_tiles(means2d.detach(), proj.reach[None].contiguous(),
                                                depths.detach()[None], TILE, tiles_x, tiles_y)
    offsets = isect_offset_encode(isect_ids, 1, tiles_x, tiles_y)  # [1, tiles_y, tiles_x]
    feats = torch.cat([colors.float(), depths[:, None]], -1)[None]  # [1, N, 4]: depth last
    bg = torch.cat([background.float(), background.new_zeros(1).float()])[None]  # [1, 4]
    densify = torch.zeros_like(means2d)  # gsplat's densification gradient: means2d.grad is ours
    out, alpha, normals, distortion, median = rasterize_to_pixels_2dgs(
        means2d, proj.transforms.float()[None], feats, opacities.float()[None], proj.normals.float()[None],
        densify, width, height, TILE, offsets, flatten_ids, backgrounds=bg, distloss=True)
    out, alpha, normals = out[0], alpha[0, ..., 0], normals[0]
    hit = alpha > 0
    depth = torch.where(hit, out[..., 3] / torch.where(hit, alpha, torch.ones_like(alpha)),
                        torch.zeros_like(alpha))
    median = torch.where(alpha >= 0.5, median[0, ..., 0], torch.zeros_like(alpha))
    return out[..., :3], alpha, depth, normals, distortion[0, ..., 0], median, tiles[0]

"""Differentiable 2D Gaussian surfel rasterizer (2DGS, Huang et al. SIGGRAPH 2024), several backends.

`rasterize_surfels(means, quats, scales, opacities, colors, camera, background, tangents=None,
backend="auto", depth="ray")` renders surfels with the ray-splat intersection and low-pass filter of 2DGS (see
`raster/reference/surfel_project.py`) and the compositing of `rasterize` (alpha = min(0.99, o G), skipped
below 1/255, front to back by centre depth, a pixel stops before the surfel that would take its transmittance
below 1e-4; 16 px tiles; surfels whose centre has camera z < 0.01 culled). Outputs:
- image [H, W, 3] = sum_i w_i c_i + T background, with w_i = alpha_i T_i;
- alpha [H, W, 1] = 1 - T;
- depth [H, W, 1] = sum_i w_i z_i / alpha, z_i the camera z of the pixel's ray-plane intersection with
  surfel i (of its centre where the low-pass filter wins); with depth="centre" z_i is always the surfel's
  centre z, as gsplat composites it (median depth and distortion then use it too); 0 where nothing was
  composited;
- meta: `normals` [H, W, 3] = sum_i w_i n_i, n_i the unit world normal of surfel i turned towards the
  camera (not divided by alpha); `median_depth` [H, W, 1] z_i of the surfel at which the transmittance
  first falls to 0.5 or below (0 where it never does); `distortion` [H, W, 1] the 2DGS depth distortion
  sum_{i,j} w_i w_j |z_i - z_j| in plain camera z (metres; not 2DGS's NDC-mapped depth), accumulated
  with gsplat's running sums 2 sum_i w_i (z_i (1 - T_i) - sum_{j<i} w_j z_j) (equal to the pair sum when
  the samples' z grow in compositing order; for interpenetrating surfels it is the signed sum);
  `means2d` [N, 2] projected centres (their `.grad` after backward is the screen-space gradient used for
  densification, as with `rasterize`), `radii` [N] int32 (0 = not rendered), `depths` [N] centre camera z,
  `visible` [N], `tiles_touched` [N], `backend`, `width`, `height`.

`tangents` [N, 3, 2], when given, are the two scaled world tangent vectors (columns s_u t_u, s_v t_v,
not necessarily orthogonal) and replace quats and scales (which may then be None): RA-GS passes refracted
surfels as t' = J t, J = refraction.apparent_jacobian(...). The normal is then t'_u x t'_v normalised.

Backends (`raster/backends.py`): "torch" (plain PyTorch, autograd, any device: the reference), "cpu" (numba
kernels with a hand-written backward, float32 compositing, CPU tensors), "gsplat" (gsplat's CUDA 2DGS
rasterization stage fed with this module's projection, so tangents too; optional, CUDA tensors; see
`raster/cuda/surfel_composite.py` for where it differs: alpha clamp 0.999, depths at the surfels' centres),
"auto" (as `rasterize`).
Gradients flow to means, quats, scales (or tangents), opacities, colors and background, through every output.
"""

from __future__ import annotations

import torch

from ragsplat.camera import Camera
from ragsplat.raster.backends import choose_backend
from ragsplat.raster.reference.surfel_project import project_surfels
from ragsplat.rasterize import check_shapes, resolve

# a sample's z: where the pixel's ray meets the surfel (2DGS) or the surfel's centre (gsplat's, always)
DEPTHS = ("ray", "centre")


def rasterize_surfels(means, quats, scales, opacities, colors, camera: Camera, background, tangents=None,
                      backend: str = "auto", depth: str = "ray"):
    """Renders surfels; returns (image [H, W, 3], alpha [H, W, 1], depth [H, W, 1], meta dict).

    means [N, 3] world; quats [N, 4] (w, x, y, z), normalised here; scales [N, 2] linear; opacities [N] in
    [0, 1]; colors [N, 3]; background [3] (tensor or sequence); tangents [N, 3, 2] scaled world tangents.
    """
    _check(means, quats, scales, opacities, colors, tangents, means.shape[0])
    if depth not in DEPTHS:
        raise ValueError(f"depth must be one of {DEPTHS}, got {depth!r}")
    background = torch.as_tensor(background, dtype=colors.dtype, device=colors.device).reshape(3)
    b = choose_backend(backend, means.device)
    if tangents is None:
        tangents = b.tangents(quats, scales)  # [N, 3, 2]
    fused = b.bin_tiles is None  # gsplat: its own tiles, from the ray transforms
    proj = project_surfels(means, tangents, opacities, camera, transforms=fused)
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    meta = {"means2d": means2d, "radii": proj.radii, "depths": proj.depths, "visible": proj.visible,
            "backend": b.name, "width": camera.width, "height": camera.height}
    if fused:
        dtype = colors.dtype
        image, alpha, depth, normals, distortion, median, tiles = b.surfel_composite(
            proj, opacities, colors, background, camera.width, camera.height)
        meta.update(normals=normals.to(dtype), median_depth=median[..., None].to(dtype),
                    distortion=distortion[..., None].to(dtype), tiles_touched=tiles)
        return image.to(dtype), alpha[..., None].to(dtype), depth[..., None].to(dtype), meta
    bins = b.bin_tiles(proj, camera.width, camera.height)
    sums, trans, distortion, median = b.surfel_composite(proj, opacities, colors, bins, camera.width,
                                                         camera.height, centre=depth == "centre")
    image, alpha, depth = resolve(sums[..., :3], trans, sums[..., 6], background)
    meta.update(normals=sums[..., 3:6], median_depth=median[..., None], distortion=distortion[..., None],
                tiles_touched=bins.tiles_touched)
    return image, alpha[..., None], depth[..., None], meta


def depth_normals(depth: torch.Tensor, camera: Camera) -> torch.Tensor:
    """World unit normals [H, W, 3] of a z-depth map [H, W] (2DGS's normal from depth): the cross product of
    the central differences of the unprojected pixels, turned towards the camera; zero on the border and
    where a difference spans a pixel without depth."""
    H, W = depth.shape
    v, u = torch.meshgrid(torch.arange(H, dtype=depth.dtype, device=depth.device) + 0.5,
                          torch.arange(W, dtype=depth.dtype, device=depth.device) + 0.5, indexing="ij")
    p = camera.unproject(torch.stack([u, v], -1), depth)  # [H, W, 3]
    n = torch.cross(p[1:-1, 2:] - p[1:-1, :-2], p[2:, 1:-1] - p[:-2, 1:-1], dim=-1)  # [H-2, W-2, 3]
    n = torch.nn.functional.normalize(n, dim=-1)
    view = p[1:-1, 1:-1] - camera.tensor("camera_center", depth.dtype, depth.device)
    n = torch.where(((n * view).sum(-1, keepdim=True) > 0), -n, n)
    ok = (depth[1:-1, 2:] > 0) & (depth[1:-1, :-2] > 0) & (depth[2:, 1:-1] > 0) & (depth[:-2, 1:-1] > 0)
    return torch.nn.functional.pad(n * ok[..., None], (0, 0, 1, 1, 1, 1))


def _check(means, quats, scales, opacities, colors, tangents, n):
    shapes = {"means": (means, (n, 3)), "opacities": (opacities, (n,)), "colors": (colors, (n, 3))}
    if tangents is None:
        shapes.update(quats=(quats, (n, 4)), scales=(scales, (n, 2)))
    else:
        shapes.update(tangents=(tangents, (n, 3, 2)))
    check_shapes("rasterize_surfels", shapes)

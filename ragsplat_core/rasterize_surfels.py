"""Differentiable 2D Gaussian surfel rasterizer (2DGS, Huang et al. SIGGRAPH 2024), several backends.

`rasterize_surfels(means, quats, scales, opacities, colors, camera, background, tangents=None,
backend="auto")` renders surfels with the ray-splat intersection and low-pass filter of 2DGS (see
`raster/surfel_project.py`) and the compositing of `rasterize` (alpha = min(0.99, o G), skipped below 1/255,
front to back by centre depth, a pixel stops before the surfel that would take its transmittance below
1e-4; 16 px tiles; surfels whose centre has camera z < 0.01 culled). Outputs:
- image [H, W, 3] = sum_i w_i c_i + T background, with w_i = alpha_i T_i;
- alpha [H, W, 1] = 1 - T;
- depth [H, W, 1] = sum_i w_i z_i / alpha, z_i the camera z of the pixel's ray-plane intersection with
  surfel i (of its centre where the low-pass filter wins); 0 where nothing was composited;
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

Backends: "torch" (plain PyTorch, autograd, any device: the reference), "cpu" (numba kernels with a
hand-written backward, float32 compositing, CPU tensors), "gsplat" (gsplat's CUDA `rasterization_2dgs`,
optional, quats and scales only; see `_rasterize_gsplat` for where it differs), "auto" (as `rasterize`,
but never gsplat when tangents are given). Gradients flow to means, quats, scales (or tangents),
opacities, colors and background, through every output.
"""

from __future__ import annotations

import torch

from ragsplat_core.camera import Camera
from ragsplat_core.errors import ConfigError
from ragsplat_core.raster.project import NEAR, TILE, bin_tiles
from ragsplat_core.raster.surfel_project import project_surfels, surfel_tangents
from ragsplat_core.rasterize import check_shapes, choose_backend, resolve


def rasterize_surfels(means, quats, scales, opacities, colors, camera: Camera, background, tangents=None,
                      backend: str = "auto"):
    """Renders surfels; returns (image [H, W, 3], alpha [H, W, 1], depth [H, W, 1], meta dict).

    means [N, 3] world; quats [N, 4] (w, x, y, z), normalised here; scales [N, 2] linear; opacities [N] in
    [0, 1]; colors [N, 3]; background [3] (tensor or sequence); tangents [N, 3, 2] scaled world tangents.
    """
    _check(means, quats, scales, opacities, colors, tangents, means.shape[0])
    background = torch.as_tensor(background, dtype=colors.dtype, device=colors.device).reshape(3)
    backend = choose_surfel_backend(backend, means.device, tangents is not None)
    if backend == "gsplat":
        return _rasterize_gsplat(means, quats, scales, opacities, colors, camera, background)
    if tangents is None:
        tangents = surfel_tangents(quats, scales, fast=backend == "cpu")  # [N, 3, 2]
    proj = project_surfels(means, tangents, opacities, camera)
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    bins = bin_tiles(proj, camera.width, camera.height, fast=backend == "cpu")
    if backend == "torch":
        from ragsplat_core.raster.surfel_torch import composite
    else:
        from ragsplat_core.raster.surfel_cpu import composite
    sums, trans, distortion, median = composite(proj, opacities, colors, bins, camera.width, camera.height)
    image, alpha, depth = resolve(sums[..., :3], trans, sums[..., 6], background)
    meta = {"normals": sums[..., 3:6], "median_depth": median[..., None], "distortion": distortion[..., None],
            "means2d": means2d, "radii": proj.radii, "depths": proj.depths, "visible": proj.visible,
            "tiles_touched": bins.tiles_touched, "backend": backend, "width": camera.width,
            "height": camera.height}
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
    view = p[1:-1, 1:-1] - torch.as_tensor(camera.camera_center, dtype=depth.dtype, device=depth.device)
    n = torch.where(((n * view).sum(-1, keepdim=True) > 0), -n, n)
    ok = (depth[1:-1, 2:] > 0) & (depth[1:-1, :-2] > 0) & (depth[2:, 1:-1] > 0) & (depth[:-2, 1:-1] > 0)
    return torch.nn.functional.pad(n * ok[..., None], (0, 0, 1, 1, 1, 1))


def choose_surfel_backend(backend: str, device: torch.device, tangents: bool) -> str:
    """As `rasterize.choose_backend`; gsplat cannot take tangents (it builds surfels from quats and
    scales), so "auto" falls back to torch for them and an explicit "gsplat" is a ConfigError."""
    chosen = choose_backend(backend, device)
    if chosen == "gsplat" and tangents:
        if backend == "gsplat":
            raise ConfigError("backend 'gsplat' takes quats and scales, not tangents; use 'torch' or 'cpu'")
        return "torch"
    return chosen


def _check(means, quats, scales, opacities, colors, tangents, n):
    shapes = {"means": (means, (n, 3)), "opacities": (opacities, (n,)), "colors": (colors, (n, 3))}
    if tangents is None:
        shapes.update(quats=(quats, (n, 4)), scales=(scales, (n, 2)))
    else:
        shapes.update(tangents=(tangents, (n, 3, 2)))
    check_shapes("rasterize_surfels", shapes)


def _rasterize_gsplat(means, quats, scales, opacities, colors, camera, background):
    """gsplat's fused CUDA 2DGS rasterizer (unpacked). Differs from the other backends (gsplat 1.5): alpha
    clamp 0.999; the filter is centred on the centre of the disk's image conic (not the projected centre);
    depth, median depth and distortion use each surfel's centre z (not the per-pixel intersection z);
    `means2d` is that conic centre and its `.grad` gsplat's densification gradient (`gradient_2dgs`).
    Colours go in per camera, [1, N, 3]: gsplat 1.5.3's 2DGS path does not broadcast [N, 3] colours to the
    camera axis before appending depth (seen on an H100)."""
    from gsplat import rasterization_2dgs

    dtype, device = means.dtype, means.device
    viewmat = torch.tensor(camera.w2c, dtype=torch.float32, device=device)[None]  # [1, 4, 4]
    K = torch.tensor(camera.K, dtype=torch.float32, device=device)[None]  # [1, 3, 3]
    scales3 = torch.cat([scales, torch.ones_like(scales[:, :1])], -1)  # [N, 3]; the third is not used
    renders, alphas, normals, _, distortion, median, info = rasterization_2dgs(
        means.float(), quats.float(), scales3.float(), opacities.float(), colors.float()[None], viewmat, K,
        camera.width, camera.height, near_plane=NEAR, packed=False, tile_size=TILE,
        backgrounds=background.float()[None], render_mode="RGB+ED", distloss=True)
    alpha = alphas[0].to(dtype)  # [H, W, 1]
    # gsplat keeps the last surfel's z where the transmittance never reaches 0.5; here that is 0.
    median = torch.where(alpha >= 0.5, median[0].to(dtype), torch.zeros_like(alpha))
    means2d = info["means2d"][0].detach()
    densify = info["gradient_2dgs"]  # [1, N, 2] leaf whose gradient gsplat fills for densification
    if densify.requires_grad:
        densify.register_hook(lambda grad: setattr(means2d, "grad", grad[0]))
    radii = info["radii"][0]
    if radii.dim() == 2:  # per-axis radii [N, 2]
        radii = radii.max(-1).values
    meta = {"normals": normals[0].to(dtype), "median_depth": median, "distortion": distortion[0].to(dtype),
            "means2d": means2d, "radii": radii.to(torch.int32), "depths": info["depths"][0],
            "visible": radii > 0, "tiles_touched": info["tiles_per_gauss"][0], "backend": "gsplat",
            "width": camera.width, "height": camera.height}
    return renders[0, ..., :3].to(dtype), alpha, renders[0, ..., 3:4].to(dtype), meta

"""Reference surfel compositing in plain PyTorch: tile-based, autograd end to end, any device.

The twin of `cpu/surfel_composite.py`, organised like `composite.py` (chunks of tiles with padded lists, each
chunk checkpointed, no sequential loop). Per pixel, front to back, for the surfels of its tile: the
ray-splat intersection and low-pass filter of `surfel_project.py`, then 3DGS compositing
(alpha = min(0.99, o G), skipped below 1/255, stop before the transmittance falls below 1e-4).
Composited per pixel: colour and world normal (per surfel) and the sample's camera z (per pixel and surfel),
plus
- distortion D = sum_i 2 w_i (z_i (1 - T_i) - sum_{j<i} w_j z_j) = 2 sum_{j<i} w_i w_j (z_i - z_j) (gsplat's
  running sums, in plain camera z): sum_{i,j} w_i w_j |z_i - z_j| whenever the samples' depths grow in
  compositing order;
- median depth: z of the sample that takes the transmittance from above 0.5 to 0.5 or below (0 if none).
"""

from __future__ import annotations

import torch

from ragsplat.raster.reference.composite import front_to_back, over_tiles
from ragsplat.raster.reference.project import ALPHA_MAX, ALPHA_MIN, TILE, Bins
from ragsplat.raster.reference.surfel_project import SurfelsProjected

_NOUT = 10  # per pixel: colour (3), normal (3), z sum, transmittance, distortion, median depth


def composite(proj: SurfelsProjected, opacities: torch.Tensor, colors: torch.Tensor, bins: Bins, width: int,
              height: int, centre: bool = False
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(sums [H, W, 7]: colour, normal, z, without background; final transmittance [H, W];
    distortion [H, W]; median depth [H, W]). `centre`: each sample's z is its surfel's centre z, as gsplat
    composites it, instead of the z where the pixel's ray meets the surfel."""
    device = colors.device
    feats = torch.cat([colors, proj.normals.to(colors.dtype)], -1)  # [N, 6]: composited per surfel
    if len(bins.gauss) == 0:  # nothing on screen; the empty sums keep the outputs in the graph
        zero = feats[:0].sum() + proj.means2d[:0].sum() + proj.rays[:0].sum() + proj.depths[:0].sum()
        empty = torch.zeros(height, width, dtype=colors.dtype, device=device) + zero
        return empty[..., None].expand(height, width, 7), empty + 1, empty, empty
    res = over_tiles(_composite_tiles, bins, width, height, proj, opacities, feats, bins, centre)  # [H,W,10]
    return res[..., :7], res[..., 7], res[..., 8], res[..., 9]


def _composite_tiles(tiles, k, px, py, proj, opacities, feats, bins, centre):
    """Composites tiles [t] with lists padded to k. Returns [t, 256, 10] (see `_NOUT`)."""
    slot = torch.arange(k, device=tiles.device)
    first = bins.offsets[tiles]  # [t]
    valid = slot[None, :] < (bins.offsets[tiles + 1] - first)[:, None]  # [t, k]
    gauss = torch.cat([bins.gauss, bins.gauss.new_zeros(1)])  # a valid index for the padding slots
    idx = gauss[torch.where(valid, first[:, None] + slot[None, :], len(bins.gauss))]  # [t, k]
    ty, tx = tiles // bins.tiles_x, tiles % bins.tiles_x
    dtype = feats.dtype
    cu = (tx[:, None] * TILE + px[None, :]).to(dtype) + 0.5  # [t, 256] pixel centres
    cv = (ty[:, None] * TILE + py[None, :]).to(dtype) + 0.5
    m = proj.means2d[idx]  # [t, k, 2]
    ray = proj.rays[idx][:, None]  # [t, 1, k, 7]
    zc = proj.depths[idx][:, None]  # [t, 1, k]
    dx = cu[:, :, None] - m[:, None, :, 0]  # [t, 256, k]
    dy = cv[:, :, None] - m[:, None, :, 1]
    q0 = ray[..., 0] * dx + ray[..., 1] * dy
    q1 = ray[..., 2] * dx + ray[..., 3] * dy
    q2 = ray[..., 4] * dx + ray[..., 5] * dy + ray[..., 6]
    meets = q2 != 0
    q2 = torch.where(meets, q2, torch.ones_like(q2))
    rho3 = torch.where(meets, (q0 / q2) ** 2 + (q1 / q2) ** 2, torch.full_like(q2, torch.inf))
    rho2 = 2 * (dx * dx + dy * dy)
    on_plane = rho3 <= rho2  # the ray-splat intersection, else the low-pass filter
    rho = torch.where(on_plane, rho3, rho2)
    z = zc.expand_as(rho) if centre else torch.where(on_plane, zc * ray[..., 6] / q2, zc)  # [t, 256, k] its z
    alpha = torch.clamp(opacities[idx][:, None, :] * torch.exp(-0.5 * rho), max=ALPHA_MAX)
    use = valid[:, None, :] & (alpha >= ALPHA_MIN)
    trans, before, weights = front_to_back(torch.where(use, alpha, torch.zeros_like(alpha)))
    acc = weights @ feats[idx]  # [t, 256, 6]
    wz = weights * z
    z_before = torch.cumsum(wz, -1) - wz  # sum_{j<i} w_j z_j
    distortion = (2 * weights * (z * (1 - before) - z_before)).sum(-1)
    with torch.no_grad():
        crossing = (before > 0.5) & (trans <= 0.5)
    median = torch.where(crossing, z, torch.zeros_like(z)).sum(-1)
    return torch.cat([acc, wz.sum(-1, keepdim=True), trans[..., -1:], distortion[..., None],
                      median[..., None]], -1)

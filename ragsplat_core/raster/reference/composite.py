"""Reference compositing of 3D Gaussians in plain PyTorch: tile-based, autograd end to end, any device.
Twin of `cpu/composite.py`.

Tiles are processed in chunks with their Gaussian lists padded to the chunk's longest list (tiles are
grouped by list length so the padding stays small); each chunk is checkpointed, so memory does not grow
with the image size times the depth complexity. Per pixel, front to back, as in 3DGS:
alpha_i = min(0.99, o_i exp(power_i)), skipped when below 1/255; the pixel stops before the first Gaussian
that would take its transmittance below 1e-4. Written without a sequential loop: with every alpha in the
list, the inclusive running product of (1 - alpha) stays >= 1e-4 exactly for the Gaussians that 3DGS
composites, because it is non-increasing. On request, the median depth (the camera z of the Gaussian after
which the pixel's transmittance is first <= 0.5) is read off the same running product, without gradient.
"""

from __future__ import annotations

import torch
from torch.utils.checkpoint import checkpoint

from ragsplat.raster.reference.project import ALPHA_MAX, ALPHA_MIN, T_MIN, TILE, Bins, Projected

# Elements of one [tiles, pixels, Gaussians] intermediate per chunk: bounds the reference's memory.
CHUNK_ELEMENTS = 1 << 20


def over_tiles(fn, bins: Bins, width: int, height: int, *args) -> torch.Tensor | tuple[torch.Tensor, ...]:
    """[H, W, C] image of `fn(tiles [t], k, px [256], py [256], *args) -> [t, 256, C]`, which composites the
    tiles `tiles` with their Gaussian lists padded to k (px, py: pixel offsets inside a tile), run over
    chunks of tiles grouped by list length and checkpointed when gradients are on. When `fn` returns a tuple
    of such tensors, so does this (one image each)."""
    n_tiles = bins.tiles_x * bins.tiles_y
    counts = bins.offsets[1:] - bins.offsets[:-1]  # [n_tiles]
    pix = torch.arange(TILE * TILE, device=bins.offsets.device)
    py, px = pix // TILE, pix % TILE  # [256] pixel offsets inside a tile
    by_len = torch.sort(counts, stable=True).indices
    cnt = counts[by_len].tolist()
    out_rows, out_tiles = [], []
    start = 0
    while start < n_tiles:
        # Grow the chunk while its padded size stays in budget (tiles are sorted by list length).
        stop = start + 1
        while stop < n_tiles and (stop + 1 - start) * TILE * TILE * max(cnt[stop], 1) <= CHUNK_ELEMENTS:
            stop += 1
        tiles = by_len[start:stop]  # [t]
        chunk = (tiles, max(cnt[stop - 1], 1), px, py, *args)
        # Recomputed in backward instead of kept: memory stays one chunk's worth of [t, 256, k] tensors.
        res = checkpoint(fn, *chunk, use_reentrant=False, preserve_rng_state=False) \
            if torch.is_grad_enabled() else fn(*chunk)
        multi = isinstance(res, tuple)
        out_rows.append(res if multi else (res,))
        out_tiles.append(tiles)
        start = stop
    order = torch.argsort(torch.cat(out_tiles))  # chunk order -> tile order
    images = []
    for parts in zip(*out_rows):
        res = torch.cat(parts)[order]  # [n_tiles, 256, C]
        res = res.reshape(bins.tiles_y, bins.tiles_x, TILE, TILE, -1).permute(0, 2, 1, 3, 4)
        images.append(res.reshape(bins.tiles_y * TILE, bins.tiles_x * TILE, -1)[:height, :width])
    return tuple(images) if multi else images[0]


def front_to_back(alpha: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Alphas [..., k] in compositing order (0 = skipped) -> (transmittance after each [..., k], before each
    [..., k], weights alpha_i T_i [..., k]), with the alphas from the one that would take the transmittance
    below 1e-4 on dropped (the running product is non-increasing, so no sequential loop is needed)."""
    with torch.no_grad():
        keep = torch.cumprod(1 - alpha, -1) >= T_MIN
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
    trans = torch.cumprod(1 - alpha, -1)  # inclusive
    before = torch.cat([torch.ones_like(trans[..., :1]), trans[..., :-1]], -1)
    return trans, before, alpha * before


def composite(proj: Projected, opacities: torch.Tensor, colors: torch.Tensor, bins: Bins, width: int,
              height: int, median: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor,
                                                          torch.Tensor | None]:
    """(colour sum [H, W, 3] without background, final transmittance [H, W], weighted z sum [H, W], median
    z-depth [H, W] without gradient, 0 where the transmittance stays above 0.5; None unless `median`)."""
    device = colors.device
    if len(bins.gauss) == 0:  # nothing on screen; the empty sum keeps the outputs in the graph
        zero = colors[:0].sum() + proj.means2d[:0].sum()
        return (torch.zeros(height, width, 3, dtype=colors.dtype, device=device) + zero,
                torch.ones(height, width, dtype=colors.dtype, device=device) + zero,
                torch.zeros(height, width, dtype=colors.dtype, device=device) + zero,
                torch.zeros(height, width, dtype=colors.dtype, device=device) if median else None)
    feats = torch.cat([colors, proj.depths[:, None]], -1)  # [N, 4]: what gets composited
    res = over_tiles(_composite_tiles, bins, width, height, proj, opacities, feats, bins, median)
    res, med = res if median else (res, None)  # [H, W, 5], [H, W, 1] or None
    return res[..., :3], res[..., 4], res[..., 3], None if med is None else med[..., 0]


def _composite_tiles(tiles, k, px, py, proj, opacities, feats, bins, median):
    """Composites tiles [t] with lists padded to k. Returns [t, 256, 5]: colour (3), z sum, transmittance;
    with `median`, also the median z [t, 256, 1] as a second tensor outside the graph, so that the gradients
    flow through the same operations with and without it."""
    slot = torch.arange(k, device=tiles.device)
    first = bins.offsets[tiles]  # [t]
    valid = slot[None, :] < (bins.offsets[tiles + 1] - first)[:, None]  # [t, k]
    gauss = torch.cat([bins.gauss, bins.gauss.new_zeros(1)])  # a valid index for the padding slots
    idx = gauss[torch.where(valid, first[:, None] + slot[None, :], len(bins.gauss))]  # [t, k]
    ty, tx = tiles // bins.tiles_x, tiles % bins.tiles_x
    cu = (tx[:, None] * TILE + px[None, :]).to(feats.dtype) + 0.5  # [t, 256] pixel centres
    cv = (ty[:, None] * TILE + py[None, :]).to(feats.dtype) + 0.5
    m = proj.means2d[idx]  # [t, k, 2]
    con = proj.conics[idx]  # [t, k, 3]
    dx = m[:, None, :, 0] - cu[:, :, None]  # [t, 256, k]
    dy = m[:, None, :, 1] - cv[:, :, None]
    ca, cb, cc = con[:, None, :, 0], con[:, None, :, 1], con[:, None, :, 2]
    power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
    alpha = torch.clamp(opacities[idx][:, None, :] * torch.exp(power), max=ALPHA_MAX)
    use = valid[:, None, :] & (power <= 0) & (alpha >= ALPHA_MIN)
    trans, _, weights = front_to_back(torch.where(use, alpha, torch.zeros_like(alpha)))
    acc = weights @ feats[idx]  # [t, 256, 4]
    res = torch.cat([acc, trans[..., -1:]], -1)
    if not median:
        return res
    with torch.no_grad():
        # trans is non-increasing along the list: the count of slots above 0.5 is the first one at or below
        first = (trans > 0.5).sum(-1)  # [t, 256]; k where the pixel never gets there
        z = torch.gather(proj.depths.detach()[idx], 1, first.clamp(max=k - 1))  # [t, 256]
        median = torch.where(first < k, z, torch.zeros_like(z))
    return res, median[..., None]

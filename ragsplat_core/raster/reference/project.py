"""EWA projection of 3D Gaussians and their binning into screen tiles: the reference (plain PyTorch), and the
rasterizer's constants and types, which every backend's kernels read from here.

Semantics follow 3DGS / gsplat ("classic" mode):
- camera-frame mean t = R mu + t_cam; Gaussians with z < NEAR (0.01) are culled;
- 2D covariance J W Sigma W^T J^T + 0.3 I, with J the Jacobian of the pinhole projection at the mean
  (x/z and y/z clamped to 1.3x the field of view before J is formed, as in both reference codes);
- conic = inverse 2D covariance; power = -0.5 (A dx^2 + C dy^2) - B dx dy with (A, B, C) = conic and
  d = mean2d - pixel centre; pixel (i, j) has its centre at (i + 0.5, j + 0.5) (the Camera convention).

Screen extent (gsplat's opacity-aware bound): alpha = o exp(power) >= 1/255 exactly inside the ellipse
d^T conic d <= 2 ln(255 o), whose axis-aligned box has half-widths sqrt(2 ln(255 o) Sigma2d_xx) and
sqrt(2 ln(255 o) Sigma2d_yy). Every pixel outside that box fails the 1/255 test, so the box is a pure
acceleration: renders do not depend on the tile size or on which backend bins them.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from ragsplat.camera import Camera

NEAR = 0.01  # near plane (camera z, metres)
EPS2D = 0.3  # low-pass dilation of the 2D covariance (pixels^2)
ALPHA_MIN = 1.0 / 255.0  # contributions below this are skipped
ALPHA_MAX = 0.99  # alpha clamp
T_MIN = 1e-4  # a pixel stops once its transmittance would fall below this
TILE = 16  # tile edge in pixels
# Rounding guard (pixels) on the screen box: float32 and float64 backends must bin the same pixels.
BOX_PAD = 0.01


class Projected(NamedTuple):
    means2d: torch.Tensor  # [N, 2] pixels (u, v), differentiable
    conics: torch.Tensor  # [N, 3] (A, B, C) of the inverse 2D covariance, differentiable
    depths: torch.Tensor  # [N] camera z, differentiable
    box: torch.Tensor  # [N, 4] int64 inclusive pixel ranges (i0, i1, j0, j1), clipped to the image
    visible: torch.Tensor  # [N] bool: in front, opacity >= 1/255 and the box meets the image
    radii: torch.Tensor  # [N] int32 max half-extent in pixels, 0 where not visible


def project(means: torch.Tensor, covars: torch.Tensor, opacities: torch.Tensor, camera: Camera) -> Projected:
    """EWA-project Gaussians (means [N, 3], world covariances [N, 3, 3], opacities [N]) into `camera`."""
    dtype, device = means.dtype, means.device
    R = camera.tensor("R", dtype, device)
    tc = camera.tensor("t", dtype, device)
    pc = means @ R.T + tc  # [N, 3]
    x, y, z = pc.unbind(-1)
    front = z >= NEAR
    z = torch.where(front, z, torch.ones_like(z))  # culled ones get a harmless z: no inf/NaN in gradients
    fx, fy, cx, cy, W, H = camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height
    u = fx * x / z + cx
    v = fy * y / z + cy
    means2d = torch.stack([u, v], -1)  # [N, 2]

    # Jacobian at the mean with x/z, y/z clamped to 1.3x the field of view (3DGS / gsplat).
    tan_x, tan_y = 0.5 * W / fx, 0.5 * H / fy
    tx = z * torch.clamp(x / z, -(cx / fx + 0.3 * tan_x), (W - cx) / fx + 0.3 * tan_x)
    ty = z * torch.clamp(y / z, -(cy / fy + 0.3 * tan_y), (H - cy) / fy + 0.3 * tan_y)
    zero = torch.zeros_like(z)
    J = torch.stack([fx / z, zero, -fx * tx / (z * z), zero, fy / z, -fy * ty / (z * z)], -1)
    J = J.reshape(-1, 2, 3)
    JW = J @ R  # [N, 2, 3]
    cov2d = JW @ covars @ JW.transpose(1, 2)  # [N, 2, 2]
    a = cov2d[:, 0, 0] + EPS2D
    b = cov2d[:, 0, 1]
    c = cov2d[:, 1, 1] + EPS2D
    det = a * c - b * b
    ok = front & (det > 0) & (opacities >= ALPHA_MIN)
    det = torch.where(ok, det, torch.ones_like(det))
    conics = torch.stack([c / det, -b / det, a / det], -1)  # [N, 3]
    box, visible, radii = screen_box(means2d, a, c, ok, opacities, camera)  # no gradient (decorated)
    return Projected(means2d, conics, pc[:, 2], box, visible, radii)


@torch.no_grad()
def screen_box(means2d, a, c, ok, opacities, camera: Camera):
    """(box [N, 4], visible [N], radii [N]) of `Projected` from the screen positions [N, 2], the dilated 2D
    variances a, c [N] and whether each Gaussian can be drawn at all `ok` [N] (in front, det > 0, opaque
    enough). Shared by `project` and its CPU kernel (`cpu/project.py`)."""
    W, H = camera.width, camera.height
    r2 = 2 * torch.log(torch.clamp(opacities.detach(), min=ALPHA_MIN) * 255.0)
    ex = torch.sqrt(r2 * torch.clamp(a.detach(), min=0)) + BOX_PAD
    ey = torch.sqrt(r2 * torch.clamp(c.detach(), min=0)) + BOX_PAD
    ud, vd = means2d[:, 0].detach(), means2d[:, 1].detach()
    # Pixel i is in the box when its centre i + 0.5 lies in [u - ex, u + ex].
    i0 = torch.ceil(ud - ex - 0.5).clamp(-1, W)
    i1 = torch.floor(ud + ex - 0.5).clamp(-1, W)
    j0 = torch.ceil(vd - ey - 0.5).clamp(-1, H)
    j1 = torch.floor(vd + ey - 0.5).clamp(-1, H)
    ok = ok & torch.isfinite(ex + ey + ud + vd)
    visible = ok & (i1 >= 0) & (i0 <= W - 1) & (j1 >= 0) & (j0 <= H - 1) & (i0 <= i1) & (j0 <= j1)
    box = torch.stack([i0.clamp(0, W - 1), i1.clamp(0, W - 1), j0.clamp(0, H - 1), j1.clamp(0, H - 1)], -1)
    box = torch.where(visible[:, None], box, torch.zeros_like(box)).to(torch.int64)
    radii = torch.where(visible, torch.ceil(torch.maximum(ex, ey)), torch.zeros_like(ex)).to(torch.int32)
    return box, visible, radii


class Bins(NamedTuple):
    gauss: torch.Tensor  # [P] int64 Gaussian index of each (tile, Gaussian) pair, by tile then depth
    offsets: torch.Tensor  # [n_tiles + 1] int64 start of each tile's run in `gauss`
    tiles_touched: torch.Tensor  # [N] int32
    tiles_x: int
    tiles_y: int


def bin_tiles(proj: Projected, width: int, height: int, tile: int = TILE) -> Bins:
    """Lists, per tile of `tile` x `tile` pixels, the visible Gaussians overlapping it, front to back (also
    for surfels: only `box`, `visible` and `depths` are read). Twin of `cpu/project.bin_tiles`."""
    device = proj.box.device
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    box = proj.box
    tx0, tx1 = box[:, 0] // tile, box[:, 1] // tile
    ty0, ty1 = box[:, 2] // tile, box[:, 3] // tile
    nx = tx1 - tx0 + 1
    count = torch.where(proj.visible, nx * (ty1 - ty0 + 1), torch.zeros_like(nx))  # [N]
    gauss = torch.repeat_interleave(torch.arange(len(count), device=device), count)  # [P]
    start = torch.cumsum(count, 0) - count
    local = torch.arange(len(gauss), device=device) - start[gauss]
    tile_id = (ty0[gauss] + local // nx[gauss]) * tiles_x + tx0[gauss] + local % nx[gauss]
    # Front to back inside a tile: a stable sort by depth, then a stable sort by tile.
    rank = torch.empty_like(count)
    rank[torch.sort(proj.depths.detach(), stable=True).indices] = torch.arange(len(count), device=device)
    order = torch.sort(tile_id * max(len(count), 1) + rank[gauss], stable=True).indices
    gauss = gauss[order]
    per_tile = torch.bincount(tile_id, minlength=tiles_x * tiles_y)
    offsets = torch.cat([per_tile.new_zeros(1), torch.cumsum(per_tile, 0)])
    return Bins(gauss, offsets, count.to(torch.int32), tiles_x, tiles_y)

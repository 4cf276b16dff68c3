"""Fast CPU EWA projection and tile lists: `reference/project.py` (its twin). The projection: `project` with
the differentiable outputs (means2d, conics, depths) computed in one numba pass per Gaussian and a
hand-written backward to the means and the world covariances. The boxes, visibility and radii (no gradient)
are then derived exactly as the twin does, from the kernel's screen position and dilated 2D variances. The
tile lists: `bin_tiles`, a counting sort.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from ragsplat.camera import Camera
from ragsplat.raster.reference.project import ALPHA_MIN, EPS2D, NEAR, TILE, Bins, Projected, screen_box

_CHUNK = 1024  # Gaussians per parallel task


@njit(cache=True, inline="always")
def _jacobian(x, y, z, fx, fy, lim, JW, R):
    """JW [2, 3] = J R, J the perspective Jacobian at (x, y, z) with x/z, y/z clamped to `lim`
    (lo_x, hi_x, lo_y, hi_y); returns (tx, ty, inside_x, inside_y)."""
    rx, ry = x / z, y / z
    inside_x, inside_y = lim[0] <= rx <= lim[1], lim[2] <= ry <= lim[3]
    tx = z * min(max(rx, lim[0]), lim[1])
    ty = z * min(max(ry, lim[2]), lim[3])
    j00, j02, j11, j12 = fx / z, -fx * tx / (z * z), fy / z, -fy * ty / (z * z)
    for k in range(3):
        JW[0, k] = j00 * R[0, k] + j02 * R[2, k]
        JW[1, k] = j11 * R[1, k] + j12 * R[2, k]
    return tx, ty, inside_x, inside_y


@njit(cache=True, inline="always")
def _view(means, covars, opacities, n, R, t, fx, fy, lim, JW):
    """What forward and backward both need of Gaussian n: camera coordinates x, y, z0 (and z, the camera z
    with culled ones at a harmless 1), whether it is in front, the clamped Jacobian (JW and
    `_jacobian`'s returns), the dilated 2D covariance entries a, b, c, their determinant and whether it is
    drawn at all (in front, det > 0, opaque enough): one code for both, so they take the same decisions."""
    x = R[0, 0] * means[n, 0] + R[0, 1] * means[n, 1] + R[0, 2] * means[n, 2] + t[0]
    y = R[1, 0] * means[n, 0] + R[1, 1] * means[n, 1] + R[1, 2] * means[n, 2] + t[1]
    z0 = R[2, 0] * means[n, 0] + R[2, 1] * means[n, 1] + R[2, 2] * means[n, 2] + t[2]
    front = z0 >= NEAR
    z = z0 if front else 1.0
    tx, ty, inside_x, inside_y = _jacobian(x, y, z, fx, fy, lim, JW, R)
    c00 = c01 = c11 = 0.0  # cov2d = JW S JW^T, entries (0, 0), (0, 1), (1, 1)
    for i in range(3):
        for j in range(3):
            s = covars[n, i, j]
            c00 += JW[0, i] * s * JW[0, j]
            c01 += JW[0, i] * s * JW[1, j]
            c11 += JW[1, i] * s * JW[1, j]
    a, b, c = c00 + EPS2D, c01, c11 + EPS2D
    det = a * c - b * b
    drawn = front and det > 0 and opacities[n] >= ALPHA_MIN
    return x, y, z0, z, front, tx, ty, inside_x, inside_y, a, b, c, det, drawn


@njit(cache=True, parallel=True)
def _forward(means, covars, opacities, R, t, fx, fy, cx, cy, lim, means2d, conics, depths, ac, ok):
    n_all = means.shape[0]
    for chunk in prange((n_all + _CHUNK - 1) // _CHUNK):
        JW = np.empty((2, 3), dtype=means.dtype)
        for n in range(chunk * _CHUNK, min(n_all, (chunk + 1) * _CHUNK)):
            x, y, z0, z, _, _, _, _, _, a, b, c, det, drawn = _view(means, covars, opacities, n, R, t, fx, fy,
                                                                    lim, JW)
            depths[n] = z0
            means2d[n, 0] = fx * x / z + cx
            means2d[n, 1] = fy * y / z + cy
            ok[n] = drawn
            if not drawn:
                det = 1.0
            conics[n, 0], conics[n, 1], conics[n, 2] = c / det, -b / det, a / det
            ac[n, 0], ac[n, 1] = a, c


@njit(cache=True, parallel=True)
def _backward(means, covars, opacities, R, t, fx, fy, lim, g_means2d, g_conics, g_depths, g_means, g_covars):
    n_all = means.shape[0]
    for chunk in prange((n_all + _CHUNK - 1) // _CHUNK):
        JW = np.empty((2, 3), dtype=means.dtype)
        G = np.empty((2, 2), dtype=means.dtype)
        gJW = np.empty((2, 3), dtype=means.dtype)
        for n in range(chunk * _CHUNK, min(n_all, (chunk + 1) * _CHUNK)):
            x, y, _, z, front, tx, ty, inside_x, inside_y, a, b, c, det, drawn = _view(
                means, covars, opacities, n, R, t, fx, fy, lim, JW)
            gA, gB, gC = g_conics[n, 0], g_conics[n, 1], g_conics[n, 2]
            if drawn:
                inv = 1.0 / det
                g_det = -inv * inv * (gA * c - gB * b + gC * a)
                ga, gb, gc = gC * inv + g_det * c, -gB * inv - 2 * b * g_det, gA * inv + g_det * a
            else:  # det replaced by 1: conics = (c, -b, a)
                ga, gb, gc = gC, -gB, gA
            # cov2d = JW S JW^T with only (0, 0), (0, 1), (1, 1) read: G = [[ga, gb], [0, gc]]
            G[0, 0], G[0, 1], G[1, 0], G[1, 1] = ga, gb, 0.0, gc
            for i in range(3):
                for j in range(3):  # g_S = JW^T G JW
                    g_covars[n, i, j] = (JW[0, i] * (G[0, 0] * JW[0, j] + G[0, 1] * JW[1, j])
                                         + JW[1, i] * (G[1, 0] * JW[0, j] + G[1, 1] * JW[1, j]))
            for r in range(2):  # g_JW = G JW S^T + G^T JW S
                for k in range(3):
                    s = 0.0
                    for m in range(3):
                        jsT = JW[0, m] * covars[n, k, m] * G[r, 0] + JW[1, m] * covars[n, k, m] * G[r, 1]
                        js = JW[0, m] * covars[n, m, k] * G[0, r] + JW[1, m] * covars[n, m, k] * G[1, r]
                        s += jsT + js
                    gJW[r, k] = s
            # JW = J R: g_J = g_JW R^T (only the non-zero entries of J matter)
            gj00 = gJW[0, 0] * R[0, 0] + gJW[0, 1] * R[0, 1] + gJW[0, 2] * R[0, 2]
            gj02 = gJW[0, 0] * R[2, 0] + gJW[0, 1] * R[2, 1] + gJW[0, 2] * R[2, 2]
            gj11 = gJW[1, 0] * R[1, 0] + gJW[1, 1] * R[1, 1] + gJW[1, 2] * R[1, 2]
            gj12 = gJW[1, 0] * R[2, 0] + gJW[1, 1] * R[2, 1] + gJW[1, 2] * R[2, 2]
            z2, z3 = z * z, z * z * z
            gz = -gj00 * fx / z2 + gj02 * 2 * fx * tx / z3 - gj11 * fy / z2 + gj12 * 2 * fy * ty / z3
            gtx, gty = -gj02 * fx / z2, -gj12 * fy / z2
            gx = gy = 0.0
            # tx = z clamp(x / z): x inside the limits, else z * limit
            if inside_x:
                gx += gtx
            else:
                gz += gtx * tx / z
            if inside_y:
                gy += gty
            else:
                gz += gty * ty / z
            gu, gv = g_means2d[n, 0], g_means2d[n, 1]
            gx += gu * fx / z
            gy += gv * fy / z
            gz += -gu * fx * x / z2 - gv * fy * y / z2
            gz0 = g_depths[n] + (gz if front else 0.0)
            for k in range(3):
                g_means[n, k] = R[0, k] * gx + R[1, k] * gy + R[2, k] * gz0


def _arr(t: torch.Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


def _camera(camera: Camera, dtype):
    R = np.ascontiguousarray(camera.R, dtype=dtype)
    t = np.ascontiguousarray(camera.t, dtype=dtype)
    fx, fy, cx, cy, W, H = camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height
    tan_x, tan_y = 0.5 * W / fx, 0.5 * H / fy
    lim = np.array([-(cx / fx + 0.3 * tan_x), (W - cx) / fx + 0.3 * tan_x,
                    -(cy / fy + 0.3 * tan_y), (H - cy) / fy + 0.3 * tan_y], dtype=dtype)
    return R, t, lim


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, covars, opacities, camera):
        n, dtype = len(means), means.dtype
        means2d, conics, depths, ac = (torch.empty(n, 2, dtype=dtype), torch.empty(n, 3, dtype=dtype),
                                       torch.empty(n, dtype=dtype), torch.empty(n, 2, dtype=dtype))
        ok = torch.empty(n, dtype=torch.bool)
        R, t, lim = _camera(camera, _arr(means).dtype)
        _forward(_arr(means), _arr(covars), _arr(opacities), R, t, camera.fx, camera.fy, camera.cx, camera.cy,
                 lim, means2d.numpy(), conics.numpy(), depths.numpy(), ac.numpy(), ok.numpy())
        ctx.save_for_backward(means, covars, opacities)
        ctx.camera = camera
        ctx.mark_non_differentiable(ac, ok)
        return means2d, conics, depths, ac, ok

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, _g_ac, _g_ok):
        means, covars, opacities = ctx.saved_tensors
        cam = ctx.camera
        R, t, lim = _camera(cam, _arr(means).dtype)
        g_means, g_covars = torch.empty_like(means), torch.empty_like(covars)
        zeros = torch.zeros((), dtype=means.dtype)
        _backward(_arr(means), _arr(covars), _arr(opacities), R, t, cam.fx, cam.fy, lim,
                  _arr(g_means2d if g_means2d is not None else zeros.expand(len(means), 2)),
                  _arr(g_conics if g_conics is not None else zeros.expand(len(means), 3)),
                  _arr(g_depths if g_depths is not None else zeros.expand(len(means))),
                  g_means.numpy(), g_covars.numpy())
        return g_means, g_covars, None, None


def project(means: torch.Tensor, covars: torch.Tensor, opacities: torch.Tensor, camera: Camera) -> Projected:
    """`reference/project.project` for CPU tensors (the gradient flows to the means and the covariances)."""
    means2d, conics, depths, ac, ok = _Project.apply(means, covars, opacities, camera)
    box, visible, radii = screen_box(means2d, ac[:, 0], ac[:, 1], ok, opacities, camera)
    return Projected(means2d, conics, depths, box, visible, radii)


@njit(cache=True)
def _bins(box, visible, order, tiles_x, tiles_y, tile):
    """Counting sort of the (tile, Gaussian) pairs: per tile, the Gaussians in `order` (front to back)."""
    n = box.shape[0]
    count = np.zeros(n, np.int32)
    offsets = np.zeros(tiles_x * tiles_y + 1, np.int64)  # the boxes are clipped to the image
    for g in range(n):
        if visible[g]:
            tx0, tx1, ty0, ty1 = box[g, 0] // tile, box[g, 1] // tile, box[g, 2] // tile, box[g, 3] // tile
            count[g] = (tx1 - tx0 + 1) * (ty1 - ty0 + 1)
            for ty in range(ty0, ty1 + 1):
                for tx in range(tx0, tx1 + 1):
                    offsets[ty * tiles_x + tx + 1] += 1
    offsets = np.cumsum(offsets)
    cursor = offsets[:-1].copy()
    gauss = np.empty(offsets[-1], np.int64)
    for g in order:
        if visible[g]:
            for ty in range(box[g, 2] // tile, box[g, 3] // tile + 1):
                for tx in range(box[g, 0] // tile, box[g, 1] // tile + 1):
                    t = ty * tiles_x + tx
                    gauss[cursor[t]] = g
                    cursor[t] += 1
    return gauss, offsets, count


def bin_tiles(proj: Projected, width: int, height: int, tile: int = TILE) -> Bins:
    """`reference/project.bin_tiles` (its twin) in O(N log N + pairs): the Gaussians sorted by depth once,
    then dealt to their tiles in that order, instead of a sort of every (tile, Gaussian) pair."""
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    order = np.argsort(proj.depths.detach().numpy(), kind="stable")  # ties by index, as torch's stable sort
    gauss, offsets, count = _bins(np.ascontiguousarray(proj.box.numpy()), proj.visible.numpy(), order,
                                  tiles_x, tiles_y, tile)
    return Bins(torch.from_numpy(gauss), torch.from_numpy(offsets), torch.from_numpy(count), tiles_x, tiles_y)

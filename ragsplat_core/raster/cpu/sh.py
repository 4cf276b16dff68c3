"""Fast CPU view colours: real spherical harmonics up to degree 3 in one numba pass per Gaussian, with a
hand-written backward to the coefficients and the means (through the view direction).

Same basis, constants and clamp as the PyTorch twin `gaussians.colors_for_view` (3DGS / gsplat). Per step
the twin is about 50 small tensor ops forward and as many backward over [N] arrays; here each Gaussian is
read once forward and once backward.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

from ragsplat import gaussians
from ragsplat.gaussians import SH_C0, SH_C1, SH_C2, SH_C3

_C2 = np.array(SH_C2)
_C3 = np.array(SH_C3)


@njit(cache=True, inline="always")
def _basis(x, y, z, degree, b):
    """b[:(degree + 1)^2] = the basis at the unit direction (x, y, z)."""
    b[0] = SH_C0
    if degree >= 1:
        b[1] = -SH_C1 * y
        b[2] = SH_C1 * z
        b[3] = -SH_C1 * x
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        b[4] = _C2[0] * x * y
        b[5] = _C2[1] * y * z
        b[6] = _C2[2] * (2 * zz - xx - yy)
        b[7] = _C2[3] * x * z
        b[8] = _C2[4] * (xx - yy)
        if degree >= 3:
            b[9] = _C3[0] * y * (3 * xx - yy)
            b[10] = _C3[1] * x * y * z
            b[11] = _C3[2] * y * (4 * zz - xx - yy)
            b[12] = _C3[3] * z * (2 * zz - 3 * xx - 3 * yy)
            b[13] = _C3[4] * x * (4 * zz - xx - yy)
            b[14] = _C3[5] * z * (xx - yy)
            b[15] = _C3[6] * x * (xx - 3 * yy)


@njit(cache=True, inline="always")
def _basis_grad(x, y, z, degree, gb):
    """d(sum_k gb[k] b_k) / d(x, y, z) for the basis weights gb."""
    dx = -SH_C1 * gb[3]
    dy = -SH_C1 * gb[1]
    dz = SH_C1 * gb[2]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        dx += _C2[0] * y * gb[4] - 2 * _C2[2] * x * gb[6] + _C2[3] * z * gb[7] + 2 * _C2[4] * x * gb[8]
        dy += _C2[0] * x * gb[4] + _C2[1] * z * gb[5] - 2 * _C2[2] * y * gb[6] - 2 * _C2[4] * y * gb[8]
        dz += _C2[1] * y * gb[5] + 4 * _C2[2] * z * gb[6] + _C2[3] * x * gb[7]
        if degree >= 3:
            dx += (_C3[0] * 6 * x * y * gb[9] + _C3[1] * y * z * gb[10] - _C3[2] * 2 * x * y * gb[11]
                   - _C3[3] * 6 * x * z * gb[12] + _C3[4] * (4 * zz - 3 * xx - yy) * gb[13]
                   + _C3[5] * 2 * x * z * gb[14] + _C3[6] * 3 * (xx - yy) * gb[15])
            dy += (_C3[0] * 3 * (xx - yy) * gb[9] + _C3[1] * x * z * gb[10]
                   + _C3[2] * (4 * zz - xx - 3 * yy) * gb[11] - _C3[3] * 6 * y * z * gb[12]
                   - _C3[4] * 2 * x * y * gb[13] - _C3[5] * 2 * y * z * gb[14] - _C3[6] * 6 * x * y * gb[15])
            dz += (_C3[1] * x * y * gb[10] + _C3[2] * 8 * y * z * gb[11]
                   + _C3[3] * (6 * zz - 3 * xx - 3 * yy) * gb[12]
                   + _C3[4] * 8 * x * z * gb[13] + _C3[5] * (xx - yy) * gb[14])
    return dx, dy, dz


@njit(cache=True, inline="always")
def _coeff(sh0, shN, n, k, c):
    return sh0[n, 0, c] if k == 0 else shN[n, k - 1, c]


_CHUNK = 512  # Gaussians per parallel task: the scratch basis is allocated once per task, not per Gaussian


@njit(cache=True, parallel=True)
def _forward(sh0, shN, means, center, degree, out):
    """out [N, 3] = max(0, sum_k b_k(dir) coeff_k + 0.5), dir = unit(means - center), coeff_0 = sh0[:, 0],
    coeff_k = shN[:, k - 1]."""
    k_used = (degree + 1) * (degree + 1)
    n_all = means.shape[0]
    for chunk in prange((n_all + _CHUNK - 1) // _CHUNK):
        b = np.empty(16, dtype=sh0.dtype)
        for n in range(chunk * _CHUNK, min(n_all, (chunk + 1) * _CHUNK)):
            vx, vy, vz = means[n, 0] - center[0], means[n, 1] - center[1], means[n, 2] - center[2]
            inv = 1 / np.sqrt(vx * vx + vy * vy + vz * vz)
            _basis(vx * inv, vy * inv, vz * inv, degree, b)
            for c in range(3):
                s = b[0] * sh0[n, 0, c]
                for k in range(1, k_used):
                    s += b[k] * shN[n, k - 1, c]
                out[n, c] = max(s + 0.5, 0.0)


@njit(cache=True, parallel=True)
def _backward(sh0, shN, means, center, degree, g_colors, g_sh0, g_shN, g_means):
    """Gradients of the loss to sh0, shN (0 for the unused degrees) and the means, from those to the
    colours. The clamp passes the gradient where the unclamped colour is >= 0 (torch's clamp_min)."""
    k_used = (degree + 1) * (degree + 1)
    n_all = means.shape[0]
    for chunk in prange((n_all + _CHUNK - 1) // _CHUNK):
        b = np.empty(16, dtype=sh0.dtype)
        gb = np.empty(16, dtype=sh0.dtype)
        for n in range(chunk * _CHUNK, min(n_all, (chunk + 1) * _CHUNK)):
            vx, vy, vz = means[n, 0] - center[0], means[n, 1] - center[1], means[n, 2] - center[2]
            inv = 1 / np.sqrt(vx * vx + vy * vy + vz * vz)
            x, y, z = vx * inv, vy * inv, vz * inv
            _basis(x, y, z, degree, b)
            s0, s1, s2 = b[0] * sh0[n, 0, 0], b[0] * sh0[n, 0, 1], b[0] * sh0[n, 0, 2]
            for k in range(1, k_used):
                s0 += b[k] * shN[n, k - 1, 0]
                s1 += b[k] * shN[n, k - 1, 1]
                s2 += b[k] * shN[n, k - 1, 2]
            g0 = g_colors[n, 0] if s0 + 0.5 >= 0 else 0.0
            g1 = g_colors[n, 1] if s1 + 0.5 >= 0 else 0.0
            g2 = g_colors[n, 2] if s2 + 0.5 >= 0 else 0.0
            g_sh0[n, 0, 0], g_sh0[n, 0, 1], g_sh0[n, 0, 2] = b[0] * g0, b[0] * g1, b[0] * g2
            gb[0] = sh0[n, 0, 0] * g0 + sh0[n, 0, 1] * g1 + sh0[n, 0, 2] * g2
            for k in range(1, k_used):
                g_shN[n, k - 1, 0], g_shN[n, k - 1, 1], g_shN[n, k - 1, 2] = b[k] * g0, b[k] * g1, b[k] * g2
                gb[k] = shN[n, k - 1, 0] * g0 + shN[n, k - 1, 1] * g1 + shN[n, k - 1, 2] * g2
            for k in range(k_used, shN.shape[1] + 1):
                g_shN[n, k - 1, 0], g_shN[n, k - 1, 1], g_shN[n, k - 1, 2] = 0, 0, 0
            dx, dy, dz = _basis_grad(x, y, z, degree, gb)
            dot = dx * x + dy * y + dz * z  # the unit direction's Jacobian: (I - d d^T) / |v|
            g_means[n, 0] = (dx - dot * x) * inv
            g_means[n, 1] = (dy - dot * y) * inv
            g_means[n, 2] = (dz - dot * z) * inv


def _arr(t: torch.Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


class _ViewColors(torch.autograd.Function):
    @staticmethod
    def forward(ctx, sh0, shN, means, center, degree):
        out = torch.empty(means.shape[0], 3, dtype=sh0.dtype)
        _forward(_arr(sh0), _arr(shN), _arr(means), _arr(center.to(means.dtype)), degree, out.numpy())
        ctx.save_for_backward(sh0, shN, means, center)
        ctx.degree = degree
        return out

    @staticmethod
    def backward(ctx, g_colors):
        sh0, shN, means, center = ctx.saved_tensors
        g_sh0, g_shN, g_means = torch.empty_like(sh0), torch.empty_like(shN), torch.empty_like(means)
        _backward(_arr(sh0), _arr(shN), _arr(means), _arr(center.to(means.dtype)), ctx.degree,
                  _arr(g_colors), g_sh0.numpy(), g_shN.numpy(), g_means.numpy())
        return g_sh0, g_shN, g_means, None, None


def view_colors(sh0: torch.Tensor, shN: torch.Tensor, means: torch.Tensor, center: torch.Tensor,
                degree: int) -> torch.Tensor:
    """RGB [N, 3] of SH coefficients sh0 [N, 1, 3], shN [N, K - 1, 3] (K >= (degree + 1)^2, degree 1..3) seen
    from `center` [3], clamped >= 0: `gaussians.colors_for_view` on CPU tensors (same dtype)."""
    if not 1 <= degree <= 3 or shN.shape[1] + 1 < (degree + 1) ** 2:
        raise ValueError(f"degree {degree} with {shN.shape[1] + 1} coefficients per channel")
    return _ViewColors.apply(sh0, shN, means, center, degree)


def colors_for_view(splats, camera_center: torch.Tensor, degree: int) -> torch.Tensor:
    """`gaussians.colors_for_view` (same arguments) for CPU tensors: the kernel from degree 1 on."""
    if degree == 0 or "shN" not in splats:  # no direction: the twin's shortcut is all there is
        return gaussians.colors_for_view(splats, camera_center, degree)
    return view_colors(splats["sh0"], splats["shN"], splats["means"], camera_center, degree)

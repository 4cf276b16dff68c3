"""Fast CPU shapes of Gaussians: the world covariance R S S^T R^T [N, 3, 3] of a 3D Gaussian and the scaled
tangents R[:, :2] diag(s) [N, 3, 2] of a surfel, from quaternions (w, x, y, z, any non-zero norm) and linear
scales, each in one numba pass with a hand-written backward to the quaternions and the scales.

Twins: `gaussians.covariance` and `gaussians.surfel_tangents` (PyTorch autograd).
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange

_CHUNK = 1024  # Gaussians per parallel task


@njit(cache=True, inline="always")
def _rotation(quats, n, R):
    """R [3, 3] of quaternion n, normalised; returns the unit quaternion and the norm."""
    w, x, y, z = quats[n, 0], quats[n, 1], quats[n, 2], quats[n, 3]
    norm = np.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / norm, x / norm, y / norm, z / norm
    R[0, 0], R[0, 1], R[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    R[1, 0], R[1, 1], R[1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    R[2, 0], R[2, 1], R[2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    return w, x, y, z, norm


@njit(cache=True, inline="always")
def _rotation_backward(w, x, y, z, norm, gR, g_quats, n):
    """g_quats[n] from dL/dR [3, 3] through R(unit q) and the normalisation q / |q|."""
    gw = 2 * (-z * gR[0, 1] + y * gR[0, 2] + z * gR[1, 0] - x * gR[1, 2] - y * gR[2, 0] + x * gR[2, 1])
    gx = 2 * (y * gR[0, 1] + z * gR[0, 2] + y * gR[1, 0] - 2 * x * gR[1, 1] - w * gR[1, 2] + z * gR[2, 0]
              + w * gR[2, 1] - 2 * x * gR[2, 2])
    gy = 2 * (-2 * y * gR[0, 0] + x * gR[0, 1] + w * gR[0, 2] + x * gR[1, 0] + z * gR[1, 2] - w * gR[2, 0]
              + z * gR[2, 1] - 2 * y * gR[2, 2])
    gz = 2 * (-2 * z * gR[0, 0] - w * gR[0, 1] + x * gR[0, 2] + w * gR[1, 0] - 2 * z * gR[1, 1] + y * gR[1, 2]
              + x * gR[2, 0] + y * gR[2, 1])
    dot = gw * w + gx * x + gy * y + gz * z  # (I - u u^T) / |q|
    g_quats[n, 0] = (gw - dot * w) / norm
    g_quats[n, 1] = (gx - dot * x) / norm
    g_quats[n, 2] = (gy - dot * y) / norm
    g_quats[n, 3] = (gz - dot * z) / norm


@njit(cache=True, parallel=True)
def _shape_forward(quats, scales, cols, out):
    """cols == 3: out [N, 3, 3] = M M^T; cols == 2: out [N, 3, 2] = M; M = R[:, :cols] diag(scales)."""
    n_all = quats.shape[0]
    for chunk in prange((n_all + _CHUNK - 1) // _CHUNK):
        R = np.empty((3, 3), dtype=quats.dtype)
        M = np.empty((3, 3), dtype=quats.dtype)
        for n in range(chunk * _CHUNK, min(n_all, (chunk + 1) * _CHUNK)):
            _rotation(quats, n, R)
            for i in range(3):
                for j in range(cols):
                    M[i, j] = R[i, j] * scales[n, j]
            if cols == 2:
                for i in range(3):
                    out[n, i, 0], out[n, i, 1] = M[i, 0], M[i, 1]
            else:
                for i in range(3):
                    for k in range(3):
                        out[n, i, k] = M[i, 0] * M[k, 0] + M[i, 1] * M[k, 1] + M[i, 2] * M[k, 2]


@njit(cache=True, parallel=True)
def _shape_backward(quats, scales, cols, g_out, g_quats, g_scales):
    """g_quats [N, 4], g_scales [N, cols] from dL/d(out) of `_shape_forward`."""
    n_all = quats.shape[0]
    for chunk in prange((n_all + _CHUNK - 1) // _CHUNK):
        R = np.empty((3, 3), dtype=quats.dtype)
        gM = np.empty((3, 3), dtype=quats.dtype)
        gR = np.zeros((3, 3), dtype=quats.dtype)
        for n in range(chunk * _CHUNK, min(n_all, (chunk + 1) * _CHUNK)):
            w, x, y, z, norm = _rotation(quats, n, R)
            if cols == 2:
                for i in range(3):
                    gM[i, 0], gM[i, 1] = g_out[n, i, 0], g_out[n, i, 1]
            else:  # d(M M^T) = dM M^T + M dM^T: gM = (G + G^T) M
                for i in range(3):
                    for j in range(3):
                        s = 0.0
                        for k in range(3):
                            s += (g_out[n, i, k] + g_out[n, k, i]) * R[k, j] * scales[n, j]
                        gM[i, j] = s
            for j in range(cols):
                gs = 0.0
                for i in range(3):
                    gs += gM[i, j] * R[i, j]
                    gR[i, j] = gM[i, j] * scales[n, j]
                g_scales[n, j] = gs
            _rotation_backward(w, x, y, z, norm, gR, g_quats, n)


def _arr(t: torch.Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


class _Shape(torch.autograd.Function):
    @staticmethod
    def forward(ctx, quats, scales, cols):
        out = torch.empty(len(quats), 3, cols, dtype=quats.dtype)
        _shape_forward(_arr(quats), _arr(scales), cols, out.numpy())
        ctx.save_for_backward(quats, scales)
        ctx.cols = cols
        return out

    @staticmethod
    def backward(ctx, g_out):
        quats, scales = ctx.saved_tensors
        g_quats, g_scales = torch.empty_like(quats), torch.empty_like(scales)
        _shape_backward(_arr(quats), _arr(scales), ctx.cols, _arr(g_out), g_quats.numpy(), g_scales.numpy())
        return g_quats, g_scales, None


def covariance_cpu(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """[N, 3, 3] world covariances of CPU quaternions [N, 4] and linear scales [N, 3]
    (`gaussians.covariance`)."""
    return _Shape.apply(quats, scales, 3)


def tangents_cpu(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """[N, 3, 2] scaled tangents of CPU quaternions [N, 4] and linear scales [N, 2]
    (`gaussians.surfel_tangents`)."""
    return _Shape.apply(quats, scales, 2)

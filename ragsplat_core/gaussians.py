"""Gaussian scene parameters, their initialisation, rotation, covariance and surfel tangents, and
spherical-harmonics colour, in plain PyTorch (autograd, any device). The `cpu` backend's numba kernels are
twins of `covariance`, `surfel_tangents` and `colors_for_view` (`raster/cpu/`, chosen in
`raster/backends.py`); this module imports nothing of the rasterizer.

Parameters live in a `torch.nn.ParameterDict` (the layout gsplat uses), keyed by
- `means`     [N, 3]  world position (metres; the TRUE position for underwater Gaussians)
- `scales`    [N, 3]  log of the standard deviations along the local axes
- `quats`     [N, 4]  rotation (w, x, y, z); kept unnormalised in the optimiser, normalised on use
- `opacities` [N]     logit of the opacity
- `sh0`       [N, 1, 3] degree-0 SH coefficient
- `shN`       [N, K-1, 3] higher-order coefficients, K = (degree + 1)^2 (absent for degree 0)
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np
import torch

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
         0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)
PARAM_NAMES = ("means", "scales", "quats", "opacities", "sh0", "shN")


class Water(Protocol):
    """What `init_points` reads of a `water_surface.WaterSurface` (named by its shape, because refraction
    imports this module)."""

    n: float

    def depth(self, points: torch.Tensor) -> torch.Tensor: ...


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """Quaternions [N, 4] (w, x, y, z), any non-zero norm -> rotation matrices [N, 3, 3]."""
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(-1, 3, 3)


def covariance(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """World covariance R S S R^T [N, 3, 3] from quaternions [N, 4] and linear scales [N, 3]."""
    M = quat_to_rotmat(quats) * scales[:, None, :]  # R diag(s)
    return M @ M.transpose(1, 2)


def surfel_tangents(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """Scaled world tangents [N, 3, 2] (columns s_u t_u, s_v t_v) of surfels from quaternions [N, 4]
    (w, x, y, z) and linear scales [N, 2]: the first two columns of the rotation (2DGS; the third is the
    normal)."""
    return quat_to_rotmat(quats)[:, :, :2] * scales[:, None, :]


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


def rgb_to_sh(rgb: torch.Tensor) -> torch.Tensor:
    """Degree-0 coefficient whose evaluation gives `rgb` (the 3DGS convention: colour = C0 * sh0 + 0.5)."""
    return (rgb - 0.5) / SH_C0


def sh_degree(splats: torch.nn.ParameterDict) -> int:
    return 0 if "shN" not in splats else round(math.sqrt(splats["shN"].shape[1] + 1)) - 1


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """Real SH basis up to `degree` (0..3) at unit directions [N, 3] -> [N, (degree + 1)^2].

    Same basis, signs and constants as 3DGS / gsplat, so exported PLYs render identically in their viewers.
    """
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy = x * x, y * y, z * z, x * y
        out += [SH_C2[0] * xy, SH_C2[1] * y * z, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * x * z,
                SH_C2[4] * (xx - yy)]
    if degree >= 3:
        out += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * xy * z, SH_C3[2] * y * (4 * zz - xx - yy),
                SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
                SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy)]
    return torch.stack(out, -1)


def eval_sh(degree: int, coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """SH of `degree` with coefficients [N, K >= (degree+1)^2, 3] at unit directions [N, 3] -> [N, 3]."""
    if degree == 0:  # no direction dependence: skip the basis (and its gradient to the means)
        return SH_C0 * coeffs[:, 0]
    # one contraction instead of 16 multiply-adds: fewer, larger kernels forward and backward
    return torch.einsum("nk,nkc->nc", sh_basis(degree, dirs), coeffs[:, :num_sh_bases(degree)])


def colors_for_view(splats: torch.nn.ParameterDict, camera_center: torch.Tensor, degree: int) -> torch.Tensor:
    """RGB [N, 3] seen from `camera_center` [3], using SH up to `degree` (the active degree), clamped >= 0.

    The direction is from the camera to the TRUE mean, evaluated before the refraction transform (the
    refraction contract takes per-view RGB). Under water the ray that actually leaves the Gaussian is the
    refracted one, steeper than this direction; with degree 0 (or the low degrees early in training)
    the difference does not arise.
    """
    if degree == 0 or "shN" not in splats:
        return (SH_C0 * splats["sh0"][:, 0] + 0.5).clamp_min(0.0)
    coeffs = torch.cat([splats["sh0"], splats["shN"]], 1)  # [N, K, 3]
    dirs = torch.nn.functional.normalize(splats["means"] - camera_center, dim=-1)  # [N, 3]
    return (eval_sh(degree, coeffs, dirs) + 0.5).clamp_min(0.0)


def _make(means: torch.Tensor, log_scales: torch.Tensor, rgb: torch.Tensor, opacity: float,
          degree: int) -> torch.nn.ParameterDict:
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be 0..3, got {degree}")
    if not 0.0 < opacity < 1.0:
        raise ValueError(f"initial opacity must be in (0, 1), got {opacity}")
    n = means.shape[0]
    quats = torch.zeros(n, 4, dtype=means.dtype, device=means.device)
    quats[:, 0] = 1.0
    params = {
        "means": means,
        "scales": log_scales,
        "quats": quats,
        "opacities": torch.full((n,), math.log(opacity / (1 - opacity)), dtype=means.dtype,
                                device=means.device),
        "sh0": rgb_to_sh(rgb)[:, None, :],
    }
    if degree > 0:
        params["shN"] = torch.zeros(n, num_sh_bases(degree) - 1, 3, dtype=means.dtype, device=means.device)
    return torch.nn.ParameterDict({k: torch.nn.Parameter(v.contiguous()) for k, v in params.items()})


def init_grid(xmin: float, xmax: float, ymin: float, ymax: float, z: float, spacing: float, degree: int = 3,
              opacity: float = 0.1, rgb: float = 0.5, dtype=torch.float32,
              device=None) -> torch.nn.ParameterDict:
    """Gaussians on a regular horizontal grid at height `z` (the paper's synthetic setup: the bed depth).

    Cell centres at `spacing` over [xmin, xmax] x [ymin, ymax]; isotropic scale = spacing, grey colour.
    """
    if not (spacing > 0 and xmax > xmin and ymax > ymin):
        raise ValueError(f"grid needs spacing > 0 and a non-empty box, got {spacing}, "
                         f"[{xmin}, {xmax}] x [{ymin}, {ymax}]")
    nx, ny = max(1, round((xmax - xmin) / spacing)), max(1, round((ymax - ymin) / spacing))
    xs = xmin + (torch.arange(nx, dtype=torch.float64) + 0.5) * (xmax - xmin) / nx
    ys = ymin + (torch.arange(ny, dtype=torch.float64) + 0.5) * (ymax - ymin) / ny
    gx, gy = torch.meshgrid(xs, ys, indexing="ij")
    means = torch.stack([gx.reshape(-1), gy.reshape(-1), torch.full_like(gx.reshape(-1), z)], -1)
    means = means.to(dtype=dtype, device=device)  # [N, 3]
    log_scales = torch.full_like(means, math.log(spacing))
    return _make(means, log_scales, torch.full_like(means, rgb), opacity, degree)


def init_points(points: torch.Tensor, rgb: torch.Tensor, water: Water | None, degree: int = 3,
                opacity: float = 0.1, depth_scale: float | None = None) -> torch.nn.ParameterDict:
    """Gaussians at the points [N, 3] of a point cloud with colours [N, 3] in [0, 1].

    A cloud reconstructed through the water (MVS on refracted images) sits at apparent depths, about the true
    depth / n; photogrammetric practice multiplies the underwater depths by n. `depth_scale` (default
    `water.n`; 1 to keep the cloud as is) multiplies the depths of the points below the surface. Scales are
    the mean distance to the 3 nearest neighbours (as 3DGS), computed with scipy on the CPU.
    """
    from scipy.spatial import cKDTree

    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] < 2 or rgb.shape != points.shape:
        raise ValueError(f"need >= 2 points [N, 3] and colours [N, 3], got {tuple(points.shape)}, "
                         f"{tuple(rgb.shape)}")
    if not torch.isfinite(points).all():
        raise ValueError("point cloud has non-finite coordinates")
    means = points.detach().clone()
    if water is not None:
        k = water.n if depth_scale is None else depth_scale
        d = water.depth(means.double()).to(means)  # [N] vertical depth below the surface
        below = d > 0
        means[below, 2] += d[below] * (1 - k)
    pts = means.detach().cpu().double().numpy()
    k_nn = min(4, len(pts))
    dist, _ = cKDTree(pts).query(pts, k=k_nn)
    mean_d = np.maximum(dist[:, 1:].mean(1), 1e-7)
    log_scales = torch.from_numpy(np.log(mean_d)).to(means)[:, None].expand(-1, 3)
    return _make(means, log_scales, rgb.detach().to(means).clamp(0, 1), opacity, degree)


def activated(splats: torch.nn.ParameterDict) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(scales [N, 3] linear, quats [N, 4] unit, opacities [N] in (0, 1)): what the renderer takes."""
    return (torch.exp(splats["scales"]), torch.nn.functional.normalize(splats["quats"], dim=-1),
            torch.sigmoid(splats["opacities"]))

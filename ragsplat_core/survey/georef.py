"""Georeferencing a structure-from-motion model: the similarity transform x' = s R x + t that takes model
coordinates to the surveyor's frame, fitted to corresponding points (camera centres against the drone's RTK
positions, or ground control points), robust to a few wrong correspondences. numpy only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Similarity:
    """x' = scale * R @ x + t."""

    scale: float
    R: np.ndarray  # [3, 3]
    t: np.ndarray  # [3]

    def apply(self, x: np.ndarray) -> np.ndarray:  # [N, 3] -> [N, 3]
        return self.scale * np.asarray(x, float) @ self.R.T + self.t


def fit_similarity(src: np.ndarray, dst: np.ndarray) -> Similarity:
    """Least-squares similarity with dst ~ s R src + t for src, dst [N, 3], N >= 3 not collinear (Umeyama,
    1991: the rotation from the SVD of the cross-covariance, a reflection excluded)."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    sign = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    R = U @ sign @ Vt
    var = (a * a).sum() / len(src)
    scale = float(np.trace(np.diag(S) @ sign) / var) if var > 0 else 1.0
    return Similarity(scale, R, md - scale * R @ ms)


def ransac_similarity(src: np.ndarray, dst: np.ndarray, threshold: float, iterations: int = 500,
                      seed: int = 0) -> tuple[Similarity, np.ndarray]:
    """(similarity, inlier mask [N]): the transform of three correspondences that most others agree with
    to within `threshold` (metres, in dst), refitted to all of its inliers. Needs N >= 3."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    n = len(src)
    if n < 3:
        raise ValueError(f"a similarity needs at least 3 correspondences, got {n}")
    rng = np.random.default_rng(seed)
    best = np.zeros(n, bool)
    for _ in range(iterations if n > 3 else 1):
        pick = rng.choice(n, 3, replace=False)
        if np.linalg.matrix_rank(src[pick] - src[pick].mean(0), tol=1e-9) < 2:
            continue  # collinear: no rotation about their line
        inl = np.linalg.norm(fit_similarity(src[pick], dst[pick]).apply(src) - dst, axis=1) < threshold
        if inl.sum() > best.sum():
            best = inl
    if best.sum() < 3:
        best = np.ones(n, bool)
    for _ in range(3):  # refit to the inliers, then take the inliers of the refit
        sim = fit_similarity(src[best], dst[best])
        inl = np.linalg.norm(sim.apply(src) - dst, axis=1) < threshold
        if inl.sum() < 3 or (inl == best).all():
            break
        best = inl
    return sim, best


def levelling(water) -> Similarity:
    """The rotation about the surface point above the origin that makes a tilted water plane (`WaterSurface`,
    no profile) level: x' = Q (x - p0) + p0, the plane then z = p0_z. For a survey whose positions fix no
    tilt (consumer GPS: a few metres of scatter over a short baseline tilted a test flight 12 degrees), the
    water fixes it: a calm surface is level to within a river's fall (under 1 %)."""
    import torch

    from ragsplat.water_surface import plane_frame

    Q, p0 = (t.numpy() for t in plane_frame(water, torch.zeros((), dtype=torch.float64)))
    return Similarity(1.0, Q, p0 - Q @ p0)


def tilt_allowed(xy: np.ndarray, sigma_z: np.ndarray, k: float = 3.0) -> float:
    """The largest tilt (a slope, rise over run) that heights of accuracy `sigma_z` [N] (m) at horizontal
    positions `xy` [N, 2] leave undetermined: k standard deviations of the steepest slope of the plane
    fitted to them by weighted least squares, sqrt of the largest eigenvalue of its slopes' covariance
    (sum of w (xy - mean)(xy - mean)^T)^-1, w = 1 / sigma_z^2. Inf for positions on a line."""
    w = 1.0 / np.asarray(sigma_z, float) ** 2
    xy = np.asarray(xy, float)
    d = xy - (w[:, None] * xy).sum(0) / w.sum()
    normal = (w[:, None, None] * d[:, :, None] * d[:, None, :]).sum(0)  # [2, 2]
    smallest = float(np.linalg.eigvalsh(normal)[0])
    return k / math.sqrt(smallest) if smallest > 1e-12 * max(float(np.trace(normal)), 1e-300) else math.inf

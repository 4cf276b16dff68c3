"""The adjustment through the water at survey scale: time and peak memory of `bundle.adjust` on a synthetic
flight (`ragsplat bench bundle`): a lawnmower grid of nadir photos over a bed under flat water, every bed
point seen by every photo whose view holds it, with pixel noise; the cameras start turned and moved, held by
RTK-like positions."""

from __future__ import annotations

import math
import time

import numpy as np
import torch

from ragsplat.bench.export import peak_rss_gb

HEIGHT, FOV, WIDTH, HEIGHT_PX = 12.0, 70.0, 400, 300  # metres above the water, degrees, pixels


def flight(columns: int, rows: int, spacing: float, points: int, seed: int = 0) -> dict:
    """The synthetic survey's tensors for `bundle.adjust` (truth and start): `columns` x `rows` photos
    `spacing` metres apart, `points` bed points 0.5-1.5 m under the water (z = 0) over the photos' area."""
    from ragsplat.camera import Camera
    from ragsplat.survey import bundle
    from ragsplat.water_surface import WaterSurface

    rng = np.random.default_rng(seed)
    cams = [Camera.look_at([i * spacing, j * spacing, HEIGHT], [i * spacing, j * spacing, 0.0], WIDTH,
                           HEIGHT_PX, FOV)
            for j in range(rows) for i in range(columns)]
    R = torch.tensor(np.array([c.R for c in cams]))
    C = torch.tensor(np.array([c.camera_center for c in cams]))
    K = torch.tensor([[c.fx, c.fy, c.cx, c.cy] for c in cams])
    P = torch.tensor(np.column_stack([rng.uniform(0, (columns - 1) * spacing, points),
                                      rng.uniform(0, (rows - 1) * spacing, points),
                                      rng.uniform(-1.5, -0.5, points)]))
    water = WaterSurface(0.0, 1.33)
    point, image, pixels = [], [], []
    for k in range(len(cams)):  # a camera at a time: who sees what
        near = torch.nonzero(((P[:, :2] - C[k, :2]).abs()
                              < HEIGHT * math.tan(math.radians(FOV / 2)) * 1.1).all(1))[:, 0]
        uv = bundle.project(R[k].expand(len(near), 3, 3), C[k].expand(len(near), 3),
                            K[k].expand(len(near), 4), P[near], water)
        inside = ((uv > 1) & (uv < torch.tensor([WIDTH - 1.0, HEIGHT_PX - 1.0]))).all(1)
        point.append(near[inside])
        image.append(torch.full((int(inside.sum()),), k))
        pixels.append(uv[inside])
    point, image, pixels = torch.cat(point), torch.cat(image), torch.cat(pixels)
    pixels = pixels + torch.tensor(rng.normal(0, 0.3, pixels.shape))
    turn = torch.tensor(rng.normal(0, math.radians(0.5), (len(cams), 3)))
    return {"R0": bundle._rotate(R, turn), "C0": C + torch.tensor(rng.normal(0, 0.05, C.shape)),
            "P0": P + torch.tensor(rng.normal(0, 0.1, P.shape)), "K": K, "point": point, "image": image,
            "pixels": pixels, "prior": C + torch.tensor(rng.normal(size=C.shape) * [0.02, 0.02, 0.03]),
            "R": R, "C": C, "P": P, "water": water}


def bench_bundle(columns: int, rows: int, spacing: float, points: int, iterations: int = 2,
                 sparse: bool | None = None) -> dict:
    """The figures of one adjustment: sizes (observations, their pairs, camera pairs), seconds per
    iteration, peak memory before and after, and the cameras' error at the end."""
    from ragsplat.survey import bundle

    f = flight(columns, rows, spacing, points)
    counts = torch.bincount(f["point"], minlength=len(f["P0"]))
    before = peak_rss_gb()
    t0 = time.perf_counter()
    got = bundle.adjust(f["R0"], f["C0"], f["K"], f["P0"], f["point"], f["image"], f["pixels"], f["water"],
                        prior_C=f["prior"], iterations=iterations, tol=0.0,
                        **({} if sparse is None else {"sparse": sparse}))
    seconds = time.perf_counter() - t0
    return {"cameras": len(f["C0"]), "points": len(f["P0"]), "observations": len(f["point"]),
            "observation_pairs": int((counts * counts).sum()), "iterations": got.iterations,
            "seconds_per_iteration": seconds / max(got.iterations, 1), "peak_rss_gb_before": before,
            "peak_rss_gb": peak_rss_gb(),
            "centre_error_m_median": float((got.C - f["C"]).norm(dim=1).median()), "sparse": sparse}

"""The export of a large bed: time and peak memory of `export.extract_bed` at a DEM resolution, on a synthetic
model of flat discs on a lattice over a square sinusoidal bed (`ragsplat bench export`)."""

from __future__ import annotations

import resource
import time

import numpy as np
import torch


def peak_rss_gb() -> float:
    """This process's peak resident memory so far (GB; Linux reports kB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6


def bed_height(xy: np.ndarray) -> np.ndarray:  # [..., 2] -> [...]: the synthetic bed, 1 m deep, +- 0.5 m
    return -1.0 + 0.5 * np.sin(xy[..., 0] / 7) * np.cos(xy[..., 1] / 5)


def disc_model(side: float, spacing: float) -> dict[str, torch.Tensor]:
    """Activated Gaussians: discs 0.6 spacing wide and 3 mm thick on a `spacing` lattice over a square of
    `side` metres centred on the origin, on `bed_height`, opacity 0.8."""
    half = side / 2
    x, y = np.meshgrid(np.arange(-half, half + spacing / 2, spacing),
                       np.arange(-half, half + spacing / 2, spacing))
    xy = np.column_stack([x.ravel(), y.ravel()])
    n = len(xy)
    return {"means": torch.tensor(np.column_stack([xy, bed_height(xy)]), dtype=torch.float32),
            "scales": torch.tensor([[0.6 * spacing, 0.6 * spacing, 0.003]], dtype=torch.float32).expand(n, 3),
            "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand(n, 4), "opacities": torch.full((n,), 0.8)}


def bench_export(side: float, spacing: float, resolution: float, on_block=None) -> dict:
    """The figures of one export: cells, blocks, seconds, peak memory before and after, height error."""
    from ragsplat.export import BLOCK_SAMPLES, extract_bed
    from ragsplat.water_surface import WaterSurface

    model = disc_model(side, spacing)
    before = peak_rss_gb()
    blocks = []
    t0 = time.perf_counter()
    bed = extract_bed(model, resolution, WaterSurface(0.0), None, gsd=spacing / 2,
                      on_block=lambda done, total: (blocks.append(total), on_block and on_block(done, total)))
    seconds = time.perf_counter() - t0
    err = np.abs(bed.grid[:, 2] - bed_height(bed.grid[:, :2]))
    return {"side_m": side, "gaussians": len(model["means"]), "resolution_m": resolution,
            "cells": len(bed.grid),
            "blocks": blocks[-1] if blocks else 1, "block_samples": BLOCK_SAMPLES, "seconds": seconds,
            "peak_rss_gb_before": before, "peak_rss_gb": peak_rss_gb(),
            "height_error_m": {"median": float(np.median(err)), "p99": float(np.percentile(err, 99))}}

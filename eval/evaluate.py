"""Evaluate one trained model: appearance on held-out views and geometry against the ground-truth bed.

`evaluate_views` takes a render function, so it serves any model (a Trainer, a loaded PLY);
`evaluate_geometry` takes activated Gaussians. `model_gaussians` and `model_renderer` adapt a Trainer.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from scipy.spatial import cKDTree

from eval import metrics
from eval.geometry import ExtractConfig, extract_surface
from ragsplat_core.scoring import geometry_metrics


def _mean(values) -> float | None:
    values = [v for v in values if v is not None]
    return float(np.mean(values)) if values else None


def evaluate_views(render: Callable, views, lpips_metric=None) -> dict:
    """Appearance on `views` (objects with `.name`, `.kind`, `.image`, `.dry` as in `ragsplat_core.dataset`).

    `render(view, interface: bool) -> [H, W, 3]` renders through the interface (True) or the true
    Gaussians without it (False). Renders are clamped to [0, 1] (as 3DGS evaluates them); the metrics run
    on the render's device, where `lpips_metric` must already be (`LPIPS.to`). Returns
    {"refr": {"psnr", "ssim", "lpips"}, "dry": {...} or None, "per_view": [...]}.
    """
    per_view = []
    for view in views:
        entry = {"name": view.name, "kind": view.kind}
        for cond, target in (("refr", view.image), ("dry", view.dry)):
            if target is None:
                entry[cond] = None
                continue
            with torch.no_grad():
                img = render(view, cond == "refr").clamp(0, 1)
                target = target.to(img.device, img.dtype)  # metrics run where the render is (LPIPS too)
                entry[cond] = {"psnr": float(metrics.psnr(img, target)), "ssim": float(metrics.ssim(img, target)),
                               "lpips": None if lpips_metric is None else float(lpips_metric(img, target))}
        per_view.append(entry)
    out = {"per_view": per_view}
    for cond in ("refr", "dry"):
        rows = [v[cond] for v in per_view if v[cond] is not None]
        out[cond] = {k: _mean(r[k] for r in rows) for k in ("psnr", "ssim", "lpips")} if rows else None
    return out


def evaluate_geometry(gaussians: dict, gt: np.ndarray, region: dict, cfg: ExtractConfig) -> dict:
    """Extraction + metrics; `gaussians` has means, scales (linear), quats (wxyz), opacities ([0, 1]).

    `gt` is the dataset's grid, already limited to `region` by the data contract (not cropped again: its
    edge nodes would come and go with rounding). The extracted grid shares the GT grid's nodes, and only
    cells where the ground truth has a point are scored: on a reach, the submerged bed, not the banks.
    """
    origin = tuple(gt[:, :2].min(0))  # a node of the GT grid, so both grids share their nodes
    grid, stats = extract_surface(gaussians["means"], gaussians["scales"], gaussians["quats"],
                                  gaussians["opacities"], cfg, region, origin)
    on_truth = np.isfinite(cKDTree(gt[:, :2]).query(grid[:, :2], distance_upper_bound=0.5 * cfg.cell)[0])
    stats["grid_points_on_truth"] = int(on_truth.sum())
    return {**geometry_metrics(grid[on_truth], gt), "extraction": stats}


def model_gaussians(trainer) -> dict:
    """The trainer's true Gaussians, activated: means, scales (linear), quats (unit wxyz), opacities."""
    from ragsplat_core.gaussians import activated

    scales, quats, opac = activated(trainer.splats)
    return {"means": trainer.splats["means"].detach(), "scales": scales.detach(), "quats": quats.detach(),
            "opacities": opac.detach()}


def model_renderer(trainer) -> Callable:
    """`render(view, interface)` for `evaluate_views`: the trainer's render of the view's camera."""
    return lambda view, interface: trainer.render(view.camera, interface=interface)[0]

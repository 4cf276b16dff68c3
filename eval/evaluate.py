"""Evaluate one trained model: appearance on held-out views and geometry against the ground-truth bed.

`evaluate_views` takes a render function, so it serves any model (a Trainer, a loaded PLY);
`evaluate_geometry` takes activated Gaussians (the volume extraction, `ragsplat.surface`),
`evaluate_fused` a depth render function (TSDF fusion of depth maps, `ragsplat.fusion`), and
`score_grid` any bed height grid (a reference answer too). `model_gaussians`, `model_renderer` and
`model_depth` adapt a Trainer.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from scipy.spatial import cKDTree

from ragsplat.dataset.layout import GT_GRID_STEP
from ragsplat.eval import metrics
from ragsplat.fusion import FuseConfig, fuse
from ragsplat.scoring import IHO_ORDERS, WITHIN, geometry_metrics, quantile_with_holes, thresholds, tvu
from ragsplat.surface import ExtractConfig, extract_surface


def _mean(values) -> float | None:
    values = [v for v in values if v is not None]
    return float(np.mean(values)) if values else None


def evaluate_views(render: Callable, views, lpips_metric=None, psnr_only: bool = False) -> dict:
    """Appearance on `views` (objects with `.name`, `.kind`, `.image`, `.dry` as in `ragsplat.dataset`).

    `render(view, interface: bool) -> [H, W, 3]` renders through the interface (True) or the true
    Gaussians without it (False). Renders are clamped to [0, 1] (as 3DGS evaluates them); the metrics run
    on the render's device, where `lpips_metric` must already be (`LPIPS.to`). `ssim` is the standard
    SSIM (scikit-image's value), `ssim_3dgs` the training one. Returns
    {"refr": {"psnr", "ssim", "ssim_3dgs", "lpips"}, "dry": {...} or None, "per_view": [...]}.
    `psnr_only`: the other metrics are None (the training curve's points need PSNR alone; the SSIMs cost
    more than the renders).
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
                entry[cond] = {"psnr": float(metrics.psnr(img, target)), "ssim": None, "ssim_3dgs": None,
                               "lpips": None}
                if not psnr_only:
                    entry[cond].update(ssim=float(metrics.ssim_standard(img, target)),
                                       ssim_3dgs=float(metrics.ssim(img, target)),
                                       lpips=None if lpips_metric is None
                                       else float(lpips_metric(img, target)))
        per_view.append(entry)
    out = {"per_view": per_view}
    for cond in ("refr", "dry"):
        rows = [v[cond] for v in per_view if v[cond] is not None]
        out[cond] = ({k: _mean(r[k] for r in rows) for k in ("psnr", "ssim", "ssim_3dgs", "lpips")} if rows
                     else None)
    return out


def score_grid(grid: np.ndarray, truth) -> dict:
    """Scores of a predicted bed height grid [P, 3] (cells of `cfg.cell` at nodes of the GT grid, inside the
    region) against `truth` (`ragsplat.dataset.load.GroundTruth`).

    Point-set scores (Chamfer, P/R/F1 at the absolute 10 / 30 cm and the depth-scaled 1 % / 3 % of the
    maximum depth) use the cells where the ground truth has a submerged point; `survey` scores every cell
    against the exact bed height at its centre (`survey_figures`).
    """
    named = thresholds(truth.max_depth)
    gt = truth.grid
    on_truth = np.isfinite(cKDTree(gt[:, :2]).query(grid[:, :2],
                                                    distance_upper_bound=0.5 * GT_GRID_STEP)[0]) \
        if len(grid) else np.zeros(0, bool)
    m = geometry_metrics(grid[on_truth], gt, tuple(named.values()))
    out = {k: m[k] for k in ("n_pred", "n_gt", "accuracy", "completeness", "chamfer")}
    out["thresholds_m"] = named
    for kind in ("precision", "recall", "f1"):
        out[kind] = {name: m[f"{kind}@{t:g}"] for name, t in named.items()}
    out["survey"] = survey_figures(grid, truth)
    return out


def survey_figures(grid: np.ndarray, truth) -> dict:
    """What a surveyor asks of a bathymetry: dz = predicted - true bed height at each cell's centre (the exact
    surface when the dataset has one, else the nearest ground-truth node), over the wet cells, by depth band
    (thirds of the maximum depth) and over the emerged banks.

    The rule that makes beds of different cover comparable: every wet ground-truth cell counts, a wet cell
    the bed leaves empty (a hole) as a miss. So `p95` (of |dz|) counts a hole as larger than any error (None
    when more than about 5 % of the band's cells are holes), and `within` (|dz| < 3 / 5 cm) and `iho` (|dz|
    within each IHO S-44 order's TVU at the cell's true depth) are fractions of all the band's wet cells.
    `bias` and `rmse` cannot count a hole: they are over the covered cells, with `cover` beside them. The
    banks are scored over their covered cells only (no hole rule: a bed may stop at the waterline).
    `coverage` = covered wet cells / wet ground-truth cells."""
    dz, depth = height_error(grid, truth)
    D = truth.max_depth
    true_depth = truth.water.depth(truth.grid)  # [G] every wet ground-truth cell, below the surface above it
    edges = [0.0, D / 3, 2 * D / 3, np.inf]  # the last band takes anything deeper than D too
    bands = {"wet": (depth > 0, true_depth > 0)}
    for name, lo, hi in zip(("shallow", "middle", "deep"), edges[:-1], edges[1:]):
        bands[name] = ((depth > lo) & (depth <= hi), (true_depth > lo) & (true_depth <= hi))
    out = {"band_edges_m": [0.0, D / 3, 2 * D / 3, D],
           "coverage": float((depth > 0).sum() / len(truth.grid))}
    for name, (mask, cells) in bands.items():
        out[name] = wet_figures(dz[mask], depth[mask], max(int(cells.sum()) - int(mask.sum()), 0))
    e = dz[depth <= 0]
    out["banks"] = {"n": len(e), "bias": float(e.mean()) if len(e) else None,
                    "rmse": float(np.sqrt((e**2).mean())) if len(e) else None,
                    "p95": float(np.percentile(np.abs(e), 95)) if len(e) else None}
    return out


def wet_figures(dz: np.ndarray, depth: np.ndarray, holes: int) -> dict:
    """`survey_figures` of one band: the errors dz [N] of its covered cells at true depths [N] (metres) and
    the number of its wet cells left empty."""
    e, total = np.abs(dz), len(dz) + holes
    share = (lambda ok: float(ok.sum() / total)) if total else (lambda ok: None)
    return {"n": len(dz), "holes": holes, "cover": float(len(dz) / total) if total else None,
            "bias": float(dz.mean()) if len(dz) else None,
            "rmse": float(np.sqrt((dz**2).mean())) if len(dz) else None,
            "p95": quantile_with_holes(e, holes, 0.95),
            "within": {name: share(e < t) for name, t in WITHIN.items()},
            "iho": {order: share(e <= tvu(depth, order)) for order in IHO_ORDERS}}


def height_error(grid: np.ndarray, truth) -> tuple[np.ndarray, np.ndarray]:
    """(dz [P], true depth [P]) of each predicted cell at its centre: the true bed's depth below the water
    surface above it (`truth.water`, a sloping one's height there)."""
    if truth.surface is not None:
        z_true = truth.surface.height_at(grid[:, :2])
    else:
        nodes = truth.nodes
        z_true = nodes[cKDTree(nodes[:, :2]).query(grid[:, :2])[1], 2] if len(grid) else np.zeros(0)
    return grid[:, 2] - z_true, truth.water.height(grid[:, :2]) - z_true


def evaluate_geometry(gaussians: dict, truth, cfg: ExtractConfig) -> tuple[dict, np.ndarray]:
    """Extraction + `score_grid`; `gaussians` has means, scales (linear), quats (wxyz), opacities ([0, 1]).
    Returns (scores with the extraction's counts, the extracted grid [P, 3]).

    The extracted grid shares the GT grid's nodes (a half-cell offset alone would cost ~2.5 cm of Chamfer);
    the GT grid is already limited to the region by the data contract (not cropped again: its edge nodes
    would come and go with rounding).
    """
    origin = tuple(truth.grid[:, :2].min(0))
    grid, stats = extract_surface(gaussians["means"], gaussians["scales"], gaussians["quats"],
                                  gaussians["opacities"], cfg, truth.region, origin)
    return {**score_grid(grid, truth), "extraction": stats}, grid


def evaluate_fused(render_depth: Callable, views, truth, cfg: FuseConfig,
                   cell: float) -> tuple[dict, np.ndarray]:
    """The bed from rendered depth + `score_grid`: `render_depth(camera) -> [H, W]` z-depth (0 = none) at
    every view's camera (the training views), fused (`ragsplat.fusion.fuse`) on the GT grid's nodes
    (`cell` apart) inside the region. Returns (scores with the fusion's choices under "fusion", the grid
    [P, 3])."""
    cameras = [v.camera for v in views]
    depths = [render_depth(cam) for cam in cameras]
    grid, stats = fuse(depths, cameras, truth.region, cell, tuple(truth.grid[:, :2].min(0)), cfg)
    return {**score_grid(grid, truth), "fusion": stats}, grid


def model_gaussians(trainer) -> dict:
    """The trainer's true Gaussians, activated: means, scales (linear), quats (unit wxyz), opacities."""
    from ragsplat.gaussians import activated

    scales, quats, opac = activated(trainer.splats)
    return {"means": trainer.splats["means"].detach(), "scales": scales.detach(), "quats": quats.detach(),
            "opacities": opac.detach()}


def model_renderer(trainer) -> Callable:
    """`render(view, interface)` for `evaluate_views`: the trainer's render of the view's camera."""
    return lambda view, interface: trainer.render(view.camera, interface=interface)[0]


def model_depth(trainer) -> Callable:
    """`render_depth(camera)` for `evaluate_fused`: the median depth of the trainer's true Gaussians."""
    return trainer.median_depth

"""Scores of a bed surface against the ground truth, shared by the evaluation and the dataset generator
(which scores trivial answers against its own ground truth). numpy and scipy only.

Both sides are point sets: accuracy = mean distance prediction -> GT, completeness = GT -> prediction,
Chamfer = their mean (metres, unsquared); precision / recall / F1 at each threshold with a strict `<` (a
distance equal to the threshold does not count).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def geometry_metrics(pred: np.ndarray, gt: np.ndarray, thresholds=(0.10, 0.30)) -> dict:
    """Chamfer and F1 of predicted points [P, 3] against GT points [G, 3] (metres; fractions, not %).

    With no predicted points the distances are None and precision/recall/F1 are 0.
    """
    pred, gt = np.asarray(pred, np.float64).reshape(-1, 3), np.asarray(gt, np.float64).reshape(-1, 3)
    if len(gt) == 0:
        raise ValueError("geometry_metrics: the ground-truth point set is empty")
    out = {"n_pred": len(pred), "n_gt": len(gt), "thresholds": [float(t) for t in thresholds]}
    if len(pred) == 0:
        out.update(accuracy=None, completeness=None, chamfer=None)
        for t in thresholds:
            out.update({f"precision@{t:g}": 0.0, f"recall@{t:g}": 0.0, f"f1@{t:g}": 0.0})
        return out
    d_pred = cKDTree(gt).query(pred)[0]  # [P] prediction -> GT
    d_gt = cKDTree(pred).query(gt)[0]  # [G] GT -> prediction
    acc, comp = float(d_pred.mean()), float(d_gt.mean())
    out.update(accuracy=acc, completeness=comp, chamfer=0.5 * (acc + comp))
    for t in thresholds:
        p, r = float((d_pred < t).mean()), float((d_gt < t).mean())
        out.update({f"precision@{t:g}": p, f"recall@{t:g}": r,
                    f"f1@{t:g}": 0.0 if p + r == 0 else 2 * p * r / (p + r)})
    return out


def thresholds(max_depth: float) -> dict[str, float]:
    """The report's thresholds: absolute 10 and 30 cm, and 1 % and 3 % of the maximum depth (scale-free:
    the paper's 10 / 30 cm on its 10 m bed)."""
    return {"10cm": 0.10, "30cm": 0.30, "1%": 0.01 * max_depth, "3%": 0.03 * max_depth}


# IHO S-44 (6th edition, 2020), total vertical uncertainty at 95 %: TVU(d) = sqrt(a^2 + (b d)^2), (a m, b) per
# order. Order 1a and 1b share their TVU.
IHO_ORDERS = {"order 2": (1.0, 0.023), "order 1": (0.5, 0.013), "special": (0.25, 0.0075),
              "exclusive": (0.15, 0.0075)}
# metres: bands tighter than every IHO order at a few metres of depth, where a river engineer's question lies
WITHIN = {"3cm": 0.03, "5cm": 0.05}


def tvu(depth: np.ndarray, order: str) -> np.ndarray:
    """[N] IHO S-44 total vertical uncertainty at 95 % (metres) of `order` at each depth [N] (metres)."""
    a, b = IHO_ORDERS[order]
    return np.sqrt(a**2 + (b * np.asarray(depth, np.float64)) ** 2)


def quantile_with_holes(abs_err: np.ndarray, holes: int, q: float) -> float | None:
    """The `q` quantile (numpy's linear rule) of the errors [N] together with `holes` cells that have none, a
    hole counting as larger than every error: None when the quantile falls on or between holes (more than
    about 1 - q of the cells are holes), and numpy's percentile of the errors alone when `holes` is 0."""
    e = np.sort(np.asarray(abs_err, np.float64))
    total = len(e) + int(holes)
    if total == 0:
        return None
    pos = q * (total - 1)
    hi = int(np.ceil(pos))
    if hi >= len(e):
        return None
    lo = int(np.floor(pos))
    return float(e[lo] + (pos - lo) * (e[hi] - e[lo]))


def plane_scores(gt: np.ndarray, z: float, max_depth: float) -> dict:
    """A flat plane at height `z`, sampled on the ground truth's own nodes, scored at `thresholds`."""
    plane = np.column_stack([gt[:, :2], np.full(len(gt), z)])
    named = thresholds(max_depth)
    m = geometry_metrics(plane, gt, tuple(named.values()))
    return {"z": float(z), "chamfer": m["chamfer"],
            **{f"{k}_{name}": m[f"{k}@{t:g}"]
               for name, t in named.items() for k in ("precision", "recall", "f1")}}

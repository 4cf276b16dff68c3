"""Is a per-cell vertical uncertainty right? The calibration figures on arrays: the predicted
uncertainty of each cell (a calibrated standard deviation sigma, or TVU95 = Z95 sigma), its error e =
predicted - true bed height, the dataset seed it came from, its true depth and how many views see it.

Definitions (all over the cells given: the wet cells with a height of the seeds evaluated; a hole has no
error to cover and is counted by the accuracy tables, not here):
- coverage at level p: the share of cells with |e| <= z_p sigma, z_p the standard normal's (1 + p) / 2
  quantile (the p interval of a Gaussian; at 0.95 it is |e| <= TVU95). Pooled over every cell, and per seed:
  cells of one seed share its poses' and water's errors, so a seed, not a cell, is the unit of the spread
  (`seed_spread`: mean, standard deviation with ddof 1, least and largest over the seeds).
- worst depth third: the least 95 % coverage over the depth bands (0, D/3], (D/3, 2D/3], (2D/3, inf) of the
  maximum depth D (the accuracy tables' bands, `ragsplat.eval.evaluate.survey_figures`); worst view-count bin:
  the least over `VIEW_BINS` bins of equal count by view count (ties in one bin); bins of fewer than `MIN_BIN`
  cells are left out of both.
- ENCE (Levi et al. 2022, expected normalised calibration error): the cells sorted by sigma into 10 bins of
  equal count; per bin RMV = sqrt(mean sigma^2), RMSE = sqrt(mean e^2); ENCE = mean over bins of
  |RMV - RMSE| / RMV. 0 for a calibrated sigma (up to sampling noise).
- z-score variance: the variance of e / sigma (1 for a calibrated Gaussian sigma).
- sharpness: the median TVU95, against
  (i) the oracle (`oracle_tvu95`): per bed (one run's cells), sigma_o(x) = sqrt(sum_j K(x - x_j) e_j^2 /
      sum_j K(x - x_j)) over that bed's cells j, K a Gaussian of `ORACLE_BANDWIDTH` m truncated at 3
      bandwidths (the cell itself included), then the same split-conformal step as the model's
      (`uncertainty.calibrate`: the ceil((n + 1) 0.95)-th smallest |e| / (Z95 sigma_o)) on that bed's own
      cells: the sharpest TVU95 of this shape that one could state knowing the errors' local size;
  (ii) the constant width w that covers the same share of the cells as the model's TVU95 does (the
      ceil(coverage N)-th smallest |e|): what one number for the whole bed would need.
  The ratios median TVU95 / median oracle TVU95 and median TVU95 / w.
- Spearman's rank correlation of TVU95 with |e|.
- the share of cells whose TVU95 is within each IHO S-44 order's TVU at its depth (`scoring.tvu`) and within
  5 cm (`scoring.WITHIN`): what the band would let a surveyor claim, cell by cell.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import norm, spearmanr

from ragsplat.scoring import IHO_ORDERS, WITHIN, tvu
from ragsplat.uncertainty import Z95, conformal_rank

LEVELS = (0.5, 0.8, 0.95)
ENCE_BINS = 10
VIEW_BINS = 5
MIN_BIN = 100  # cells: a smaller depth or view-count bin is not judged (its coverage is mostly noise)
ORACLE_BANDWIDTH = 0.25  # metres: 5 cells of the evaluation's 5 cm, about the size of the beds' error patches


def z_level(level: float) -> float:
    """The half-width in standard deviations of a Gaussian's central `level` interval."""
    return float(norm.ppf(0.5 + level / 2))


def coverage(sigma, err, level: float = 0.95) -> float:
    """The share of cells with |err| <= z_level(level) sigma (NaN for no cells)."""
    sigma, err = np.asarray(sigma, float), np.asarray(err, float)
    return float(np.mean(np.abs(err) <= z_level(level) * sigma)) if len(err) else float("nan")


def per_seed(values_of, seeds) -> dict:
    """{seed: values_of(mask of its cells)} for each seed in `seeds` [N] (sorted)."""
    seeds = np.asarray(seeds)
    return {s.item() if hasattr(s, "item") else s: values_of(seeds == s) for s in np.unique(seeds)}


def seed_spread(values) -> dict:
    """Mean, standard deviation (ddof 1; None for one seed), least and largest of per-seed figures."""
    v = np.asarray(list(values), float)
    return {"seeds": len(v), "mean": float(v.mean()), "std": float(v.std(ddof=1)) if len(v) > 1 else None,
            "min": float(v.min()), "max": float(v.max())}


def depth_bins(depth, max_depth: float | None = None) -> np.ndarray:
    """[N] band 0, 1, 2 of each depth: thirds of `max_depth` (default the deepest cell), the last open."""
    depth = np.asarray(depth, float)
    D = float(depth.max()) if max_depth is None else float(max_depth)
    return np.searchsorted([D / 3, 2 * D / 3], depth, side="left")


def view_bins(views, bins: int = VIEW_BINS) -> np.ndarray:
    """[N] bins of about equal count by view count, the cells of one count always in one bin."""
    views = np.asarray(views, float)
    edges = np.unique(np.quantile(views, np.linspace(0, 1, bins + 1)[1:-1], method="inverted_cdf"))
    return np.searchsorted(edges, views, side="left")


def worst_bin(sigma, err, bins, level: float = 0.95, min_cells: int = MIN_BIN) -> dict:
    """{"worst": the least coverage over the bins [N] with >= min_cells cells (None: none has), "bins": {bin:
    (cells, coverage)}}."""
    sigma, err, bins = np.asarray(sigma, float), np.asarray(err, float), np.asarray(bins)
    per = {int(b): (int((bins == b).sum()), coverage(sigma[bins == b], err[bins == b], level))
           for b in np.unique(bins)}
    judged = [c for n, c in per.values() if n >= min_cells]
    return {"worst": min(judged) if judged else None, "bins": per}


def ence(sigma, err, bins: int = ENCE_BINS) -> float:
    """Expected normalised calibration error over `bins` equal-count bins by sigma (module docstring)."""
    sigma, err = np.asarray(sigma, float), np.asarray(err, float)
    order = np.argsort(sigma, kind="stable")
    terms = []
    for part in np.array_split(order, bins):
        if len(part):
            rmv, rmse = np.sqrt(np.mean(sigma[part] ** 2)), np.sqrt(np.mean(err[part] ** 2))
            terms.append(abs(rmv - rmse) / rmv)
    return float(np.mean(terms))


def z_variance(sigma, err) -> float:
    """The variance (ddof 0) of the z-scores err / sigma."""
    return float(np.var(np.asarray(err, float) / np.asarray(sigma, float)))


def conformal_scale(score, coverage_level: float = 0.95) -> float:
    """The split-conformal quantile of scores [n]: the ceil((n + 1) coverage)-th smallest (inf when that
    exceeds n)."""
    score = np.sort(np.asarray(score, float))
    k = conformal_rank(len(score), coverage_level)
    return float(score[k - 1]) if k <= len(score) else float("inf")


def local_rms(xy, err, cell: float, bandwidth: float = ORACLE_BANDWIDTH) -> np.ndarray:
    """[N] sqrt(sum_j K e_j^2 / sum_j K) at each cell of one seed (xy [N, 2] on a grid of `cell` m), K a
    Gaussian of `bandwidth` m truncated at 3 bandwidths: normalised convolution on the grid (the cells that
    are not given weigh nothing)."""
    from scipy.ndimage import gaussian_filter

    xy, err = np.asarray(xy, float), np.asarray(err, float)
    ij = np.rint((xy - xy.min(0)) / cell).astype(np.int64)
    shape = tuple(ij.max(0) + 1)
    num, den = np.zeros(shape), np.zeros(shape)
    num[ij[:, 0], ij[:, 1]] = err**2
    den[ij[:, 0], ij[:, 1]] = 1.0
    s = bandwidth / cell
    num, den = (gaussian_filter(a, s, mode="constant", truncate=3.0) for a in (num, den))
    return np.sqrt(num[ij[:, 0], ij[:, 1]] / den[ij[:, 0], ij[:, 1]])


def oracle_tvu95(xy, err, beds, cell: float, bandwidth: float = ORACLE_BANDWIDTH,
                 coverage_level: float = 0.95) -> np.ndarray:
    """[N] the oracle's TVU95 (module docstring): each bed's locally smoothed errors (`beds` [N]: labels),
    scaled by the conformal step on that bed's own cells."""
    xy, err, beds = np.asarray(xy, float), np.asarray(err, float), np.asarray(beds)
    out = np.empty(len(err))
    for s in np.unique(beds):
        m = beds == s
        sig = np.maximum(local_rms(xy[m], err[m], cell, bandwidth), 1e-12)
        out[m] = Z95 * conformal_scale(np.abs(err[m]) / (Z95 * sig), coverage_level) * sig
    return out


def constant_width(err, share: float) -> float:
    """The least width w with |err| <= w for `share` of the cells: the ceil(share N)-th smallest |err|."""
    e = np.sort(np.abs(np.asarray(err, float)))
    return float(e[min(max(int(np.ceil(share * len(e) - 1e-9)), 1), len(e)) - 1])


def iho_shares(tvu95, depth) -> dict:
    """{order: share of cells whose TVU95 <= the order's TVU at their depth} for each IHO S-44 order, and
    {"5cm": share with TVU95 <= 5 cm}."""
    tvu95, depth = np.asarray(tvu95, float), np.asarray(depth, float)
    out = {order: float(np.mean(tvu95 <= tvu(depth, order))) for order in IHO_ORDERS}
    out["5cm"] = float(np.mean(tvu95 <= WITHIN["5cm"]))
    return out


def tvu_band_summary(tvu95, err, depth) -> dict:
    """What `ragsplat score` says of a DEM's TVU95 band over the wet cells it covers (TVU95 [N], errors [N],
    true depths [N], m): the cells, the coverage of the central `LEVELS` intervals (|e| <= z_p sigma, sigma =
    TVU95 / Z95; at 0.95 |e| <= TVU95), the median TVU95 (the sharpness), the z-scores' variance, and the IHO
    orders' shares (`iho_shares`). None for each figure where there is no cell."""
    tvu95, err = np.asarray(tvu95, float), np.asarray(err, float)
    if not len(err):
        return {"cells": 0, "coverage": {f"{p:g}": None for p in LEVELS}, "median_tvu95": None,
                "z_variance": None, "iho": None}
    sigma = tvu95 / Z95
    return {"cells": len(err), "coverage": {f"{p:g}": coverage(sigma, err, p) for p in LEVELS},
            "median_tvu95": float(np.median(tvu95)), "z_variance": z_variance(sigma, err),
            "iho": iho_shares(tvu95, depth)}


def calibration_report(tvu95, err, seeds, depth, views, xy=None, cell: float = 0.05,
                       max_depth: float | None = None, beds=None) -> dict:
    """Every figure of the module docstring for cells with TVU95 [N] (m), errors [N] (m), dataset seeds [N],
    true depths [N] (m), view counts [N], and, for the oracle, their horizontal positions xy [N, 2] on a grid
    of `cell` m (None: no oracle) and which bed each cell is of ([N] labels; default `seeds`: several training
    runs on one dataset seed are several beds over the same cells, each smoothed on its own). `max_depth`:
    the depth bands' D (default the deepest cell)."""
    tvu95, err, seeds = np.asarray(tvu95, float), np.asarray(err, float), np.asarray(seeds)
    sigma = tvu95 / Z95
    band = tvu_band_summary(tvu95, err, depth)  # cells, pooled coverage, median, z variance, IHO
    pooled = band["coverage"]
    seeds_cov = {f"{p:g}": per_seed(lambda m, p=p: coverage(sigma[m], err[m], p), seeds) for p in LEVELS}
    achieved = pooled["0.95"]
    width = constant_width(err, achieved)
    out = {**band, "coverage_per_seed": seeds_cov,
           "coverage_seed_spread": {p: seed_spread(v.values()) for p, v in seeds_cov.items()},
           "worst_depth_third": worst_bin(sigma, err, depth_bins(depth, max_depth)),
           "worst_view_bin": worst_bin(sigma, err, view_bins(views)),
           "ence": ence(sigma, err), "constant_width": width,
           "sharpness_vs_constant": float(np.median(tvu95) / width) if width > 0 else None,
           "spearman": float(spearmanr(tvu95, np.abs(err)).statistic)}
    if xy is not None:
        oracle = oracle_tvu95(xy, err, seeds if beds is None else beds, cell)
        out.update(oracle_median_tvu95=float(np.median(oracle)),
                   sharpness_vs_oracle=float(np.median(tvu95) / np.median(oracle)))
    return out


def reliability_figure(tvu95, err, seeds=None, title: str = ""):
    """A matplotlib figure: left, the observed coverage of the central p intervals (|e| <= z_p sigma) against
    p, pooled (black) and per seed (thin); right, RMSE against RMV in the ENCE's bins (log-log), both against
    the diagonal of a calibrated uncertainty. The caller saves or shows it."""
    from ragsplat.pages import pyplot

    plt = pyplot()

    sigma, err = np.asarray(tvu95, float) / Z95, np.asarray(err, float)
    levels = np.linspace(0.05, 0.99, 48)
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4.5), constrained_layout=True)
    if seeds is not None:
        for s, m in per_seed(lambda m: m, seeds).items():
            left.plot(levels, [coverage(sigma[m], err[m], p) for p in levels], lw=0.8, alpha=0.6,
                      label=f"seed {s}")
    left.plot(levels, [coverage(sigma, err, p) for p in levels], "k", lw=2, label="pooled")
    left.plot([0, 1], [0, 1], ":", color="grey")
    left.set(xlabel="nominal coverage p", ylabel="observed share with |e| <= z_p sigma", xlim=(0, 1),
             ylim=(0, 1))
    left.legend(fontsize=8)
    order = np.argsort(sigma, kind="stable")
    parts = [p for p in np.array_split(order, ENCE_BINS) if len(p)]
    rmv = [np.sqrt(np.mean(sigma[p] ** 2)) for p in parts]
    rmse = [np.sqrt(np.mean(err[p] ** 2)) for p in parts]
    right.loglog(rmv, rmse, "o-k")
    lim = [min(rmv + rmse), max(rmv + rmse)]
    right.plot(lim, lim, ":", color="grey")
    right.set(xlabel="RMV: root mean predicted variance (m)", ylabel="RMSE of the errors (m)")
    for ax in (left, right):
        ax.grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    return fig

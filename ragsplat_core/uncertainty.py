"""A per-cell vertical uncertainty of the bed at 95 % (TVU95, IHO S-44's measure) from what a finished run
has: the views, the water, the extraction's samples. numpy and torch, no I/O.

Features of each cell of the bed's grid (`cell_features`, `CellFeatures`):
- geometry: the vertical standard deviation (m) of the cell's bed point triangulated from the views that see
  it through the water, for a pixel noise of 1 (`view_geometry`). Per view i, J_i [2, 3] = d pixel / d point
  = the projection's Jacobian at the apparent point times the refraction's (`refraction.apparent_jacobian`);
  the information matrix is sum_i J_i^T J_i and the point's covariance its inverse, so sigma_z =
  sqrt(inverse[2, 2]). A view sees the cell when its camera is above the water and the apparent point lies in
  front of it, inside its image (occlusion by the bed itself is not tested: a 2.5-D bed seen from above).
  With fewer than two views, or an information matrix that is singular to round-off, nothing triangulates the
  point: `GEOMETRY_CAP` m per pixel stands in.
- views: how many views see the cell (for the calibration's bins; not in the model by default).
- depth: below the water surface (0 on emerged ground).
- spread: the robust spread of the extraction's filtered samples' heights in the cell (`surface.cell_spread`:
  the surfels' thickness, and two layers where floaters sit over the bed); a cell with fewer than two samples
  takes the median spread of the cells that have one.
- filled: 1 for a cell the extraction's step 6 interpolated (`surface.fill_holes`), else 0.
- the systematic terms, which do not average out over a reach: a water level wrong by dL moves the
  triangulated bed by about (n - 1) dL (the apparent depth is about d / n: a bed placed n (d / n + dL) under a
  level dL higher lies (n - 1) dL lower), an index wrong by dn by about d / n. Here both exactly to first
  order through the views (`view_geometry`): with the pixels fixed at the true point's, a change of the water
  moves the least-squares point by dP = -(sum J_i^T J_i)^-1 sum J_i^T g_i dw, g_i = d pixel_i / d w (central
  differences of `refraction.apparent_points`). sigma_sys = sqrt((dz/dL sigma_L)^2 + (dz/dn sigma_n)^2).

The model (`UncertaintyModel`): sigma^2 = sum_k w_k^2 f_k^2 over the features named in `features` (default
`FEATURES`: a constant in metres, the geometry times a pixel noise, depth, spread, filled), fitted by the
Gaussian negative log-likelihood of the errors e = predicted - true bed height (`fit`) on development seeds;
then a split-conformal scale c on another development seed (`calibrate`) so that |e| <= TVU95 holds for 95 %
of its wet cells: TVU95 = Z95 sqrt((c sigma)^2 + sigma_sys^2) (`tvu95`). The systematic term is not fitted
nor scaled: development seeds render with the true water (sigma_sys = 0 there), and a survey's level and n
have their own, stated uncertainty. The evaluation seeds are never used for either step (docs/uncertainty.md).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, replace

import numpy as np
import torch

from ragsplat.errors import ConfigError
from ragsplat.refraction import apparent_jacobian, apparent_points
from ragsplat.water_surface import WaterSurface

Z95 = 1.959963984540054  # the standard normal's 97.5 % quantile: a 95 % two-sided interval is +-Z95 sigma
GEOMETRY_CAP = 1.0  # m per pixel: the geometry feature of a cell no two views triangulate
# Central differences of the apparent points in the water level (m) and n: float64 round-off of the solve
# (~1e-15 relative) over these steps leaves ~1e-10 relative error, their truncation ~1e-8.
LEVEL_STEP, N_STEP = 1e-4, 1e-4
FEATURES = ("one", "geometry", "depth", "spread", "filled")


@dataclass(frozen=True)
class ViewGeometry:
    """`view_geometry` of G points."""

    sigma_z: np.ndarray  # [G] vertical standard deviation (m) for a pixel noise of 1; inf: not triangulated
    views: np.ndarray  # [G] int: the views that see the point
    dz_dlevel: np.ndarray  # [G] the triangulated height's change per metre of the water level (NaN: none)
    dz_dn: np.ndarray  # [G] ... per unit of n (NaN: none, or no water)


def _project_jacobian(camera, apparent: torch.Tensor):
    """(pixels [G, 2], z-depth [G], d pixel / d point [G, 2, 3]) of world points [G, 3] (float64)."""
    R = torch.tensor(camera.R, dtype=apparent.dtype)
    pc = apparent @ R.T + torch.tensor(camera.t, dtype=apparent.dtype)  # [G, 3]
    x, y, z = pc.unbind(-1)
    zero = torch.zeros_like(z)
    d_cam = torch.stack([torch.stack([camera.fx / z, zero, -camera.fx * x / z**2], -1),
                         torch.stack([zero, camera.fy / z, -camera.fy * y / z**2], -1)], -2)  # [G, 2, 3]
    pixels = torch.stack([camera.fx * x / z + camera.cx, camera.fy * y / z + camera.cy], -1)
    return pixels, z, d_cam @ R


def _pixels(camera, points: torch.Tensor, water: WaterSurface | None):  # [G, 2] pixels of the true points
    center = torch.tensor(camera.camera_center, dtype=points.dtype)
    apparent = points if water is None else apparent_points(points, center, water)
    return _project_jacobian(camera, apparent)[0]


def _above(camera, water: WaterSurface | None) -> bool:  # refraction needs the camera in the air
    c = camera.camera_center
    return water is None or float(c[2]) > float(water.height(np.asarray(c[:2], float)))


def view_geometry(points, cameras, water: WaterSurface | None, chunk: int = 65_536) -> ViewGeometry:
    """The triangulation's vertical precision and the systematic slopes (module docstring) at each of `points`
    [G, 3] (the bed's cells, tensors or arrays) seen by `cameras` (`Camera`s) through `water` (None: air
    alone, n = 1). `chunk` points at a time (memory ~ 300 bytes each)."""
    pts = torch.as_tensor(np.asarray(points, float) if not torch.is_tensor(points) else points.detach().cpu(),
                          dtype=torch.float64)
    cams = [c for c in cameras if _above(c, water)]
    out = [_view_geometry(pts[s: s + chunk], cams, water) for s in range(0, len(pts), chunk)]
    if not out:
        return ViewGeometry(np.zeros(0), np.zeros(0, np.int64), np.zeros(0), np.zeros(0))
    return ViewGeometry(*(np.concatenate(parts) for parts in zip(*out)))


def _water_steps(water: WaterSurface | None):
    """[(name, water at +step, water at -step, step)] of the water's level and n for central differences (n
    one-sided at 1: n < 1 is not water)."""
    if water is None:
        return []
    lo_n = max(float(water.n) - N_STEP, 1.0)
    return [("level", replace(water, level=float(water.level) + LEVEL_STEP),
             replace(water, level=float(water.level) - LEVEL_STEP), 2 * LEVEL_STEP),
            ("n", replace(water, n=float(water.n) + N_STEP), replace(water, n=lo_n),
             float(water.n) + N_STEP - lo_n)]


def _view_geometry(pts: torch.Tensor, cameras, water: WaterSurface | None):
    G = len(pts)
    info = torch.zeros(G, 3, 3, dtype=pts.dtype)
    views = torch.zeros(G, dtype=torch.int64)
    steps = _water_steps(water)
    rhs = {name: torch.zeros(G, 3, dtype=pts.dtype) for name, *_ in steps}  # sum_i J_i^T g_i
    for cam in cameras:
        center = torch.tensor(cam.camera_center, dtype=pts.dtype)
        apparent = pts if water is None else apparent_points(pts, center, water)
        pixels, z, _ = _project_jacobian(cam, apparent)
        seen = (z > 0) & (pixels[:, 0] >= 0) & (pixels[:, 0] <= cam.width) & (pixels[:, 1] >= 0) \
            & (pixels[:, 1] <= cam.height)
        rows = seen.nonzero().squeeze(1)  # the rest of the work only where the view sees the point
        if not len(rows):
            continue
        p = pts[rows]
        j_app = torch.eye(3, dtype=pts.dtype) if water is None else apparent_jacobian(p, center, water)
        J = _project_jacobian(cam, apparent[rows])[2] @ j_app  # [S, 2, 3]
        info[rows] += J.transpose(1, 2) @ J
        views[rows] += 1
        for name, up, down, h in steps:
            g = (_pixels(cam, p, up) - _pixels(cam, p, down)) / h  # [S, 2] d pixel / d (level or n)
            rhs[name][rows] += (J.transpose(1, 2) @ torch.nan_to_num(g)[..., None])[..., 0]
    # triangulated where two views see the point and the information is not singular to round-off
    eig = torch.linalg.eigvalsh(info)  # [G, 3] ascending
    ok = (views >= 2) & (eig[:, 0] > 1e-12 * eig[:, 2].clamp(min=1e-300))
    cov = torch.full_like(info, math.nan)
    cov[ok] = torch.linalg.inv(info[ok])
    sigma = torch.where(ok, cov[:, 2, 2].clamp(min=0).sqrt(), torch.full_like(eig[:, 0], math.inf))
    slopes = {name: -(cov @ rhs[name][..., None])[:, 2, 0] for name in rhs}
    nan = np.full(G, np.nan)
    return (sigma.numpy(), views.numpy(), slopes["level"].numpy() if "level" in slopes else nan,
            slopes["n"].numpy() if "n" in slopes else nan)


@dataclass(frozen=True)
class CellFeatures:
    """`cell_features` of a bed's G cells (module docstring)."""

    grid: np.ndarray  # [G, 3] the bed's cells
    geometry: np.ndarray  # [G] m per pixel, `GEOMETRY_CAP` where nothing triangulates
    views: np.ndarray  # [G] int
    depth: np.ndarray  # [G] m, 0 on emerged ground
    spread: np.ndarray  # [G] m
    samples: np.ndarray  # [G] int: the filtered samples in the cell
    filled: np.ndarray  # [G] bool
    dz_dlevel: np.ndarray  # [G]
    dz_dn: np.ndarray  # [G]
    systematic: np.ndarray  # [G] m: sigma_sys for the level's and n's standard deviations given

    def matrix(self, names=FEATURES) -> np.ndarray:  # [G, K] the features the model weighs
        cols = {"one": np.ones(len(self.grid)), "geometry": self.geometry, "depth": self.depth,
                "spread": self.spread, "filled": self.filled.astype(np.float64),
                "samples": 1 / np.sqrt(np.maximum(self.samples, 1))}
        unknown = [n for n in names if n not in cols]
        if unknown:
            raise ConfigError(f"unknown uncertainty feature(s) {unknown}; known: {', '.join(cols)}")
        return np.column_stack([cols[n] for n in names])

    def select(self, mask) -> CellFeatures:  # the cells of a mask or index array
        return CellFeatures(**{k: v[mask] for k, v in asdict(self).items()})


def cell_features(grid, cameras, water: WaterSurface | None, cells: dict | None = None,
                  sigma_level: float = 0.0, sigma_n: float = 0.0, chunk: int = 65_536) -> CellFeatures:
    """The features of each cell of a bed `grid` [G, 3] (the extracted cells' points) seen by `cameras`
    (the run's training views) through `water` (the run's); `cells`: the extraction's per-cell record
    (`surface.extract_surface(..., cells=True)`'s stats["cells"]: samples, spread, filled; None: no samples
    known, spread 0 and nothing filled); `sigma_level` (m) and `sigma_n`: the standard deviations of the
    water's level and index the run used, for the systematic term."""
    grid = np.asarray(grid, np.float64)
    geo = view_geometry(grid, cameras, water, chunk)
    depth = np.zeros(len(grid)) if water is None else np.maximum(np.asarray(water.depth(grid), float), 0.0)
    if cells is None:
        samples, spread, filled = (np.zeros(len(grid), np.int64), np.zeros(len(grid)),
                                   np.zeros(len(grid), bool))
    else:
        samples, spread, filled = (np.asarray(cells[k]) for k in ("samples", "spread", "filled"))
        if not len(samples) == len(spread) == len(filled) == len(grid):
            raise ConfigError(f"the extraction's per-cell record has {len(samples)} cells, the bed "
                              f"{len(grid)}")
        known = np.isfinite(spread)
        spread = np.where(known, spread, np.median(spread[known]) if known.any() else 0.0)
    level_term = np.nan_to_num(geo.dz_dlevel) * sigma_level
    n_term = np.nan_to_num(geo.dz_dn) * sigma_n
    return CellFeatures(grid, np.where(np.isfinite(geo.sigma_z), geo.sigma_z, GEOMETRY_CAP), geo.views, depth,
                        spread.astype(np.float64), samples.astype(np.int64), filled.astype(bool),
                        geo.dz_dlevel, geo.dz_dn, np.hypot(level_term, n_term))


# ---------------------------------------------------------------- the model


@dataclass(frozen=True)
class UncertaintyModel:
    """sigma^2 = sum_k weights_k^2 f_k^2 over `features`; TVU95 = Z95 sqrt((scale sigma)^2 + sigma_sys^2)."""

    features: tuple[str, ...]
    weights: tuple[float, ...]  # >= 0, in the units that make w f metres (the geometry's: pixels)
    scale: float = 1.0  # the conformal step's (1: not calibrated)
    coverage: float = 0.95  # what the conformal step was for
    fit_seeds: tuple = ()  # dataset seeds (or other ids) of the cells the weights were fitted on
    calibration_seeds: tuple = ()  # ... the scale was calibrated on
    commit: str | None = None  # the code that made it (the caller's git commit)
    stats: dict = field(default_factory=dict)  # what fit and calibrate report: cells, NLL, quantile rank

    def __post_init__(self):
        for name in ("features", "weights", "fit_seeds", "calibration_seeds"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        if len(self.features) != len(self.weights):
            raise ConfigError(f"{len(self.features)} features and {len(self.weights)} weights")
        if not (all(math.isfinite(w) and w >= 0 for w in self.weights) and self.scale > 0):
            raise ConfigError(f"uncertainty weights must be finite and >= 0, the scale > 0: {self.weights}, "
                              f"{self.scale}")

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=1)

    @classmethod
    def from_json(cls, text: str) -> UncertaintyModel:
        try:
            d = json.loads(text)
            return cls(**d)
        except (ValueError, TypeError) as err:
            raise ConfigError(f"not an uncertainty model: {err}") from None


def _matrix(model_or_names, features) -> np.ndarray:
    names = model_or_names.features if isinstance(model_or_names, UncertaintyModel) else tuple(model_or_names)
    return features.matrix(names) if isinstance(features, CellFeatures) else np.asarray(features, np.float64)


def _systematic(features, systematic) -> np.ndarray | float:
    if systematic is not None:
        return np.asarray(systematic, np.float64)
    return features.systematic if isinstance(features, CellFeatures) else 0.0


def sigma(model: UncertaintyModel, features, systematic=None) -> np.ndarray:
    """[N] the model's calibrated standard deviation (m): TVU95 / Z95. `features`: `CellFeatures` or the
    matrix [N, K] of the model's features (then `systematic` [N] m, default 0)."""
    F = _matrix(model, features)
    stat = F**2 @ np.square(model.weights)
    return np.sqrt(model.scale**2 * stat + np.square(_systematic(features, systematic)))


def tvu95(model: UncertaintyModel, features, systematic=None) -> np.ndarray:
    """[N] the total vertical uncertainty at 95 % (m) of each cell (module docstring)."""
    return Z95 * sigma(model, features, systematic)


def _nll(v, F2, e2, s2):  # mean Gaussian NLL (without the constant) and its gradient in v = w^2 [K]
    var = F2 @ v + s2  # [N]
    nll = 0.5 * np.mean(np.log(var) + e2 / var)
    grad = 0.5 * F2.T @ ((1 / var - e2 / var**2) / len(var))
    return nll, grad


def fit(features, errors, names=FEATURES, seeds=(), systematic=None, commit: str | None = None,
        floor: float = 1e-6) -> UncertaintyModel:
    """The weights that minimise the Gaussian negative log-likelihood of `errors` [N] (predicted - true, m)
    under sigma^2 = sum_k w_k^2 f_k^2 + sigma_sys^2; `features`: `CellFeatures` or the matrix [N, K] of the
    features `names`; `seeds`: which development seeds the cells came from (recorded). Minimised in v = w^2
    >= 0 (L-BFGS-B, analytic gradient: the NLL is smooth there and a feature that explains nothing reaches
    v = 0 exactly). `floor` (m): the least sigma any cell may get, against a zero variance where every feature
    is 0. Raises ConfigError for no finite cells."""
    from scipy.optimize import minimize

    F = _matrix(names, features)
    e = np.asarray(errors, np.float64)
    s2 = np.broadcast_to(np.square(_systematic(features, systematic)), e.shape) + floor**2
    ok = np.isfinite(e) & np.isfinite(F).all(1) & np.isfinite(s2)
    if not ok.any():
        raise ConfigError("no cell with a finite error and features to fit the uncertainty on")
    F2, e2, s2 = F[ok] ** 2, e[ok] ** 2, s2[ok]
    # scaled variables: each column's v in units of mean(e^2) / mean(f^2), so that all start near 1
    unit = np.mean(e2) / np.maximum(F2.mean(0), 1e-300)

    def objective(u):  # [K] scaled -> (NLL, its gradient in u)
        nll, grad = _nll(u * unit, F2, e2, s2)
        return nll, grad * unit

    res = minimize(objective, np.full(F.shape[1], 1.0 / F.shape[1]), jac=True, method="L-BFGS-B",
                   bounds=[(0, None)] * F.shape[1], options={"maxiter": 1000, "ftol": 1e-15, "gtol": 1e-12})
    v = res.x * unit
    return UncertaintyModel(tuple(names), tuple(float(np.sqrt(x)) for x in v), fit_seeds=tuple(seeds),
                            commit=commit, stats={"fit_cells": int(ok.sum()), "fit_nll": float(res.fun),
                                                  "fit_converged": bool(res.success)})


def conformal_rank(n: int, coverage: float) -> int:
    """The split-conformal order statistic (1-based) of n calibration scores: ceil((n + 1) coverage), so that
    a new exchangeable cell is covered with probability >= coverage. Above n: no finite scale guarantees
    it."""
    return math.ceil((n + 1) * coverage - 1e-9)


def calibrate(model: UncertaintyModel, features, errors, seeds=(), systematic=None,
              coverage: float = 0.95) -> UncertaintyModel:
    """`model` with the split-conformal scale c of its statistical term on the calibration cells (another
    development seed than the fit's): each cell's score is the least c for which |e| <= Z95 sqrt((c
    sigma)^2 + sigma_sys^2), and c is the `conformal_rank`-th smallest score, so that TVU95 covers `coverage`
    of the cells (at least: ties and the (n + 1) correction round up). Raises ConfigError with too few
    cells."""
    F = _matrix(model, features)
    e = np.asarray(errors, np.float64)
    stat = np.sqrt(F**2 @ np.square(model.weights))
    sys = np.broadcast_to(_systematic(features, systematic), e.shape)
    ok = np.isfinite(e) & np.isfinite(stat) & (stat > 0)
    n = int(ok.sum())
    k = conformal_rank(n, coverage)
    if k > n:
        raise ConfigError(f"{n} calibration cells cannot give a {coverage:g} conformal interval (need "
                          f">= {math.ceil(coverage / (1 - coverage))})")
    need = np.sqrt(np.maximum((e[ok] / Z95) ** 2 - sys[ok] ** 2, 0.0)) / stat[ok]  # [n] each cell's least c
    c = float(np.partition(need, k - 1)[k - 1])
    return replace(model, scale=max(c, 1e-12), coverage=coverage, calibration_seeds=tuple(seeds),
                   stats={**model.stats, "calibration_cells": n, "conformal_rank": k})

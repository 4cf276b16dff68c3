"""Numerical stability of the refraction transform over the whole domain (`ragsplat stability`).

Cases are drawn per regime (nadir, near-surface, grazing, low camera, deep, n ~ 1, typical survey and the
full domain), each with the camera at (0, 0, H) over the plane z = 0. For every dtype the report gives,
per regime, the apparent-point error relative to |P - C| against a bracketed float64 reference (bisection
on the same Snell geometry, 200 halvings, from the dtype-rounded inputs), NaN/Inf counts in values and in
autograd gradients (w.r.t. x, y, depth, H and n), the worst case's inputs, and in float64 the Jacobian's
relative error against central differences; `passed` says whether every target was met.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import torch

from ragsplat.refraction import apparent_jacobian, apparent_offsets, apparent_points
from ragsplat.water_surface import WaterSurface

DOMAIN = {"r": (0.0, 1e3), "d": (1e-4, 100.0), "H": (0.1, 1e3), "n": (1.0, 1.6)}
TARGETS = {"float64": 1e-10, "float32": 2e-6}
JACOBIAN_TARGET = 1e-6

# regime -> log10 ranges (or linear for n) of (r, d, H, n); r is sampled log-uniformly, then a share set to 0.
REGIMES = {
    "nadir": {"r": (-12, -3), "d": (-4, 2), "H": (-1, 3), "n": (1.0, 1.6), "r_zero": 0.25},
    "near-surface": {"r": (-3, 3), "d": (-4, -2), "H": (-1, 3), "n": (1.0, 1.6)},
    "grazing": {"r": (2, 3), "d": (-4, 2), "H": (-1, 0.5), "n": (1.0, 1.6)},
    "low camera": {"r": (-3, 3), "d": (-4, 2), "H": (-1, -0.5), "n": (1.0, 1.6)},
    "deep": {"r": (-3, 3), "d": (1.5, 2), "H": (-1, 3), "n": (1.0, 1.6)},
    "n ~ 1": {"r": (-3, 3), "d": (-4, 2), "H": (-1, 3), "n": (1.0, 1.0 + 1e-4), "n_one": 0.25},
    "typical survey": {"r": (-1, 2), "d": (-1, 1), "H": (1, 2.1), "n": (1.33, 1.34)},
    "full domain": {"r": (-6, 3), "d": (-4, 2), "H": (-1, 3), "n": (1.0, 1.6), "r_zero": 0.05, "n_one": 0.05},
}


@dataclass
class StabilityConfig:
    cases_per_regime: int = 150_000  # x 8 regimes = 1.2 M per dtype
    dtypes: tuple[str, ...] = ("float64", "float32")
    jacobian_cameras: int = 32  # distinct (H, n) per regime for the float64 Jacobian check
    jacobian_points: int = 128
    seed: int = 0
    chunk: int = 200_000


@dataclass
class RegimeResult:
    cases: int
    max_error: float
    median_error: float
    nan_inf_values: int
    nan_inf_grads: int
    worst: dict
    jacobian_max_rel_error: float | None = None
    passed: bool = field(default=True)


def sample(regime: dict, count: int, gen: torch.Generator):  # -> r, d, H, n [count] float64
    def logu(lo_hi):
        lo, hi = lo_hi
        return 10 ** (lo + (hi - lo) * torch.rand(count, generator=gen, dtype=torch.float64))

    r, d, H = logu(regime["r"]), logu(regime["d"]), logu(regime["H"])
    r = r.clamp(max=DOMAIN["r"][1])
    lo, hi = regime["n"]
    n = lo + (hi - lo) * torch.rand(count, generator=gen, dtype=torch.float64)
    r[torch.rand(count, generator=gen) < regime.get("r_zero", 0.0)] = 0.0
    n[torch.rand(count, generator=gen) < regime.get("n_one", 0.0)] = 1.0
    return r, d, H, n


def reference(r, d, H, n, halvings: int = 200):
    """Float64 bisection for a = tan(theta_a) on H a + d tan(theta_w(a)) = r, bracket [0, r / H].

    Returns (r', d'): the apparent radius and depth.
    """
    lo, hi = torch.zeros_like(r), r / H
    for _ in range(halvings):
        mid = (lo + hi) / 2
        tan_w = mid / torch.sqrt(n * n + (n - 1) * (n + 1) * mid * mid)  # from sin(ta) = n sin(tw)
        short = H * mid + d * tan_w < r
        lo, hi = torch.where(short, mid, lo), torch.where(short, hi, mid)
    return apparent_from_tan_a((lo + hi) / 2, d, H, n)


def apparent_from_tan_a(tan_a, d, H, n):
    """(r', d') on the air ray leaving the camera at tan(theta_a), by the paper's Eq. 5 in angles."""
    tan_w = tan_a / torch.sqrt(n * n + (n - 1) * (n + 1) * tan_a * tan_a)
    cos_ratio2 = (1 + tan_w * tan_w) / (1 + tan_a * tan_a)  # (cos ta / cos tw)^2
    d_app = d * cos_ratio2**1.5 / n
    return tan_a * (H + d_app), d_app


def _errors_and_grads(r, d, H, n, dtype):
    """Relative apparent-point error [N], NaN/Inf counts of values and of gradients, for one chunk."""
    azimuth = torch.linspace(0, 2 * math.pi, len(r), dtype=torch.float64)
    x, y = (r * torch.cos(azimuth)).to(dtype), (r * torch.sin(azimuth)).to(dtype)
    leaves = [t.clone().requires_grad_(True) for t in (x, y, d.to(dtype), H.to(dtype), n.to(dtype))]
    xl, yl, dl, Hl, nl = leaves
    rho, d_app = apparent_offsets(xl * xl + yl * yl, dl, Hl, nl)
    out = torch.stack([rho * xl, rho * yl, -d_app], -1)  # [N, 3] apparent point, camera at (0, 0, H)
    out.sum().backward()
    bad_values = int((~torch.isfinite(out)).any(-1).sum())
    bad_grads = int(sum((~torch.isfinite(t.grad)).sum() for t in leaves))
    # Reference from the rounded inputs the solver actually saw.
    xr, yr, dr, Hr, nr = (t.detach().double() for t in leaves)
    r_in = torch.sqrt(xr * xr + yr * yr)
    r_ref, d_ref = reference(r_in, dr, Hr, nr)
    got = out.detach().double()
    r_got = torch.sqrt(got[:, 0] ** 2 + got[:, 1] ** 2)
    err = torch.sqrt((r_got - r_ref) ** 2 + (got[:, 2] + d_ref) ** 2) / torch.sqrt(r_in**2 + (Hr + dr) ** 2)
    return err, bad_values, bad_grads, (xr, yr, dr, Hr, nr)


def _jacobian_error(regime: dict, cfg: StabilityConfig, gen: torch.Generator) -> float:
    """Max relative error of apparent_jacobian against central differences, float64."""
    worst = 0.0
    for _ in range(cfg.jacobian_cameras):
        r, d, H, n = sample(regime, cfg.jacobian_points, gen)
        cam = torch.tensor([0.0, 0.0, float(H[0])], dtype=torch.float64)
        water = WaterSurface(0.0, float(n[0]))
        az = torch.rand(len(r), generator=gen, dtype=torch.float64) * 2 * math.pi
        p = torch.stack([r * torch.cos(az), r * torch.sin(az), -d], -1)
        J = apparent_jacobian(p, cam, water)
        # Fourth-order central differences: the step must stay well inside the depth and the camera height
        # (the point stays submerged and the map bends on those scales), and a second-order stencil that
        # small drowns in the round-off of coordinates up to 1e3 m.
        h = 5e-3 * torch.minimum(d, H[0])[:, None]
        cols = []
        for k in range(3):
            e = torch.zeros(3, dtype=torch.float64)
            e[k] = 1.0
            f = [apparent_points(p + j * h * e, cam, water) for j in (-2, -1, 1, 2)]
            cols.append((f[0] - 8 * f[1] + 8 * f[2] - f[3]) / (12 * h))
        fd = torch.stack(cols, -1)
        rel = (J - fd).abs().amax(dim=(1, 2)) / J.abs().amax(dim=(1, 2))
        worst = max(worst, float(rel.max()))
    return worst


def run_sweep(cfg: StabilityConfig) -> dict:
    results: dict = {"config": asdict(cfg), "domain": DOMAIN, "targets": TARGETS,
                     "jacobian_target": JACOBIAN_TARGET, "dtypes": {}}
    for dtype_name in cfg.dtypes:
        dtype = getattr(torch, dtype_name)
        per_regime = {}
        for i, (name, regime) in enumerate(REGIMES.items()):
            gen = torch.Generator().manual_seed(cfg.seed * 1000 + i)
            errs, bad_v, bad_g, worst = [], 0, 0, (-1.0, None)
            for start in range(0, cfg.cases_per_regime, cfg.chunk):
                count = min(cfg.chunk, cfg.cases_per_regime - start)
                err, bv, bg, inputs = _errors_and_grads(*sample(regime, count, gen), dtype)
                errs.append(err)
                bad_v += bv
                bad_g += bg
                k = int(torch.nan_to_num(err, nan=math.inf).argmax())
                e = float(err[k]) if torch.isfinite(err[k]) else math.inf
                if e > worst[0]:
                    worst = (e, {key: float(t[k]) for key, t in zip(["x", "y", "depth", "H", "n"], inputs)})
            err = torch.cat(errs)
            jac = _jacobian_error(regime, cfg, gen) if dtype == torch.float64 else None
            ok = worst[0] <= TARGETS[dtype_name] and bad_v == 0 and bad_g == 0
            if jac is not None:
                ok = ok and jac <= JACOBIAN_TARGET
            per_regime[name] = asdict(RegimeResult(len(err), worst[0], float(err.median()), bad_v, bad_g,
                                                   worst[1], jac, ok))
        results["dtypes"][dtype_name] = per_regime
    results["passed"] = all(r["passed"] for d in results["dtypes"].values() for r in d.values())
    return results


def format_table(results: dict) -> str:
    lines = []
    for dtype_name, regimes in results["dtypes"].items():
        lines.append(f"\n{dtype_name}: target max error {TARGETS[dtype_name]:.0e} of |P - C|"
                     + (f", Jacobian vs central differences {JACOBIAN_TARGET:.0e}"
                        if dtype_name == "float64" else ""))
        lines.append(f"{'regime':<15} {'cases':>8} {'max err':>9} {'median':>9} {'NaN/Inf':>8} "
                     f"{'grad NaN':>8} {'Jacobian':>9}  ok  worst case (x, y, depth, H, n)")
        for name, r in regimes.items():
            jac = f"{r['jacobian_max_rel_error']:.1e}" if r["jacobian_max_rel_error"] is not None else "-"
            w = r["worst"] or {}
            worst = ", ".join(f"{w[k]:.4g}" for k in ("x", "y", "depth", "H", "n")) if w else "-"
            lines.append(f"{name:<15} {r['cases']:>8} {r['max_error']:>9.1e} {r['median_error']:>9.1e} "
                         f"{r['nan_inf_values']:>8} {r['nan_inf_grads']:>8} {jac:>9}  "
                         f"{'yes' if r['passed'] else 'NO ':<3} ({worst})")
    lines.append(f"\n{'all targets met' if results['passed'] else 'TARGETS MISSED'}")
    return "\n".join(lines)

"""Error against run time of Snell solvers, and the cost of refract_gaussians (`ragsplat bench refraction`).

Every solver maps the same cases (drawn over the stability domain, see `stability.REGIMES["full domain"]`)
to the apparent point; error is relative to |P - C| against the float64 bisection reference of
`stability.reference`. Solvers:
- `halley-alpha` (the one used): Halley in alpha = tan(theta_a)/r from the larger closed-form lower bound,
  plus the tracked Newton step, at 1..6 iterations;
- `newton-alpha`: Newton on the same unknown and start, 1..6 iterations;
- `newton-s`: Newton on the paper's quartic in s from the paraxial guess s = r H / (H + d/n), 6 iterations;
- `ferrari`: the quartic's closed-form roots (complex arithmetic), keeping the real root in [0, r] where
  Snell's residual is smallest; its leading coefficient 1 - n^2 vanishes at n = 1;
- `bisection-alpha`: plain bisection on the alpha equation, 30 and 60 halvings.
"""

from __future__ import annotations

import functools
import statistics
import time

import torch

from ragsplat_core.bench.stability import REGIMES, apparent_from_tan_a, reference, sample
from ragsplat_core.refraction import SOLVER_STEPS, WaterSurface, apparent_offsets, refract_gaussians


def _apparent_from_alpha(alpha, r2, d, H, n):  # -> r', d'
    D = torch.sqrt(n * n + (n - 1) * (n + 1) * r2 * alpha * alpha)
    d_app = d * n * n / D**3
    return alpha * (H + d_app) * torch.sqrt(r2), d_app


def halley_alpha(r, d, H, n, steps):
    rho, d_app = apparent_offsets(r * r, d, H, n, steps)
    return rho * r, d_app


def newton_alpha(r, d, H, n, steps):
    r2, n2, m2 = r * r, n * n, (n - 1) * (n + 1)
    rm = torch.sqrt(r2 * m2)
    alpha = torch.maximum(1 / (H + d / n), (rm - d) / (H * torch.clamp(rm, min=torch.finfo(r.dtype).tiny)))
    for _ in range(steps):
        D = torch.sqrt(n2 + m2 * r2 * alpha * alpha)
        alpha = alpha - (alpha * (H + d / D) - 1) / (H + d * n2 / D**3)
    return _apparent_from_alpha(alpha, r2, d, H, n)


def _quartic(r, d, H, n):  # coefficients of the paper's Eq. 2, highest first, z = -d
    n2 = n * n
    return (1 - n2, 2 * (n2 - 1) * r, (1 - n2) * r * r - n2 * H * H + d * d, 2 * n2 * H * H * r, -n2 * H * H * r * r)


def newton_s(r, d, H, n, steps):
    a4, a3, a2, a1, a0 = _quartic(r, d, H, n)
    s = r * H / (H + d / n)
    for _ in range(steps):
        f = (((a4 * s + a3) * s + a2) * s + a1) * s + a0
        df = ((4 * a4 * s + 3 * a3) * s + 2 * a2) * s + a1
        s = s - f / df
    return apparent_from_tan_a(s / H, d, H, n)


def ferrari(r, d, H, n, steps=None):
    a4, a3, a2, a1, a0 = _quartic(r, d, H, n)
    cdtype = torch.complex128 if r.dtype == torch.float64 else torch.complex64
    b, c, e, f = (x.to(cdtype) / a4.to(cdtype) for x in (a3, a2, a1, a0))
    # Depressed quartic y^4 + p y^2 + q y + t with s = y - b/4, solved through its resolvent cubic.
    p = c - 3 * b * b / 8
    q = b**3 / 8 - b * c / 2 + e
    t = -3 * b**4 / 256 + b * b * c / 16 - b * e / 4 + f
    # Resolvent m^3 + p m^2 + (p^2/4 - t) m - q^2/8 = 0, by Cardano.
    A, B, C = p, p * p / 4 - t, -q * q / 8
    P = B - A * A / 3
    Q = 2 * A**3 / 27 - A * B / 3 + C
    root = torch.sqrt(Q * Q / 4 + P**3 / 27)
    u = (-Q / 2 + root) ** (1 / 3)
    u = torch.where(u.abs() == 0, (-Q / 2 - root) ** (1 / 3), u)
    m = u - P / (3 * u) - A / 3
    sq = torch.sqrt(2 * m)
    best = None
    for sign in (1, -1):
        disc = torch.sqrt(-(2 * p + 2 * m + sign * 2 * q / sq))
        for pm in (1, -1):
            s = ((sign * sq + pm * disc) / 2 - b / 4).real.to(r.dtype)
            ok = (s >= 0) & (s <= r)
            tan_w = (r - s) / d
            residual = torch.abs(s / torch.sqrt(s * s + H * H) - n * tan_w / torch.sqrt(1 + tan_w * tan_w))
            residual = torch.where(ok, residual, torch.full_like(residual, float("inf")))
            if best is None:
                best, best_s = residual, s
            else:
                better = residual < best
                best, best_s = torch.where(better, residual, best), torch.where(better, s, best_s)
    return apparent_from_tan_a(best_s / H, d, H, n)


def bisection_alpha(r, d, H, n, steps):
    lo, hi = torch.zeros_like(r), 1 / H  # bracket of alpha
    r2 = r * r
    for _ in range(steps):
        mid = (lo + hi) / 2
        short = mid * (H + d / torch.sqrt(n * n + (n - 1) * (n + 1) * r2 * mid * mid)) < 1
        lo, hi = torch.where(short, mid, lo), torch.where(short, hi, mid)
    return _apparent_from_alpha((lo + hi) / 2, r2, d, H, n)


SOLVERS = [("halley-alpha", halley_alpha, range(1, 7)), ("newton-alpha", newton_alpha, range(1, 7)),
           ("newton-s", newton_s, [6]), ("ferrari", ferrari, [None]), ("bisection-alpha", bisection_alpha, [30, 60])]


def _median_time(fn, repeats):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def solver_table(cases: int, repeats: int, seed: int) -> list[dict]:
    gen = torch.Generator().manual_seed(seed)
    r, d, H, n = sample(REGIMES["full domain"], cases, gen)
    rows = []
    for dtype in (torch.float32, torch.float64):
        inputs = [x.to(dtype) for x in (r, d, H, n)]
        r_ref, d_ref = reference(*(x.double() for x in inputs))
        dist = torch.sqrt(inputs[0].double() ** 2 + (inputs[1].double() + inputs[2].double()) ** 2)
        for name, fn, steps_list in SOLVERS:
            for steps in steps_list:
                with torch.no_grad():
                    r_app, d_app = fn(*inputs, steps)
                    err = torch.sqrt((r_app.double() - r_ref) ** 2 + (d_app.double() - d_ref) ** 2) / dist
                    seconds = _median_time(functools.partial(fn, *inputs, steps), repeats)
                bad = int((~torch.isfinite(err)).sum())
                finite = err[torch.isfinite(err)]
                rows.append({"dtype": str(dtype).removeprefix("torch."), "solver": name, "steps": steps,
                             "max_error": float(finite.max()) if len(finite) else float("nan"),
                             "non_finite": bad, "mpoints_per_s": cases / seconds / 1e6})
    return rows


def transform_table(sizes, repeats: int, seed: int) -> list[dict]:
    """Full position + isotropic scale + opacity transform, float32, with and without autograd."""
    gen = torch.Generator().manual_seed(seed)
    water = WaterSurface(0.0, 1.33)
    cam = torch.tensor([0.0, 0.0, 40.0])
    rows = []
    for size in sizes:
        means = torch.cat([(torch.rand(size, 2, generator=gen) - 0.5) * 60, -10 - torch.rand(size, 1, generator=gen)], 1)
        scales = torch.rand(size, 3, generator=gen) * 0.05 + 0.01
        quats = torch.nn.functional.normalize(torch.randn(size, 4, generator=gen), dim=-1)
        opac = torch.rand(size, generator=gen)
        colors = torch.rand(size, 3, generator=gen)
        with torch.no_grad():
            fwd = _median_time(functools.partial(refract_gaussians, means, scales, quats, opac, colors, cam, water),
                               repeats)
        leaves = [t.clone().requires_grad_(True) for t in (means, scales, opac)]

        def fwd_bwd(leaves=leaves, quats=quats, colors=colors):
            out = refract_gaussians(leaves[0], leaves[1], quats, leaves[2], colors, cam, water)
            (out.means.sum() + out.scales.sum() + out.opacities.sum()).backward()

        both = _median_time(fwd_bwd, repeats)
        rows.append({"gaussians": size, "forward_s": fwd, "forward_mgaussians_per_s": size / fwd / 1e6,
                     "forward_backward_s": both, "forward_backward_mgaussians_per_s": size / both / 1e6})
    return rows


def format_tables(solvers: list[dict], transform: list[dict]) -> str:
    lines = [f"{'dtype':<8} {'solver':<16} {'steps':>5} {'max error':>10} {'non-finite':>10} {'M points/s':>10}"]
    for row in solvers:
        steps = "-" if row["steps"] is None else row["steps"]
        lines.append(f"{row['dtype']:<8} {row['solver']:<16} {steps:>5} {row['max_error']:>10.2e} "
                     f"{row['non_finite']:>10} {row['mpoints_per_s']:>10.2f}")
    lines.append(f"\nrefract_gaussians, float32, position + isotropic scale + opacity "
                 f"(chosen solver: {SOLVER_STEPS[torch.float32]} Halley steps + 1 tracked Newton step)")
    lines.append(f"{'gaussians':>10} {'forward s':>10} {'M/s':>7} {'fwd+bwd s':>10} {'M/s':>7}")
    for row in transform:
        lines.append(f"{row['gaussians']:>10} {row['forward_s']:>10.4f} {row['forward_mgaussians_per_s']:>7.2f} "
                     f"{row['forward_backward_s']:>10.4f} {row['forward_backward_mgaussians_per_s']:>7.2f}")
    return "\n".join(lines)

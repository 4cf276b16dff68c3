"""Error against run time of Snell solvers, and the cost of refract_gaussians (`ragsplat bench refraction`).

Every solver maps the same cases (drawn over the stability domain, see `stability.REGIMES["full domain"]`)
to the apparent point; error is relative to |P - C| against the float64 bisection reference of
`stability.reference`. All solvers are vectorised torch in float32 or float64 with a fixed amount of work
per call (no tolerance test, no data-dependent early exit); per-element choices are `torch.where`. Solvers:
- `halley-alpha` (the one used): Halley in alpha = tan(theta_a)/r from the larger closed-form lower bound,
  plus the tracked Newton step, at 1..6 iterations;
- `newton-alpha`: Newton on the same unknown and start, 1..6 iterations, no bracket;
- `newton-s-bracketed`: safeguarded Newton (bisection fallback) in the interface offset s on the factored
  Snell equation, bracketed by closed-form bounds, 3..6 iterations (`newton_s`);
- `ferrari-scaled`: Ferrari's closed form for the quartic in a scaled leg ratio, with the cancelling terms
  rewritten and the root picked in [0, 1] (`ferrari`);
- `bisection-alpha`: plain bisection on the alpha equation, 30 and 60 halvings.
"""

from __future__ import annotations

import functools
import statistics
import time

import torch

from ragsplat.bench.stability import REGIMES, apparent_from_tan_a, reference, sample
from ragsplat.refraction import SOLVER_STEPS, apparent_offsets, refract_gaussians
from ragsplat.water_surface import WaterSurface


def _apparent_from_alpha(alpha, r2, d, H, n):  # -> r', d'
    D = torch.sqrt(n * n + (n - 1) * (n + 1) * r2 * alpha * alpha)
    d_app = d * n * n / D**3
    return alpha * (H + d_app) * torch.sqrt(r2), d_app


def halley_alpha(r, d, H, n, steps):
    """The project's solver (`refraction.apparent_offsets`): `steps` Halley steps in alpha = tan(theta_a) / r
    from the larger of the paraxial and grazing lower bounds, clamped to [lower bound, 1/H], then one Newton
    step (the one that carries gradients); returns (r', d')."""
    rho, d_app = apparent_offsets(r * r, d, H, n, steps)
    return rho * r, d_app


def newton_alpha(r, d, H, n, steps):
    """`steps` plain Newton steps on g(alpha) = alpha (H + d / D) - 1 from the same lower bound as
    `halley_alpha`, no bracket or clamp; returns (r', d')."""
    r2, n2, m2 = r * r, n * n, (n - 1) * (n + 1)
    rm = torch.sqrt(r2 * m2)
    alpha = torch.maximum(1 / (H + d / n), (rm - d) / (H * torch.clamp(rm, min=torch.finfo(r.dtype).tiny)))
    for _ in range(steps):
        D = torch.sqrt(n2 + m2 * r2 * alpha * alpha)
        alpha = alpha - (alpha * (H + d / D) - 1) / (H + d * n2 / D**3)
    return _apparent_from_alpha(alpha, r2, d, H, n)


# -> lo, hi: closed-form bounds on the interface offset s, 0 <= lo <= s <= hi <= r
def _bracket_s(r, d, H, n):
    m2 = (n - 1) * (n + 1)  # n^2 - 1 without cancellation near n = 1
    rm, nH = r * torch.sqrt(m2), n * H
    paraxial = nH / (nH + d)  # tan(theta_w) <= tan(theta_a) / n
    grazing = (rm - d) / torch.clamp(rm, min=torch.finfo(r.dtype).tiny)  # tan(theta_w) < 1 / sqrt(n^2 - 1)
    lo = r * torch.maximum(paraxial, grazing)
    S = torch.sqrt(nH * nH + rm * rm)
    chord = r * S / (S + d)  # tan(theta_w) is concave in tan(theta_a): above its chord on [0, r / H]
    return lo, torch.maximum(chord, lo)


def newton_s(r, d, H, n, steps):
    """Bracketed (safeguarded) Newton for the interface offset s; exactly `steps` iterations, no tolerance
    test.

    Unknown: s = H tan(theta_a), the horizontal distance from the camera nadir to the refraction point, in
    [0, r]. Snell's law sin(theta_a) = n sin(theta_w) with sin(theta_a) = s / sqrt(s^2 + H^2) and
    sin(theta_w) = (r - s) / sqrt((r - s)^2 + d^2), squared, (r - s)^2 factored out and the positive root
    taken:

        f(s) = s d - (r - s) sqrt((n - 1)(n + 1) s^2 + n^2 H^2) = 0,

    never expanded into quartic coefficients. f(0) = -r n H <= 0 <= f(r) = r d and f has one root in [0, r],
    so f < 0 left of it and f > 0 right of it. Bracket (`_bracket_s`): lo = r max(n H / (n H + d),
    1 - d / (r sqrt(n^2 - 1))) (paraxial and grazing bounds), hi = r S / (S + d) with
    S = sqrt(n^2 H^2 + (n^2 - 1) r^2) (chord bound). Start at lo. Each iteration evaluates f and f' once,
    moves lo or hi to s by the sign of f, and takes the Newton step; a step landing outside [lo, hi] by more
    than 4 eps hi (rounding) is replaced by the midpoint (bisection), one inside that margin is clipped to
    [lo, hi]. r = 0 gives lo = hi = 0, so s = 0 (the vertical ray) exactly; n = 1 gives lo = hi = r H / (H +
    d) (the straight line). Returns (r', d') from tan(theta_a) = s / H by `stability.apparent_from_tan_a`.
    """
    lo, hi = _bracket_s(r, d, H, n)
    m2, nH2 = (n - 1) * (n + 1), (n * H) ** 2
    slack = 4 * torch.finfo(r.dtype).eps * hi
    s = lo
    for _ in range(steps):
        q = torch.sqrt(m2 * s * s + nH2)
        t = r - s
        f = s * d - t * q
        lo, hi = torch.where(f < 0, s, lo), torch.where(f > 0, s, hi)
        step = s - f * q / ((d + q) * q - m2 * s * t)  # f / f', f' = d + q - (r - s) (n^2 - 1) s / q
        clipped = torch.clamp(step, lo, hi)
        # Outside the bracket by more than the slack, or NaN (f' = 0): bisect.
        s = torch.where((step - clipped).abs() <= slack, clipped, (lo + hi) / 2)
    return apparent_from_tan_a(s / H, d, H, n)


def _largest_cubic_root(a2, a1, a0):
    """Largest real root of y^3 + a2 y^2 + a1 y + a0: Cardano (one real root) or Viete (three), y scaled
    first."""
    scale = torch.maximum(torch.maximum(a2.abs(), a1.abs().sqrt()), a0.abs() ** (1 / 3))
    # y = scale * v, coefficients of v in [-1, 1]
    scale = torch.where(scale > 0, scale, torch.ones_like(scale))
    b2, b1, b0 = a2 / scale, a1 / scale**2, a0 / scale**3
    shift = b2 / 3  # v = u - shift: u^3 + p u + q = 0
    p = b1 - b2 * shift
    q = b0 - b1 * shift + 2 * shift**3
    disc = (q / 2) ** 2 + (p / 3) ** 3
    A = -torch.where(q >= 0, 1.0, -1.0).to(q.dtype) * (q.abs() / 2 + torch.sqrt(disc.clamp(min=0))) ** (1 / 3)
    # no cancellation in A
    one = torch.where(A != 0, A - p / (3 * torch.where(A != 0, A, 1)), torch.zeros_like(A))
    m = torch.sqrt((-p / 3).clamp(min=0))
    three = 2 * m * torch.cos(torch.acos((-q / 2 / torch.where(m > 0, m**3, 1)).clamp(-1, 1)) / 3)
    return scale * (torch.where(disc >= 0, one, three) - shift)


def _quadratic_roots(p, q):  # x^2 + p x + q: both roots (NaN when complex), the small one as q / big
    root = torch.sqrt(p * p - 4 * q)
    big = -(p + torch.where(p >= 0, root, -root)) / 2
    return big, q / big


def ferrari(r, d, H, n, steps=None):
    """Ferrari's closed form for Snell's quartic in a scaled leg ratio; no iteration, no polish (`steps`
    unused).

    With a = d, b = n H, c = sqrt((n - 1)(n + 1)) r and w = s / (r - s) (air leg over water leg,
    horizontally), the squared Snell equation of `newton_s` is a^2 w^2 (1 + w)^2 = c^2 w^2 + b^2 (1 + w)^2,
    with one root w >= 0, and w <= 1 exactly when 4 a^2 >= c^2 + 4 b^2. The solve takes x = w there and x =
    1/w otherwise, so the wanted x is in [0, 1], and divides by a^2 (resp. b^2), which makes it dimensionless:

        x^4 + 2 x^3 + C x^2 - 2 k x - k = 0,  k = (b/a)^2, C = 1 - k - (c/a)^2
        (resp. k = (a/b)^2, C = 1 - k + (c/b)^2).

    Ferrari: y is the largest real root of the resolvent y^3 - C y^2 - K = 0, K = 4 k (C + k - 1) written as
    -4 k (c/a)^2 (resp. +4 k (c/b)^2), by `_largest_cubic_root`; then the quartic is
    (x^2 + (1 - alpha) x + y/2 - beta)(x^2 + (1 + alpha) x + y/2 + beta) with
    beta = sign(y + 2k) sqrt(y^2/4 + k) and alpha = sqrt(1 + K/y^2) where that is >= 1/2, else
    alpha = (y + 2k) / (2 beta) (so neither is the square root of a cancelled difference). Cancelling
    coefficients are rewritten: 1 - alpha = -(K/y^2) / (1 + alpha) for alpha >= 1/2, and of the two constant
    terms the one without cancellation is computed and the other from their product -k (Vieta). Each quadratic
    is solved in the stable form; of the (up to four) real roots the one nearest to [0, 1] is kept, then s = r
    x / (1 + x) (resp. r / (1 + x)). c = 0 (n = 1 or r = 0) makes the quartic degenerate: there s = r n H / (n
    H + d), the straight line at n = 1 and s = 0 (the vertical ray) at r = 0. Returns (r', d') as `newton_s`
    does.
    """
    a, b, c = d, n * H, torch.sqrt((n - 1) * (n + 1)) * r
    small = 4 * a * a >= c * c + 4 * b * b  # the root has w <= 1: solve in w, else in 1/w
    big, other = torch.where(small, a, b), torch.where(small, b, a)
    k = (other / big) ** 2
    sign = torch.where(small, -1.0, 1.0).to(r.dtype)
    cb2 = (c / big) ** 2
    C = 1 - k + sign * cb2
    K = 4 * k * cb2 * sign
    y = _largest_cubic_root(-C, torch.zeros_like(C), -K)
    delta = K / (y * y)  # = y - C, from the resolvent, without subtracting
    g = y + 2 * k  # = 2 alpha beta
    beta = torch.where(g >= 0, 1.0, -1.0).to(r.dtype) * torch.sqrt(y * y / 4 + k)
    alpha_sqrt = torch.sqrt((1 + delta).clamp(min=0))
    alpha = torch.where(alpha_sqrt >= 0.5, alpha_sqrt, g / (2 * beta))
    p1 = torch.where(alpha >= 0.5, -delta / (1 + alpha), 1 - alpha)
    p2 = 1 + alpha
    same = (y >= 0) == (beta >= 0)
    q_direct = y / 2 + torch.where(same, beta, -beta)  # y/2 + beta or y/2 - beta, whichever adds magnitudes
    q_vieta = -k / q_direct
    q1, q2 = torch.where(same, q_vieta, q_direct), torch.where(same, q_direct, q_vieta)
    roots = torch.stack([*_quadratic_roots(p1, q1), *_quadratic_roots(p2, q2)])
    outside = torch.where(torch.isnan(roots), torch.inf, (-roots).clamp(min=0) + (roots - 1).clamp(min=0))
    x = roots.gather(0, outside.argmin(0)[None])[0]
    s = torch.where(small, r * x / (1 + x), r / (1 + x))
    s = torch.where(c == 0, r * b / (b + d), s)
    return apparent_from_tan_a(s / H, d, H, n)


def bisection_alpha(r, d, H, n, steps):
    """`steps` halvings of the bracket [0, 1/H] of alpha on the sign of g(alpha); the midpoint; returns (r',
    d')."""
    lo, hi = torch.zeros_like(r), 1 / H  # bracket of alpha
    r2 = r * r
    for _ in range(steps):
        mid = (lo + hi) / 2
        short = mid * (H + d / torch.sqrt(n * n + (n - 1) * (n + 1) * r2 * mid * mid)) < 1
        lo, hi = torch.where(short, mid, lo), torch.where(short, hi, mid)
    return _apparent_from_alpha((lo + hi) / 2, r2, d, H, n)


SOLVERS = [("halley-alpha", halley_alpha, range(1, 7)), ("newton-alpha", newton_alpha, range(1, 7)),
           ("newton-s-bracketed", newton_s, range(3, 7)), ("ferrari-scaled", ferrari, [None]),
           ("bisection-alpha", bisection_alpha, [30, 60])]


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
        means = torch.cat([(torch.rand(size, 2, generator=gen) - 0.5) * 60,
                           -10 - torch.rand(size, 1, generator=gen)], 1)
        scales = torch.rand(size, 3, generator=gen) * 0.05 + 0.01
        quats = torch.nn.functional.normalize(torch.randn(size, 4, generator=gen), dim=-1)
        opac = torch.rand(size, generator=gen)
        colors = torch.rand(size, 3, generator=gen)
        with torch.no_grad():
            fwd = _median_time(
                functools.partial(refract_gaussians, means, scales, quats, opac, colors, cam, water), repeats)
        leaves = [t.clone().requires_grad_(True) for t in (means, scales, opac)]

        def fwd_bwd(leaves=leaves, quats=quats, colors=colors):
            out = refract_gaussians(leaves[0], leaves[1], quats, leaves[2], colors, cam, water)
            (out.means.sum() + out.scales.sum() + out.opacities.sum()).backward()

        both = _median_time(fwd_bwd, repeats)
        rows.append({"gaussians": size, "forward_s": fwd, "forward_mgaussians_per_s": size / fwd / 1e6,
                     "forward_backward_s": both, "forward_backward_mgaussians_per_s": size / both / 1e6})
    return rows


def format_tables(solvers: list[dict], transform: list[dict]) -> str:
    lines = [(f"{'dtype':<8} {'solver':<18} {'steps':>5} {'max error':>10} {'non-finite':>10} "
              f"{'M points/s':>10}")]
    for row in solvers:
        steps = "-" if row["steps"] is None else row["steps"]
        lines.append(f"{row['dtype']:<8} {row['solver']:<18} {steps:>5} {row['max_error']:>10.2e} "
                     f"{row['non_finite']:>10} {row['mpoints_per_s']:>10.2f}")
    lines.append(f"\nrefract_gaussians, float32, position + isotropic scale + opacity "
                 f"(chosen solver: {SOLVER_STEPS[torch.float32]} Halley steps + 1 tracked Newton step)")
    lines.append(f"{'gaussians':>10} {'forward s':>10} {'M/s':>7} {'fwd+bwd s':>10} {'M/s':>7}")
    for row in transform:
        lines.append(f"{row['gaussians']:>10} {row['forward_s']:>10.4f} "
                     f"{row['forward_mgaussians_per_s']:>7.2f} {row['forward_backward_s']:>10.4f} "
                     f"{row['forward_backward_mgaussians_per_s']:>7.2f}")
    return "\n".join(lines)

"""The benchmark's alternative Snell solvers, checked against physics and the float64 bisection reference.

Geometry: camera centre at height H over the plane, a point at horizontal distance r and depth d, index n.
Every solver returns (r', d'), the apparent point; errors are relative to |P - C| = sqrt(r^2 + (H + d)^2).
"""

import pytest
import torch

from ragsplat.bench import refraction as bench
from ragsplat.bench.stability import REGIMES, apparent_from_tan_a, reference, sample

# (solver, steps) as the benchmark runs them at float64 round-off; halley_alpha is the project's solver.
SOLVERS = [(bench.newton_s, 6), (bench.ferrari, None), (bench.bisection_alpha, 60), (bench.halley_alpha, 4)]
IDS = ["newton_s", "ferrari", "bisection_alpha", "halley_alpha"]
TOLERANCE = {torch.float64: 1e-12, torch.float32: 2e-6}  # measured: ~1e-15 and ~6e-7


def _special_cases(dtype):
    """Hand-picked r, d, H, n: nadir (r = 0), pinhole (n = 1), grazing (r >> H), near-surface (d = 1e-4),
    both."""
    rows = [(0.0, 5.0, 10.0, 1.33), (0.0, 1e-4, 0.1, 1.6), (7.0, 3.0, 2.0, 1.0), (1e3, 100.0, 0.1, 1.0),
            (1e3, 1.0, 0.1, 1.33), (1e3, 100.0, 0.1, 1.6), (500.0, 0.5, 0.2, 1.0 + 1e-6),
            (50.0, 1e-4, 1e3, 1.33), (1e3, 1e-4, 0.1, 1.5), (1e-6, 1e-4, 1e3, 1.33), (1e-12, 100.0, 0.1, 1.2)]
    return [torch.tensor(col, dtype=dtype) for col in zip(*rows)]


def _cases(dtype):
    """A few hundred random cases per regime (r = 0 and n = 1 included) plus the special ones."""
    gen = torch.Generator().manual_seed(7)
    parts = [sample(REGIMES[name], 400, gen) for name in
             ("full domain", "nadir", "grazing", "near-surface", "low camera", "deep", "n ~ 1")]
    cols = [torch.cat([p[i] for p in parts]).to(dtype) for i in range(4)]
    return [torch.cat([c, s]) for c, s in zip(cols, _special_cases(dtype))]


def _error(out, r, d, H, n):
    """Relative apparent-point error against the float64 bisection reference from the same (rounded)
    inputs."""
    r, d, H, n = (x.double() for x in (r, d, H, n))
    r_ref, d_ref = reference(r, d, H, n)
    r_app, d_app = (x.double() for x in out)
    return torch.sqrt((r_app - r_ref) ** 2 + (d_app - d_ref) ** 2) / torch.sqrt(r * r + (H + d) ** 2)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
@pytest.mark.parametrize(("fn", "steps"), SOLVERS, ids=IDS)
def test_solver_matches_bisection_reference(fn, steps, dtype):
    cases = _cases(dtype)
    with torch.no_grad():
        out = fn(*cases, steps)
    assert all(x.dtype == dtype for x in out)
    err = _error(out, *cases)
    assert bool(torch.isfinite(err).all()), fn.__name__
    assert float(err.max()) < TOLERANCE[dtype], (fn.__name__, float(err.max()))


@pytest.mark.parametrize(("fn", "steps"), SOLVERS[:3], ids=IDS[:3])
def test_baselines_agree_with_the_project_solver(fn, steps):
    cases = _cases(torch.float64)
    r, d, H, _ = cases
    (ra, da), (rb, db) = fn(*cases, steps), bench.halley_alpha(*cases, 4)
    err = torch.sqrt((ra - rb) ** 2 + (da - db) ** 2) / torch.sqrt(r * r + (H + d) ** 2)
    assert float(err.max()) < 1e-12


@pytest.mark.parametrize(("fn", "steps"), SOLVERS, ids=IDS)
def test_output_obeys_snell(fn, steps):
    """The interface point implied by (r', d') satisfies sin(theta_a) = n sin(theta_w)."""
    cases = _cases(torch.float64)
    r, d, H, n = (x[cases[0] > 0] for x in cases)
    r_app, d_app = fn(r, d, H, n, steps)
    s = r_app * H / (H + d_app)  # where the straight air ray to the apparent point crosses the plane
    sin_a = s / torch.sqrt(s * s + H * H)
    sin_w = (r - s) / torch.sqrt((r - s) ** 2 + d * d)
    assert float((sin_a - n * sin_w).abs().max()) < 1e-9


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
@pytest.mark.parametrize(("fn", "steps"), SOLVERS, ids=IDS)
def test_pinhole_and_nadir(fn, steps, dtype):
    """n = 1: no refraction, the apparent point is the point. r = 0: the vertical ray, r' = 0 and d' = d /
    n."""
    gen = torch.Generator().manual_seed(3)
    r, d, H, _ = (x.to(dtype) for x in sample(REGIMES["full domain"], 500, gen))
    r_app, d_app = fn(r, d, H, torch.ones_like(r), steps)
    scale = torch.sqrt(r.double() ** 2 + (H.double() + d.double()) ** 2)
    eps = torch.finfo(dtype).eps
    assert float(((r_app.double() - r.double()).abs() / scale).max()) < 8 * eps
    assert float(((d_app.double() - d.double()).abs() / scale).max()) < 8 * eps
    n = 1 + 0.6 * torch.rand(500, generator=gen, dtype=torch.float64).to(dtype)
    r_app, d_app = fn(torch.zeros_like(r), d, H, n, steps)
    assert bool((r_app == 0).all())
    assert float(((d_app - d / n).abs() / d).max()) < 8 * eps


@pytest.mark.parametrize(("fn", "steps"), SOLVERS, ids=IDS)
def test_equal_legs_case(fn, steps):
    """A case built so that the refraction point is at s = r / 2 (where ferrari switches from w to 1/w)."""
    r, H, n = (torch.tensor(x, dtype=torch.float64)
               for x in ([2.0, 2.0, 60.0], [1.0, 1e-3, 3.0], [1.33, 1.6, 1.01]))
    # sin(theta_a) = n sin(theta_w) with both legs r / 2 wide: d^2 = n^2 (r^2 / 4 + H^2) - r^2 / 4.
    d = torch.sqrt(n * n * (r * r / 4 + H * H) - r * r / 4)
    r_exp, d_exp = apparent_from_tan_a(r / 2 / H, d, H, n)
    r_app, d_app = fn(r, d, H, n, steps)
    scale = torch.sqrt(r * r + (H + d) ** 2)
    assert float((torch.sqrt((r_app - r_exp) ** 2 + (d_app - d_exp) ** 2) / scale).max()) < 1e-13


def test_newton_bracket_contains_the_root():
    """The closed-form bounds (paraxial, grazing, chord) enclose the reference refraction point."""
    r, d, H, n = _cases(torch.float64)
    lo, hi = bench._bracket_s(r, d, H, n)
    r_ref, d_ref = reference(r, d, H, n)
    s = r_ref * H / (H + d_ref)
    slack = 1e-12 * r
    assert bool((lo <= hi).all()) and bool((0 <= lo).all()) and bool((hi <= r).all())
    assert bool((lo <= s + slack).all()) and bool((s <= hi + slack).all())


def test_newton_converges_with_steps():
    cases = _cases(torch.float64)
    errors = [float(_error(bench.newton_s(*cases, k), *cases).max()) for k in (2, 4, 6)]
    assert errors[0] > errors[1] > 1e-14 > errors[2]


def test_solver_table_rows():
    rows = bench.solver_table(cases=500, repeats=1, seed=0)
    names = {row["solver"] for row in rows}
    assert (names == {"halley-alpha", "newton-alpha", "newton-s-bracketed", "ferrari-scaled",
                      "bisection-alpha"})
    final = {(row["dtype"], row["solver"]): row for row in rows
             if row["steps"] in (None, 6, 60) and row["solver"] != "newton-alpha"}
    for (dtype, name), row in final.items():
        assert row["non_finite"] == 0, name
        assert row["max_error"] < (1e-12 if dtype == "float64" else 2e-6), (dtype, name, row["max_error"])
    assert "ferrari-scaled" in bench.format_tables(rows, [])

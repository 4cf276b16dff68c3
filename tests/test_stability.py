"""The stability sweep and the benchmark's alternative solvers, at a size that runs in seconds."""

import torch

from ragsplat.bench import refraction as bench
from ragsplat.bench.stability import REGIMES, StabilityConfig, reference, run_sweep, sample


def test_sweep_meets_targets_in_every_regime():
    results = run_sweep(StabilityConfig(cases_per_regime=3000, jacobian_cameras=4, jacobian_points=64,
                                        seed=1))
    failed = [(dt, name) for dt, regimes in results["dtypes"].items() for name, r in regimes.items()
              if not r["passed"]]
    assert not failed, failed
    assert set(results["dtypes"]["float64"]) == set(REGIMES)


def test_reference_obeys_snell():
    r, d, H, n = sample(REGIMES["full domain"], 1000, torch.Generator().manual_seed(0))
    r_app, d_app = reference(r, d, H, n)
    # Interface point: where the air ray to the apparent point crosses the plane.
    s = r_app * H / (H + d_app)
    sin_a = s / torch.sqrt(s * s + H * H)
    sin_w = (r - s) / torch.sqrt((r - s) ** 2 + d * d)
    assert float((sin_a - n * sin_w).abs().max()) < 1e-9


def test_alternative_solvers_agree_on_typical_survey_cases():
    r, d, H, n = sample(REGIMES["typical survey"], 2000, torch.Generator().manual_seed(2))
    r_ref, d_ref = reference(r, d, H, n)
    assert int((r > 2 * H).sum()) > 0  # steep views included: the careful baselines must hold there too
    for fn, steps in [(bench.newton_s, 6), (bench.ferrari, None), (bench.bisection_alpha, 60),
                      (bench.newton_alpha, 6), (bench.halley_alpha, 3)]:
        r_app, d_app = fn(r, d, H, n, steps)
        err = torch.sqrt((r_app - r_ref) ** 2 + (d_app - d_ref) ** 2) / torch.sqrt(r * r + (H + d) ** 2)
        assert float(err.max()) < 1e-8, fn.__name__

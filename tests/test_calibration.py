"""The calibration figures of a per-cell uncertainty (eval/calibration.py) on draws of known calibration."""

import numpy as np
import pytest
from scipy.stats import norm

from ragsplat.eval.calibration import (
    calibration_report,
    constant_width,
    coverage,
    depth_bins,
    ence,
    iho_shares,
    local_rms,
    oracle_tvu95,
    reliability_figure,
    view_bins,
    worst_bin,
    z_level,
    z_variance,
)
from ragsplat.scoring import tvu
from ragsplat.uncertainty import Z95

N = 200_000


def cells(rng, n=N, seeds=5):
    """Synthetic wet cells of `seeds` seeds: (sigma [n] heteroscedastic, seed [n], depth [n], views [n], xy
    [n, 2] on a 5 cm grid, each seed's own 100 x (n / seeds / 100) patch)."""
    per = n // seeds
    side = 100
    ij = np.stack(np.meshgrid(np.arange(side), np.arange(per // side), indexing="ij"), -1).reshape(-1, 2)
    xy = np.tile(ij * 0.05, (seeds, 1))
    depth = 0.1 + 3.9 * xy[:, 0] / xy[:, 0].max()
    views = rng.integers(2, 40, len(xy))
    sigma = 0.01 + 0.005 * depth + 0.05 / np.sqrt(views)
    return sigma, np.repeat(np.arange(seeds), per), depth, views, xy


def test_a_calibrated_gaussian_predictor_scores_as_calibrated():
    rng = np.random.default_rng(0)
    sigma, seeds, depth, views, xy = cells(rng)
    err = rng.normal(0, sigma)
    se = lambda p: np.sqrt(p * (1 - p) / N)
    for p in (0.5, 0.8, 0.95):
        assert coverage(sigma, err, p) == pytest.approx(p, abs=4 * se(p))
    assert ence(sigma, err) < 0.02
    assert z_variance(sigma, err) == pytest.approx(1.0, abs=0.02)
    r = calibration_report(Z95 * sigma, err, seeds, depth, views, xy)
    assert r["coverage"]["0.95"] == pytest.approx(0.95, abs=4 * se(0.95))
    assert set(r["coverage_per_seed"]["0.95"]) == {0, 1, 2, 3, 4}
    spread = r["coverage_seed_spread"]["0.95"]
    assert spread["seeds"] == 5 and 0.94 < spread["min"] <= spread["mean"] <= spread["max"] < 0.96
    assert r["worst_depth_third"]["worst"] > 0.94 and r["worst_view_bin"]["worst"] > 0.94
    assert r["spearman"] > 0.1  # |e| is noisy: only its spread grows with sigma
    # a heteroscedastic truth: the right sigma is narrower than one width for all at the same coverage
    assert r["sharpness_vs_constant"] < 0.95
    # the oracle smooths the same errors: close to the truth's width
    assert r["sharpness_vs_oracle"] == pytest.approx(1.0, abs=0.1)


def test_a_predictor_off_by_two_is_flagged():
    rng = np.random.default_rng(1)
    sigma, seeds, depth, views, _ = cells(rng)
    err = rng.normal(0, sigma)
    narrow = calibration_report(Z95 * sigma / 2, err, seeds, depth, views)
    assert narrow["coverage"]["0.95"] == pytest.approx(2 * norm.cdf(Z95 / 2) - 1, abs=0.005)  # |z| <= 0.98
    assert narrow["z_variance"] == pytest.approx(4.0, rel=0.03)
    assert narrow["ence"] == pytest.approx(1.0, abs=0.03)  # |s - 2 s| / s
    wide = calibration_report(Z95 * sigma * 2, err, seeds, depth, views)
    assert wide["coverage"]["0.95"] > 0.999
    assert wide["coverage"]["0.5"] == pytest.approx(2 * norm.cdf(2 * z_level(0.5)) - 1, abs=0.005)
    assert wide["z_variance"] == pytest.approx(0.25, rel=0.03)
    assert wide["ence"] == pytest.approx(0.5, abs=0.02)


def test_the_worst_bins_find_a_band_that_is_off():
    rng = np.random.default_rng(2)
    sigma, seeds, depth, views, _ = cells(rng)
    err = rng.normal(0, sigma * np.where(depth_bins(depth) == 2, 2.0, 1.0))  # the deep third twice as wrong
    r = calibration_report(Z95 * sigma, err, seeds, depth, views)
    assert r["worst_depth_third"]["worst"] == pytest.approx(0.68, abs=0.01)
    assert r["worst_depth_third"]["bins"][0][1] == pytest.approx(0.95, abs=0.01)
    bins = view_bins(np.array([1, 1, 1, 2, 2, 3, 3, 3, 3, 9]), bins=3)
    assert len(set(bins[:3])) == 1 and len(set(bins[5:9])) == 1  # ties in one bin
    assert worst_bin(np.ones(10), np.zeros(10), np.zeros(10, int), min_cells=11)["worst"] is None


def test_bands_are_thirds_of_the_maximum_depth():
    np.testing.assert_array_equal(depth_bins([0.5, 1.0, 1.01, 2.0, 2.5, 3.0, 4.0], max_depth=3.0),
                                  [0, 0, 1, 1, 2, 2, 2])


def test_a_seed_with_a_shared_offset_shows_in_the_per_seed_spread():
    rng = np.random.default_rng(3)
    sigma, seeds, depth, views, _ = cells(rng)
    err = rng.normal(0, sigma) + np.where(seeds == 4, 0.05, 0.0)  # one seed's level 5 cm off
    r = calibration_report(Z95 * sigma, err, seeds, depth, views)
    per = r["coverage_per_seed"]["0.95"]
    assert per[4] < 0.8 and min(per[s] for s in range(4)) > 0.94
    assert r["coverage_seed_spread"]["0.95"]["std"] > 0.1


def test_constant_width_and_oracle_by_hand():
    assert constant_width([0.3, -0.1, 0.2, -0.4], 0.5) == 0.2
    assert constant_width([0.3, -0.1, 0.2, -0.4], 0.75) == 0.3
    assert constant_width([0.3, -0.1, 0.2, -0.4], 1.0) == 0.4
    xy = np.stack(np.meshgrid(np.arange(20), np.arange(20), indexing="ij"), -1).reshape(-1, 2) * 0.05
    signs = np.where(np.random.default_rng(4).random(len(xy)) < 0.5, -1, 1)
    assert local_rms(xy, 0.03 * signs, 0.05) == pytest.approx(0.03)  # constant |e|: its own RMS everywhere
    # a constant |e|: every score is 1 / Z95 sigma ... the conformal scale makes TVU95 exactly |e|
    assert oracle_tvu95(xy, 0.03 * signs, np.zeros(len(xy)), 0.05) == pytest.approx(0.03)


def test_ence_by_hand():
    sigma = np.array([1.0, 1.0, 2.0, 2.0])
    err = np.array([1.0, -1.0, 4.0, 4.0])  # bin 1: RMSE 1 = RMV; bin 2: RMSE 4, RMV 2
    assert ence(sigma, err, bins=2) == pytest.approx(0.5)
    assert z_level(0.95) == pytest.approx(Z95)


def test_iho_shares():
    depth = np.array([1.0, 1.0, 10.0, 10.0])
    t = np.array([0.04, 0.2, 0.2, 0.3])
    shares = iho_shares(t, depth)
    assert shares["5cm"] == 0.25
    assert shares["exclusive"] == pytest.approx(np.mean(t <= tvu(depth, "exclusive"))) == 0.25
    assert shares["special"] == 0.75  # 0.3 > sqrt(0.25^2 + 0.075^2) = 0.261
    assert shares["order 2"] == 1.0


def test_the_reliability_figure():
    rng = np.random.default_rng(5)
    sigma, seeds, *_ = cells(rng, n=20_000)
    fig = reliability_figure(Z95 * sigma, rng.normal(0, sigma), seeds, title="synthetic")
    assert len(fig.axes) == 2
    left = fig.axes[0]
    pooled = next(line for line in left.lines if line.get_label() == "pooled")
    x, y = pooled.get_data()
    assert np.abs(np.asarray(y) - np.asarray(x)).max() < 0.03
    import matplotlib.pyplot as plt

    plt.close(fig)

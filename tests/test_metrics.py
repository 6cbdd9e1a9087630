"""Error metrics (avsm_dr.metrics; the studies' log-domain errors, experiments._tau): signed,
tail and log-domain errors on known cases."""
from __future__ import annotations

import math

import numpy as np
import pytest

from avsm_dr import metrics
from experiments import _tau


def test_error_stats_known_values():
    ref = np.full(8, 0.5)
    err = np.array([0.03, -0.05, 0.01, 0.0, 0.0, 0.025, -0.021, 0.0])
    s = metrics.error_stats(ref + err, ref)
    assert s["rmse"] == pytest.approx(math.sqrt(np.mean(err ** 2)), rel=1e-12)
    assert s["max_error"] == pytest.approx(0.05, rel=1e-12)
    assert s["mean_error"] == pytest.approx(err.mean(), abs=1e-15)
    assert s["mean_abs_error"] == pytest.approx(np.abs(err).mean(), rel=1e-12)
    assert s["leak_fraction"] == 2 / 8 and s["dark_fraction"] == 2 / 8        # |e| > 0.02
    assert s["n"] == 8 and s["nan_count"] == s["inf_count"] == s["bounds_violations"] == 0
    s = metrics.error_stats(ref + err, ref, threshold=0.04)
    assert s["leak_fraction"] == 0 and s["dark_fraction"] == 1 / 8


def test_tail_percentiles_interpolate_linearly():
    """|e| = 0, 1, ..., 999 (scaled): the q-th percentile sits at rank (n - 1) q."""
    a = np.arange(1000) / 1000.0
    s = metrics.error_stats(a[::-1], np.zeros(1000))
    assert s["p99_error"] == pytest.approx((999 * 0.99) / 1000.0, rel=1e-12)
    assert s["p999_error"] == pytest.approx((999 * 0.999) / 1000.0, rel=1e-12)
    assert s["max_error"] == pytest.approx(0.999)


def test_non_finite_estimates_are_counted_not_averaged():
    est = np.array([0.5, np.nan, np.inf, 1.2, -0.1])
    s = metrics.error_stats(est, np.full(5, 0.5))
    assert s["nan_count"] == 1 and s["inf_count"] == 1 and s["bounds_violations"] == 2
    assert s["max_error"] == pytest.approx(0.7) and s["n"] == 5
    assert s["mean_error"] == pytest.approx((0.0 + 0.7 - 0.6) / 3)


def test_optical_depth_error_sign_and_floor():
    ref = np.array([math.exp(-3.0), 1e-6, 1e-9, 0.5])
    est = np.array([math.exp(-2.0), 0.0, 1e-3, 0.5])
    s = _tau.optical_depth_error(est, ref)                      # floor 1e-4
    e = np.array([1.0, 0.0, -math.log(1e-4) + math.log(1e-3), 0.0])  # tau(ref) - tau(est)
    assert s["tau_max_error"] == pytest.approx(e.max(), rel=1e-12)
    assert s["tau_mean_error"] == pytest.approx(e.mean(), rel=1e-12)
    assert s["tau_leak_fraction"] == 2 / 4 and s["tau_dark_fraction"] == 0
    assert s["tau_floor"] == 1e-4
    # a finer floor resolves the 1e-6 vs 0 receiver (over-dark by ln(1e-6 / 1e-8), capped by the
    # floor) and widens the third receiver's leak to ln(1e-3 / 1e-8)
    s2 = _tau.optical_depth_error(est, ref, floor=1e-8)
    assert s2["tau_max_error"] == pytest.approx(math.log(1e-3 / 1e-8), rel=1e-12)
    assert s2["tau_dark_fraction"] == 1 / 4 and s2["tau_leak_fraction"] == 2 / 4
    assert s2["tau_mean_error"] == pytest.approx((1.0 - math.log(1e-6 / 1e-8) + math.log(1e-3 / 1e-8)) / 4,
                                                 rel=1e-12)
    assert _tau.optical_depth([0.0, 1.0]).tolist() == pytest.approx([-math.log(1e-4), 0.0])


@pytest.mark.parametrize("call, name", [
    (lambda: metrics.error_stats([0.5, 0.5], [0.5]), "estimate"),
    (lambda: metrics.error_stats([0.5], [np.nan]), "reference"),
    (lambda: metrics.error_stats([0.5], [0.5], threshold=-1), "threshold"),
    (lambda: _tau.optical_depth_error([0.5], [0.5], floor=0.0), "floor"),
])
def test_bad_input_names_the_argument(call, name):
    with pytest.raises(ValueError, match=f"^{name}:"):
        call()


def test_image_metrics_signed_split_psnr_and_flip():
    """The images experiment's metrics: a uniformly brighter image leaks by exactly c,
    PSNR = 10 log10(S^2 / c^2); identical images have FLIP 0, a visibly different one > 0."""
    from experiments.images import image_metrics
    ref = np.linspace(0.0, 1.0, 32 * 40).reshape(32, 40)
    same, fmap = image_metrics(ref, ref, 1.0)
    assert same["rmse"] == 0 and same["flip"] == 0 and fmap.shape == (32, 40)
    c = 0.05
    m, fmap = image_metrics(ref, ref + c, 1.0)
    assert m["mean_signed"] == pytest.approx(c) and m["leak_mean"] == pytest.approx(c) and m["dark_mean"] == 0
    assert m["leak_pixels"] == 1.0 and m["dark_pixels"] == 0.0                    # c > 0.02 S
    assert m["psnr"] == pytest.approx(10 * math.log10(1 / c ** 2))
    assert m["flip"] > 0 and fmap.mean() == pytest.approx(m["flip"], rel=1e-5)
    d, _ = image_metrics(ref, ref - 0.01, 0.4)                                   # 0.01 > 0.02 * 0.4
    assert d["dark_pixels"] == 1.0 and d["leak_mean"] == 0 and d["dark_mean"] == pytest.approx(0.01)

"""Bootstrap intervals, paired comparisons and claims over configurations (avsm_dr.stats)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from avsm_dr import stats

REPS = 200
#: 3 binomial standard deviations of an observed coverage over REPS intervals at 95 %.
BINOMIAL_3SD = 3 * math.sqrt(0.95 * 0.05 / REPS)


@pytest.mark.parametrize("method", stats.METHODS)
def test_interval_of_the_mean_covers_95_percent(method):
    """Over 200 samples of 40 standard normals the 95 % interval of the mean contains 0
    in 95 % +- 3 binomial sd (4.6 %) of the repetitions (measured: 95.5 % percentile,
    94.0 % BCa)."""
    hits = 0
    for r in range(REPS):
        x = np.random.default_rng(1000 + r).standard_normal(40)
        ci = stats.bootstrap_ci(x, "mean", method=method, seed=r)
        assert ci["low"] <= ci["estimate"] <= ci["high"]
        hits += ci["low"] <= 0.0 <= ci["high"]
    assert abs(hits / REPS - 0.95) <= BINOMIAL_3SD


def test_bca_shifts_right_for_right_skewed_data():
    """BCa corrects the percentile interval of a right-skewed mean towards larger values
    (Efron & Tibshirani 1993, ch. 14): both ends move up for lognormal samples."""
    for s in range(4):
        x = np.random.default_rng(s).lognormal(0.0, 1.0, 60)
        p = stats.bootstrap_ci(x, "mean", seed=s)
        b = stats.bootstrap_ci(x, "mean", method="bca", seed=s)
        assert b["low"] > p["low"] and b["high"] > p["high"]


def test_jackknife_of_the_mean():
    x = np.random.default_rng(0).random(7)
    jack = stats._jackknife(lambda idx: x[idx].mean(axis=1), x.size)
    assert np.allclose(jack, (x.sum() - x) / 6, rtol=1e-14)


def test_seeded_and_statistics_by_name():
    x = np.random.default_rng(0).standard_normal(100)
    a, b = stats.bootstrap_ci(x, "rmse", seed=5), stats.bootstrap_ci(x, "rmse", seed=5)
    assert a == b
    assert a["estimate"] == pytest.approx(math.sqrt(np.mean(x ** 2)))
    assert stats.bootstrap_ci(x, "rmse", seed=6) != a
    c = stats.bootstrap_ci(x, lambda v, axis: np.mean(v ** 2, axis=axis), seed=5)
    assert c["estimate"] == pytest.approx(a["estimate"] ** 2)


def test_paired_comparison_cancels_receiver_variation():
    """Method a has half of method b's error on every receiver times (1 + eps_i), eps_i
    ~ 1 % noise: every replicate's RMSE ratio is a weighted mean of 0.5 (1 + eps_i), so
    the paired interval lies inside 0.5 (1 + [min eps, max eps]) and is far tighter than
    the ratio of two unpaired intervals (receiver-to-receiver spread cancels)."""
    rng = np.random.default_rng(1)
    b = np.abs(rng.standard_normal(500)) * rng.lognormal(0, 1, 500)
    eps = 0.01 * rng.standard_normal(500)
    a = 0.5 * b * (1 + eps)
    r = stats.paired_bootstrap(a, b, "rmse", "ratio", seed=0)
    assert 0.5 * (1 + eps.min()) <= r["low"] <= r["estimate"] <= r["high"] <= 0.5 * (1 + eps.max())
    assert r["p_a_smaller"] == 1.0
    ca, cb = stats.bootstrap_ci(a, "rmse", seed=1), stats.bootstrap_ci(b, "rmse", seed=2)
    assert (ca["high"] / cb["low"] - ca["low"] / cb["high"]) > 20 * (r["high"] - r["low"])
    d = stats.paired_bootstrap(a, b, "mean_abs", "difference", seed=0)
    assert d["estimate"] == pytest.approx(np.mean(np.abs(a)) - np.mean(np.abs(b)))


def test_claim_over_configurations():
    """a beats b (ratio 0.5) in three configurations and loses (ratio 1.5) in a fourth:
    the pooled geometric mean (0.5^3 1.5)^(1/4) = 0.66 holds, every-configuration does not."""
    rng = np.random.default_rng(2)
    bs = [np.abs(rng.standard_normal(400)) for _ in range(4)]
    factors = [0.5, 0.5, 0.5, 1.5]
    as_ = [f * b * (1 + 0.02 * rng.standard_normal(b.size)) for f, b in zip(factors, bs)]
    out = stats.claim(as_, bs, configs=["s0", "s1", "s2", "s3"], seed=0)
    assert [r["config"] for r in out["per_config"]] == ["s0", "s1", "s2", "s3"]
    assert [r["holds"] for r in out["per_config"]] == [True, True, True, False]
    assert not out["holds_in_every_configuration"]
    assert out["estimate"] == pytest.approx((0.5 ** 3 * 1.5) ** 0.25, rel=0.01)
    assert out["low"] <= out["estimate"] <= out["high"]
    good = stats.claim(as_[:3], bs[:3], seed=0)
    assert good["holds_in_every_configuration"] and good["holds_pooled"] and good["high"] < 0.52


@pytest.mark.parametrize("call, name", [
    (lambda: stats.bootstrap_ci([1.0], "mean"), "x"),
    (lambda: stats.bootstrap_ci([1.0, np.nan], "mean"), "x"),
    (lambda: stats.bootstrap_ci([1.0, 2.0], "mode"), "statistic"),
    (lambda: stats.bootstrap_ci([1.0, 2.0], n_boot=10), "n_boot"),
    (lambda: stats.bootstrap_ci([1.0, 2.0], level=1.0), "level"),
    (lambda: stats.bootstrap_ci([1.0, 2.0], method="basic"), "method"),
    (lambda: stats.paired_bootstrap([1.0, 2.0], [1.0, 2.0, 3.0]), "b"),
    (lambda: stats.paired_bootstrap([1.0, 2.0], [1.0, 2.0], compare="log"), "compare"),
    (lambda: stats.claim([[1.0, 2.0]], []), "b_by_config"),
])
def test_bad_input_names_the_argument(call, name):
    with pytest.raises(ValueError, match=f"^{name}:"):
        call()

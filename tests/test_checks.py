"""The shared checks of avsm_dr.checks: each must pass on a correct input and fail on the
fault it exists to catch (a biased estimator, an overconfident standard error, a wrong
gradient in both AD modes, a reverse mode that disagrees with forward mode)."""
import math

import numpy as np
import pytest

import drjit as dr
from avsm_dr import backend
from avsm_dr.checks import check_gradients, mc_agreement

T64 = backend.types()
N = 4000


def _noisy(rng, se, bias=0.0):
    """An estimate of reference values in [0.1, 1] with Gaussian noise of std ``se``."""
    ref = rng.uniform(0.1, 1.0, N)
    return ref + bias + rng.normal(size=N) * se, ref


# ================================================================= Monte Carlo
def test_unbiased_estimate_with_honest_stderr_passes(rng):
    se = rng.uniform(0.01, 0.05, N)
    est, ref = _noisy(rng, se)
    r = mc_agreement(est, ref, se, max_rms_ratio=1.1)
    assert r.ok, r
    assert 0.99 < r.fraction_within <= 1 and abs(r.z) < 4 and 0.9 < r.rms_ratio < 1.1


def test_bias_of_a_quarter_stderr_fails_on_z_only(rng):
    # every element stays within 3 SE, but sum(e) / sqrt(sum SE^2) = 0.25 sqrt(N) = 16
    se = np.full(N, 0.02)
    est, ref = _noisy(rng, se, bias=0.25 * 0.02)
    r = mc_agreement(est, ref, se)
    assert not r.ok and r.fraction_within >= 0.98
    assert len(r.failures) == 1 and "bias" in r.failures[0] and r.z > 10


def test_overconfident_stderr_fails_on_fraction(rng):
    se = np.full(N, 0.02)
    est, ref = _noisy(rng, se)
    r = mc_agreement(est, ref, se / 2)           # claimed SE half the true one: 1.5 sigma bands
    assert not r.ok and "within" in r.failures[0] and r.fraction_within < 0.9


def test_floor_admits_a_bounded_deterministic_error(rng):
    se = np.full(N, 1e-6)
    est, ref = _noisy(rng, se, bias=5e-5)        # e.g. float32 rounding of the reference
    assert not mc_agreement(est, ref, se).ok
    assert mc_agreement(est, ref, se, floor=1e-4).ok
    assert not mc_agreement(est, ref, se, floor=2e-5).ok


def test_scalar_stderr_and_rms_ratio_catch_a_small_systematic_mismatch(rng):
    # An image-style check: one noise level sigma for every pixel.  A deterministic
    # mismatch of 0.8 sigma per pixel (random sign: no bias) raises the RMS ratio to
    # sqrt(1 + 0.64) = 1.28 while nearly every pixel stays within 3 sigma.
    sigma = 0.02
    est, ref = _noisy(rng, sigma)
    assert mc_agreement(est, ref, sigma, max_rms_ratio=1.2).ok
    off = est + 0.8 * sigma * rng.choice([-1.0, 1.0], N)
    r = mc_agreement(off, ref, sigma, max_rms_ratio=1.2)
    assert not r.ok and len(r.failures) == 1 and "RMS" in r.failures[0]
    assert r.rms_ratio == pytest.approx(math.sqrt(1.64), rel=0.05)


def test_relative_error_thresholds_with_floor():
    ref = np.array([1.0, 0.5, 1e-4, 0.0])
    est = ref * 1.01                              # 1 % everywhere (the last two: below the floor)
    r = mc_agreement(est, ref, 0.0, min_fraction=0, floor=1.0, rel_floor=1e-2, mean_rtol=0.02, max_rtol=0.02)
    assert r.ok, r
    assert r.rel_max == pytest.approx(0.01) and r.rel_mean == pytest.approx((0.01 + 0.01 + 1e-4) / 4)
    est[1] = 0.6                                  # one element 20 % off: the max catches it, not the mean
    r = mc_agreement(est, ref, 0.0, min_fraction=0, floor=1.0, mean_rtol=0.06, max_rtol=0.02)
    assert not r.ok and r.failures == [f"max relative error {r.rel_max:.3g} > 0.02"]


def test_infinite_stderr_carries_no_bias_information():
    ref = np.zeros(10)
    est = np.ones(10)
    r = mc_agreement(est, ref, np.inf)
    assert r.ok and r.z == 0.0


@pytest.mark.parametrize("kw, name", [
    ({"reference": np.zeros(3)}, "reference"),
    ({"stderr": -np.ones(4)}, "stderr"),
    ({"stderr": np.ones(3)}, "stderr"),
    ({"k": 0.0}, "k"),
    ({"min_fraction": 1.5}, "min_fraction"),
    ({"max_rtol": -1.0}, "max_rtol"),
])
def test_mc_agreement_bad_input(kw, name):
    args = dict(estimate=np.zeros(4), reference=np.zeros(4), stderr=np.ones(4))
    args.update(kw)
    with pytest.raises(ValueError, match=name):
        mc_agreement(**args)


# =================================================================== gradients
W = np.linspace(-1.0, 2.0, 12)


def _loss(x):
    return dr.sum(dr.sin(x) * T64.Float64(W) + x * x)


class _WrongBackward(dr.CustomOp):
    """y = x^2 with the right forward derivative and a backward one 1.5 x too large."""

    def eval(self, x):
        self.x = x
        return x * x

    def forward(self):
        self.set_grad_out(2 * self.x * self.grad_in("x"))

    def backward(self):
        self.set_grad_in("x", 3 * self.x * self.grad_out())


def test_correct_gradient_passes():
    x = T64.Float64(np.linspace(0.1, 1.2, 12))
    chk = check_gradients(_loss, x, fd=6)
    assert chk.ok, chk
    np.testing.assert_allclose(chk.gradient, W * np.cos(x.numpy()) + 2 * x.numpy(), rtol=1e-14)
    assert len(chk.indices) == 6 and chk.reverse == pytest.approx(chk.forward, rel=1e-12)
    assert chk.summary()["ok"] and chk.summary()["fd_checked"] == 6


def test_gradient_wrong_in_both_modes_is_caught_by_finite_differences():
    # x * detach(x): both AD modes see d/dx = x instead of 2x, so they agree with each other
    x = T64.Float64(np.linspace(0.1, 1.2, 12))
    chk = check_gradients(lambda y: dr.sum(y * dr.detach(y)), x, fd=4)
    assert not chk.ok
    assert all("finite difference" in f for f in chk.failures) and len(chk.failures) == 4
    assert chk.reverse == pytest.approx(chk.forward, rel=1e-12)


def test_reverse_mode_disagreeing_with_forward_mode_is_caught():
    x = T64.Float64(np.linspace(0.1, 1.2, 12))
    chk = check_gradients(lambda y: dr.sum(dr.custom(_WrongBackward, y)), x, fd=0)
    assert not chk.ok and len(chk.failures) == 1 and "forward mode" in chk.failures[0]
    assert chk.reverse == pytest.approx(1.5 * chk.forward, rel=1e-12)


def test_tensor_input_primal_and_accept():
    """Tensors work; ``primal`` replaces the differenced function; coordinates refused by
    ``accept`` are skipped and too few remaining is a failure."""
    x = T64.TensorXf64(np.linspace(0.1, 1.2, 12).reshape(3, 4))

    def loss(t):
        return dr.sum(t.array * t.array)

    chk = check_gradients(loss, x, fd=[0, 5, 11], primal=lambda a: float(np.sum(a * a)))
    assert chk.ok and chk.indices == [(0, 0), (1, 1), (2, 3)] and chk.gradient.shape == (3, 4)
    wrong = check_gradients(loss, x, fd=[0, 5], primal=lambda a: float(np.sum(a * a * a)), forward=False)
    assert not wrong.ok and np.isnan(wrong.forward)
    few = check_gradients(loss, x, fd=[0, 5, 11, 7], accept=lambda xp, xm: xp[0, 0] == xm[0, 0])
    assert few.skipped == 1 and len(few.indices) == 3 and few.ok           # 3 of 4 = the default 3/4
    none = check_gradients(loss, x, fd=[0, 5], accept=lambda xp, xm: False)
    assert not none.ok and "only 0 coordinates" in none.failures[0]


@pytest.mark.parametrize("kw, name", [({"eps": 0.0}, "eps"), ({"fd": -1}, "fd"), ({"fd": [99]}, "fd")])
def test_check_gradients_bad_input(kw, name):
    with pytest.raises(ValueError, match=name):
        check_gradients(_loss, T64.Float64(np.ones(12)), **kw)
    with pytest.raises(ValueError, match="x"):
        check_gradients(_loss, np.ones(12))

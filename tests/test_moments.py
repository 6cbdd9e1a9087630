"""Moment-based representation ('moments'): 4, 6, 8 power moments of the absorbance with
the Hamburger bound, linear and log depth warps, against tests/reference/moments_ref.py.

Tolerances:
* moments b_k, linear warp: eps (16 + N) sum tau (|x^k| <= 1; N-term float sum), as for
  every basis.  Log warp: the same plus 64 eps sum tau for the logarithms of the clipped
  depths (|d x^k / d ln z| <= 2k / ln(far / near), k <= 8) and the series / recurrence of
  the segment means (``log_warp_means``, every term <= 1); measured <= 2e-15 absolute.
* bounds L, U in float64 vs the NumPy route (linalg.solve / roots / Vandermonde): the
  Hankel matrix has condition number up to ~1 / (alpha p_min) (its pivots are floored at
  alpha times the bias target's, smallest p_min = 0.234, 0.026, 0.011 for 4, 6, 8
  moments), so eps64 / (alpha p_min) ~ 1e-6 at the float64 defaults (alpha = 1e-9, 1e-8,
  1e-7): asserted 1e-7 (4) and 1e-6 (6, 8); measured <= 5e-10 on these inputs.
* the Chebyshev-Markov-Stieltjes property L(x) <= F(x-) and U(x) >= F(x) for the biased
  absorbance distribution F: the same tolerances (exact in exact arithmetic).
* float32 vs float64 kernels at the same bias: see test_float32_close_to_float64 (the
  weights are ill-conditioned where x_f nears a support point).
* trigonometric moments (2, 3, 4): coefficients as above; bounds of the kernel's Cayley
  route vs the reference's Toeplitz route 1e-6 (see the test).
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import avsm_dr as ad
import drjit as dr

from cases import random_segments, to_segments
from avsm_dr.representations import moments as MOD
from reference import linear_ref as R
from reference import moments_ref as M
from helpers import optical_depth

EPS = {"float32": 2.0 ** -24, "float64": 2.0 ** -53}


def host_case(seg):
    h = seg.numpy()
    return dict(offsets=h["offsets"], z0=h["z0"], z1=h["z1"], tau=h["optical_depth"], dtype=seg.dtype)


def coefficient_array(rep):
    return np.stack([np.asarray(c, np.float64) for c in rep.coefficients], axis=1)


def uint32(x):
    return ad.backend.types().UInt32(np.asarray(x, np.uint32))


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("rng_kw", [{}, {"depth_range": "texel"}, {"near": -0.25, "far": 1.5}],
                         ids=["global", "texel", "explicit"])
def test_moments_match_reference(rng_kw, dtype, rng):
    case = random_segments(rng, texels=24, max_count=12, opaque_fraction=0.0)
    seg = to_segments(case, dtype)
    hc = host_case(seg)
    rep = ad.build("moments", seg, **rng_kw)
    ref = M.moments(hc, **rng_kw)
    counts = np.diff(hc["offsets"])
    total = np.add.reduceat(np.append(hc["tau"], 0), hc["offsets"][:-1]) * (counts > 0)
    tol = EPS[dtype] * (16 + counts) * total
    assert np.all(np.abs(coefficient_array(rep) - ref) <= tol[:, None] + 1e-300)
    assert rep.nbytes_per_texel == (5 + (2 if rng_kw.get("depth_range") == "texel" else 0)) \
        * (4 if dtype == "float32" else 8)


def _receivers(rep, T, k=23):
    u = (np.arange(k) + 0.37) / k
    tex = np.repeat(np.arange(T), k)
    if rep._per_texel:
        near, far = np.asarray(rep.near, np.float64), np.asarray(rep.far, np.float64)
        span = np.maximum(far - near, 1e-6 * np.maximum(abs(near), abs(far)) + 1e-30)
        d = near[tex] + np.tile(u, T) * span[tex]
    else:
        d = rep.near + np.tile(u, T) * (rep.far - rep.near)
    return tex, d


@pytest.mark.parametrize("beta", [0.0, 0.25, 1.0])
@pytest.mark.parametrize("rng_kw", [{}, {"depth_range": "texel"}], ids=["global", "texel"])
def test_bounds_and_transmittance_match_reference(rng_kw, beta, rng):
    case = random_segments(rng, texels=20, max_count=10, opaque_fraction=0.0)
    seg = to_segments(case, "float64")
    hc = host_case(seg)
    rep = ad.build("moments", seg, overestimation=beta, **rng_kw)
    alpha = rep.params["bias"]
    tex, d = _receivers(rep, seg.n_texels)
    Float64 = ad.backend.types().Float64
    lo, up = (np.asarray(v) for v in rep.bounds(uint32(tex), Float64(d)))
    b = coefficient_array(rep)
    near, span = R.ranges(hc, **rng_kw)
    u = (d - near[tex]) / span[tex]
    ref = np.array([M.bounds(b[t], 2 * uj - 1, alpha) for t, uj in zip(tex, u)])
    nonempty = b[tex, 0] > 0
    np.testing.assert_allclose(lo[nonempty], ref[nonempty, 0], rtol=0, atol=1e-7)
    np.testing.assert_allclose(up[nonempty], ref[nonempty, 1], rtol=0, atol=1e-7)
    Dref = np.concatenate([M.optical_depth(b[t], u[tex == t], alpha, beta)
                           for t in range(seg.n_texels)])
    D = np.asarray(optical_depth(rep, tex, d))
    tol = 1e-7 * (1 + b[tex, 0])          # the fraction's 1e-7 times b_0
    assert np.all(np.abs(D - Dref) <= tol), np.max(np.abs(D - Dref))
    T = np.asarray(rep.eval(tex, d))
    assert np.all(np.abs(T - np.exp(-Dref)) <= tol)


def test_bounds_bracket_the_true_distribution(rng):
    """Chebyshev-Markov-Stieltjes: L(x) <= F(x-) and F(x) <= U(x) for every distribution
    with these moments, in particular the (biased) absorbance distribution itself,
    F = (1 - alpha) D_exact(x) / b_0 + alpha (x + 1) / 2."""
    case = random_segments(rng, texels=40, max_count=10, opaque_fraction=0.0, zero_fraction=0.3)
    seg = to_segments(case, "float64")
    hc = host_case(seg)
    rep = ad.build("moments", seg, near=0.0, far=1.0, bias_target=MOD.UNIFORM_TARGET[4])
    alpha = rep.params["bias"]
    k = 57
    u = (np.arange(k) + 0.5) / k
    tex = np.repeat(np.arange(seg.n_texels), k)
    d = np.tile(u, seg.n_texels)
    lo, up = (np.asarray(v) for v in rep.bounds(uint32(tex), ad.backend.types().Float64(d)))
    b0 = coefficient_array(rep)[:, 0]
    checked = 0
    for t in range(seg.n_texels):
        if b0[t] <= 0:
            continue
        s = tex == t
        left = R.exact_optical_depth(hc, t, u - 1e-12) / b0[t]     # F(x-)
        right = R.exact_optical_depth(hc, t, u) / b0[t]            # F(x)
        Fl = (1 - alpha) * left + alpha * u
        Fr = (1 - alpha) * right + alpha * u
        assert np.all(lo[s] <= Fl + 1e-7), np.max(lo[s] - Fl)
        assert np.all(up[s] >= Fr - 1e-7), np.max(Fr - up[s])
        checked += 1
    assert checked > 20


def test_single_delta_is_a_step():
    """One zero-length segment: the upper bound (beta = 1) is the exact step, the lower
    bound (beta = 0) the same step with the receiver at the delta counted in front."""
    seg = ad.Segments.from_arrays([0, 1, 1], [0.5], [0.5], optical_depth=[1.5], dtype="float64")
    d = np.array([0.0, 0.1, 0.3, 0.45, 0.5, 0.55, 0.7, 0.9, 1.0])
    exact = np.exp(-1.5 * (d >= 0.5))
    for beta, at_delta in ((1.0, np.exp(-1.5)), (0.0, 1.0)):
        T = np.asarray(ad.build("moments", seg, near=0.0, far=1.0, overestimation=beta)
                       .eval(np.zeros(d.size, int), d))
        expect = exact.copy()
        expect[4] = at_delta
        np.testing.assert_allclose(T, expect, rtol=0, atol=1e-6)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_exact_at_near_and_far_and_empty(dtype, rng):
    case = random_segments(rng, texels=16, max_count=8, opaque_fraction=0.0)
    seg = to_segments(case, dtype)
    hc = host_case(seg)
    rep = ad.build("moments", seg)
    tex = np.arange(16)
    assert np.all(np.asarray(rep.eval(tex, np.full(16, rep.near))) == 1.0)
    counts = np.diff(hc["offsets"])
    total = np.add.reduceat(np.append(hc["tau"], 0), hc["offsets"][:-1]) * (counts > 0)
    T = np.asarray(rep.eval(tex, np.full(16, rep.far)), np.float64)
    eps = EPS[dtype]
    tol = np.exp(-total) * eps * (counts + 16) * total + 4 * eps
    assert np.all(np.abs(T - np.exp(-total)) <= tol)
    T = np.asarray(rep.eval(np.repeat(tex, 5), np.tile(np.linspace(-1, 2, 5), 16)))
    assert np.all(T[np.repeat(counts == 0, 5)] == 1.0)


def test_overestimation_orders_the_curves(rng):
    case = random_segments(rng, texels=16, max_count=8, opaque_fraction=0.0)
    seg = to_segments(case, "float64")
    tex = np.repeat(np.arange(16), 31)
    d = np.tile(np.linspace(0, 1, 31), 16)
    T = [np.asarray(ad.build("moments", seg, overestimation=b).eval(tex, d))
         for b in (0.0, 0.25, 1.0)]
    assert np.all(T[0] >= T[1] - 1e-12) and np.all(T[1] >= T[2] - 1e-12)
    assert np.any(T[0] > T[2] + 1e-3)


def test_float32_close_to_float64(rng):
    """Same bias (the float32 default 1e-5) in both precisions: the a-priori bound
    eps32 cond(B) ~ eps32 45 / (4 alpha) ~ 0.07 is loose; measured max 3.2e-4 over four
    seeds (receivers next to a support point), mean ~1e-7.  Asserted: max 2e-3, mean 1e-5."""
    case = random_segments(rng, texels=64, max_count=20, opaque_fraction=0.0)
    tex = np.repeat(np.arange(64), 41)
    d = np.tile(np.linspace(0, 1, 41), 64)
    T32 = np.asarray(ad.build("moments", to_segments(case, "float32"), bias=1e-5).eval(tex, d),
                     np.float64)
    T64 = np.asarray(ad.build("moments", to_segments(case, "float64"), bias=1e-5).eval(tex, d))
    err = np.abs(T32 - T64)
    assert err.max() <= 2e-3 and err.mean() <= 1e-5, (err.max(), err.mean())


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2 ** 31), dtype=st.sampled_from(["float32", "float64"]),
       beta=st.floats(0, 1), opaque=st.floats(0, 0.5),
       depth_range=st.sampled_from(["global", "texel"]))
def test_property_finite_and_in_unit_interval(seed, dtype, beta, opaque, depth_range):
    rng = np.random.default_rng(seed)
    case = random_segments(rng, texels=6, max_count=6, opaque_fraction=opaque,
                           depth_range=(rng.uniform(-5, 5), rng.uniform(5.5, 9)))
    rep = ad.build("moments", to_segments(case, dtype), overestimation=beta,
                   depth_range=depth_range)
    tex = np.repeat(np.arange(6), 40)
    d = np.tile(np.linspace(-6, 10, 40), 6)
    T = np.asarray(rep.eval(tex, d))
    assert np.all(np.isfinite(T)) and np.all((T >= 0) & (T <= 1))
    assert np.all(np.isfinite(coefficient_array(rep)))


def test_gradients_match_finite_differences(rng):
    """Reverse and forward mode through the nonlinear bound vs central differences
    (float64, h = 1e-6; receivers away from the case switches at the roots)."""
    Float64 = ad.backend.types().Float64
    case = random_segments(rng, texels=3, max_count=4, opaque_fraction=0.0, empty_fraction=0.0,
                           zero_fraction=0.0, depth_range=(0.2, 0.8))
    tex = np.repeat(np.arange(3), 7)
    d = np.tile(np.linspace(0.05, 0.95, 7), 3)
    w = rng.normal(size=tex.size)

    def loss(**over):
        c = {**case, **over}
        seg = ad.Segments.from_arrays(c["offsets"], c["z0"], c["z1"], optical_depth=c["tau"],
                                      dtype="float64")
        rep = ad.build("moments", seg, near=0.0, far=1.0)
        return dr.sum(rep.eval(tex, d) * Float64(w))

    for field in ("tau", "z0", "z1"):
        x = Float64(case[field])
        dr.enable_grad(x)
        dr.backward(loss(**{field: x}))
        rev = np.asarray(dr.grad(x))
        fd = np.zeros(case[field].size)
        for i in range(fd.size):
            p, m = case[field].copy(), case[field].copy()
            p[i] += 1e-6
            m[i] -= 1e-6
            fd[i] = (np.asarray(loss(**{field: p}))[0] - np.asarray(loss(**{field: m}))[0]) / 2e-6
        np.testing.assert_allclose(rev, fd, rtol=1e-5, atol=1e-7, err_msg=f"d/d{field}")
        v = rng.normal(size=fd.size)
        y = Float64(case[field])
        dr.enable_grad(y)
        out = loss(**{field: y})
        dr.set_grad(y, Float64(v))
        fwd = float(np.asarray(dr.forward_to(out))[0])
        np.testing.assert_allclose(fwd, fd @ v, rtol=1e-5, atol=1e-7, err_msg=f"forward d/d{field}")
    assert np.any(np.abs(fd) > 1e-3)


@pytest.mark.parametrize("params,arg", [
    ({"bias": 0.0}, "bias"),
    ({"bias": -1e-5}, "bias"),
    ({"bias": 2.0}, "bias"),
    ({"bias": float("nan")}, "bias"),
    ({"overestimation": 1.5}, "overestimation"),
    ({"overestimation": "0.2"}, "overestimation"),
    ({"near": 0.5, "far": 0.5}, "near"),
    ({"depth_range": "x"}, "depth_range"),
    ({"moments": 5}, "moments"),
    ({"moments": 10}, "moments"),
    ({"moments": 6, "family": "x"}, "family"),
    ({"moments": 6, "family": "trigonometric"}, "moments"),
    ({"moments": 3}, "moments"),
    ({"family": "trigonometric", "moments": 2, "bias_target": (0.0, 0.1)}, "bias_target"),
    ({"warp": "cubic"}, "warp"),
    ({"warp": "log", "near": 0.0}, "near"),
    ({"warp": "log", "near": -1.0, "far": 1.0}, "near"),
    ({"bias_target": (0.0, 0.3, 0.0)}, "bias_target"),
    ({"bias_target": (0.0, 1.0, 0.0, 0.5)}, "bias_target"),        # m4 < m2^2: not positive definite
    ({"bias_target": "abcd"}, "bias_target"),
])
def test_bad_input(params, arg):
    seg = ad.Segments.from_arrays([0, 2], [0.1, 0.5], [0.3, 0.9], optical_depth=[1.0, 0.5])
    with pytest.raises(ValueError, match=f"^{arg}:"):
        ad.build("moments", seg, **params)


@pytest.mark.parametrize("dtype,tol", [("float32", 1e-6), ("float64", 1e-12)])
def test_non_increasing_up_to_rounding(dtype, tol, rng):
    """The bounds are non-decreasing in x in exact arithmetic (infima / suprema of CDFs),
    but the float weights are not guaranteed to be (monotone = False): increases stay at
    rounding level (measured 5.4e-7 in float32, 1.1e-16 in float64 on 200 texels)."""
    case = random_segments(rng, texels=50, max_count=20, opaque_fraction=0.0)
    d = np.linspace(-0.1, 1.1, 801)
    for beta in (0.0, 0.25, 1.0):
        rep = ad.build("moments", to_segments(case, dtype), overestimation=beta)
        T = np.asarray(rep.eval(np.repeat(np.arange(50), d.size), np.tile(d, 50)), np.float64)
        assert np.diff(T.reshape(50, -1), axis=1).max() <= tol
    assert rep.monotone is False


def test_log_warp_needs_positive_texel_depths():
    seg = ad.Segments.from_arrays([0, 1, 2, 2], [0.0, 0.3], [0.2, 0.5], optical_depth=[1.0, 0.5])
    with pytest.raises(ValueError, match="^near:"):
        ad.build("moments", seg, warp="log", depth_range="texel")
    seg = ad.Segments.from_arrays([0, 1, 2, 2], [0.1, 0.3], [0.2, 0.5], optical_depth=[1.0, 0.5])
    rep = ad.build("moments", seg, warp="log", depth_range="texel")      # the empty texel is fine
    T = np.asarray(rep.eval([0, 1, 2], [0.3, 0.6, 0.5]))
    assert np.all(np.isfinite(T)) and T[2] == 1.0


# ----------------------------------------------------------------------------
# 6 and 8 moments, the log warp
# ----------------------------------------------------------------------------
def _log_receivers(near, span, tex, u, warp):
    if warp == "linear":
        return near[tex] + u * span[tex]
    return near[tex] * np.exp(u * np.log((near[tex] + span[tex]) / near[tex]))


def _bounds_on_receivers(rep, hc, warp, k=23):
    """23 receivers per texel, uniform in the warped depth: (texels, depths, their warped u,
    the representation's lower and upper bounds there)."""
    near, span = R.ranges(hc)
    tex, u = np.repeat(np.arange(rep.n_texels), k), np.tile((np.arange(k) + 0.37) / k, rep.n_texels)
    d = _log_receivers(near, span, tex, u, warp)
    lo, up = (np.asarray(v) for v in rep.bounds(uint32(tex), ad.backend.types().Float64(d)))
    return tex, d, M.warped_u(d, near[tex], span[tex], warp), lo, up


@pytest.mark.parametrize("n", [4, 6, 8])
@pytest.mark.parametrize("warp", ["linear", "log"])
def test_moments_and_bounds_match_reference(n, warp, rng):
    """Coefficients (global and per-texel ranges) and bounds / D / T (global) in float64;
    tolerances in the module docstring."""
    case = random_segments(rng, texels=16, max_count=10, opaque_fraction=0.0, depth_range=(0.05, 1.0))
    seg = to_segments(case, "float64")
    hc = host_case(seg)
    counts = np.diff(hc["offsets"])
    total = np.add.reduceat(np.append(hc["tau"], 0), hc["offsets"][:-1]) * (counts > 0)
    extra = 64 if warp == "log" else 0
    for rng_kw in ({}, {"depth_range": "texel"}):
        rep = ad.build("moments", seg, moments=n, warp=warp, **rng_kw)
        ref = M.moments(hc, n, warp, **rng_kw)
        tol = EPS["float64"] * (16 + extra + counts) * total
        assert np.all(np.abs(coefficient_array(rep) - ref) <= tol[:, None] + 1e-300)
        assert rep.nbytes_per_texel == (n + 1 + (2 if rng_kw else 0)) * 8
    alpha, beta = rep.params["bias"], 0.25
    rep = ad.build("moments", seg, moments=n, warp=warp, overestimation=beta)
    b = coefficient_array(rep)
    tex, d, uu, lo, up = _bounds_on_receivers(rep, hc, warp)
    ref = np.array([M.bounds(b[t], 2 * x - 1, alpha) for t, x in zip(tex, uu)])
    ne = b[tex, 0] > 0
    tol = 1e-7 if n == 4 else 1e-6
    np.testing.assert_allclose(lo[ne], ref[ne, 0], rtol=0, atol=tol)
    np.testing.assert_allclose(up[ne], ref[ne, 1], rtol=0, atol=tol)
    Dref = np.array([M.optical_depth(b[t], [x], alpha, beta)[0] for t, x in zip(tex, uu)])
    T = np.asarray(rep.eval(tex, d))
    assert np.all(np.abs(T - np.exp(-Dref)) <= tol * (1 + b[tex, 0]))


@pytest.mark.parametrize("n,warp", [(6, "linear"), (8, "log")])
def test_bounds_bracket_the_true_distribution_6_8(n, warp, rng):
    """L(x) <= F(x-) and F(x) <= U(x) (Chebyshev-Markov-Stieltjes) for the biased absorbance
    distribution F = (1 - alpha) D_exact / b_0 + alpha u (bias toward the uniform target)."""
    case = random_segments(rng, texels=24, max_count=10, opaque_fraction=0.0, zero_fraction=0.3,
                           depth_range=(0.05, 1.0))
    seg = to_segments(case, "float64")
    hc = host_case(seg)
    rep = ad.build("moments", seg, moments=n, warp=warp, near=0.05, far=1.0,
                   bias_target=MOD.UNIFORM_TARGET[n])
    alpha = rep.params["bias"]
    k = 57
    u = (np.arange(k) + 0.5) / k
    near, span = np.array([0.05]), np.array([0.95])
    d = _log_receivers(near, span, np.zeros(k, int), u, warp)
    tex = np.repeat(np.arange(seg.n_texels), k)
    lo, up = (np.asarray(v).reshape(seg.n_texels, k) for v in
              rep.bounds(uint32(tex), ad.backend.types().Float64(np.tile(d, seg.n_texels))))
    b0 = coefficient_array(rep)[:, 0]
    checked = 0
    for t in range(seg.n_texels):
        if b0[t] <= 0:
            continue
        Fl = (1 - alpha) * R.exact_optical_depth(hc, t, d * (1 - 1e-12)) / b0[t] + alpha * u
        Fr = (1 - alpha) * R.exact_optical_depth(hc, t, d) / b0[t] + alpha * u
        assert np.all(lo[t] <= Fl + 1e-6), np.max(lo[t] - Fl)
        assert np.all(up[t] >= Fr - 1e-6), np.max(Fr - up[t])
        checked += 1
    assert checked > 10


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_adversarial_texels_finite(dtype):
    """One segment (rank-1 moment matrix before the bias), one zero-length segment, huge and
    opaque optical depth, everything at one depth, two deltas: T finite in [0, 1] for every
    moment count and beta, and 0 <= L <= U <= 1.  Float64: T within 1e-6 (1 + b_0) of the
    reference (tolerances of the module docstring) where b_0 < 1e3; float32 with its
    published bias: finite and bounded (the rank-1 case is where public float32 Cholesky
    implementations return NaN)."""
    offsets = [0, 1, 2, 3, 4, 7, 9, 9]
    z0 = [0.5, 0.3, 0.3, 0.5, 0.5, 0.5, 0.5, 0.2, 0.7]
    z1 = [0.5, 0.6, 0.6, 0.5, 0.5, 0.5, 0.5, 0.2, 0.7]
    tau = [1.5, 2.0, 1e4, ad.OPAQUE_OPTICAL_DEPTH, 0.1, 1.0, 3.0, 1.0, 1.0]
    seg = ad.Segments.from_arrays(offsets, z0, z1, optical_depth=tau, dtype=dtype)
    d = np.linspace(0.0, 1.0, 101)
    tex = np.repeat(np.arange(7), d.size)
    dd = np.tile(d, 7)
    for fam, n in (("power", 4), ("power", 6), ("power", 8), ("trigonometric", 2), ("trigonometric", 4)):
        for beta in (0.0, 1.0):
            rep = ad.build("moments", seg, family=fam, moments=n, near=0.0, far=1.0, overestimation=beta)
            T = np.asarray(rep.eval(tex, dd), np.float64)
            assert np.all(np.isfinite(T)) and np.all((T >= 0) & (T <= 1)), (n, beta)
            lo, up = (np.asarray(v, np.float64) for v in rep.bounds(uint32(tex), rep.Float(dd)))
            assert np.all((0 <= lo) & (lo <= up) & (up <= 1)), (n, beta)
            if dtype == "float64":
                b = coefficient_array(rep)
                a = rep.params["bias"]
                if fam == "power":
                    Dref = np.concatenate([M.optical_depth(b[t], d, a, beta) for t in range(7)])
                else:
                    Dref = np.concatenate([_trig_depth(b[t], d, a, beta) for t in range(7)])
                ok = b[tex, 0] < 1e3                       # D = b_0 frac: compare T where b_0 is moderate
                assert np.all(np.abs(T - np.exp(-Dref))[ok] <= 1e-6 * (1 + b[tex, 0][ok])), (n, beta)



@pytest.mark.parametrize("fam,n", [("power", 4), ("power", 6), ("power", 8), ("trigonometric", 3),
                                   ("trigonometric", 4)])
def test_texels_of_negligible_optical_depth_are_transparent(fam, n):
    """A texel of the plume (simulated_plume, seed 2, light dir_b, 256^2) whose segments
    carry optical depths of 1e-38..2e-37, repeated on 2048 texels: a build that large runs
    on Dr.Jit's worker threads, which flush float32 subnormals to 0, so the higher moments
    came out 0 (moments of no distribution) and 8 power moments returned NaN between the
    texel's ends.  Such a texel is empty (``NEGLIGIBLE``): T = 1 exactly, as ``exp(-b_0)``
    is in float32; bounds finite.  A texel of optical depth 1e-19 (above the threshold)
    keeps ``D = b_0 frac``: T = 1 there too, bounds finite."""
    z0 = [1.0250361, 1.0426043, 1.0582293, 1.0738543, 1.0894793, 0.2, 0.4]
    z1 = [1.0406611, 1.0582293, 1.0738543, 1.0894793, 1.098516, 0.3, 0.5]
    tau = [1.3026124e-38, 3.1689053e-38, 1.1315636e-37, 1.9486743e-37, 1.1692592e-37, 1e-19, 1e-19]
    reps = 1024
    seg = ad.Segments.from_arrays(np.concatenate([[0], np.tile([5, 7], reps) + 7 * np.repeat(np.arange(reps), 2)]),
                                  np.tile(z0, reps), np.tile(z1, reps), optical_depth=np.tile(tau, reps),
                                  dtype="float32")
    rep = ad.build("moments", seg, family=fam, moments=n, near=0.15894191, far=1.4081748)
    d = np.linspace(0.15, 1.41, 64, dtype=np.float32)
    for t in (0, 1, 2 * reps - 1):
        T = np.asarray(rep.eval(np.full(d.size, t, np.int32), d), np.float64)
        assert np.all(T == 1.0), (t, T)
        lo, up = (np.asarray(v, np.float64) for v in rep.bounds(uint32(np.full(d.size, t)), rep.Float(d)))
        assert np.all(np.isfinite(lo) & np.isfinite(up)), t

def _trig_depth(b, u, alpha, beta):
    out = np.zeros(len(u))
    for j, uj in enumerate(u):
        if uj <= 0 or b[0] <= 0:
            continue
        lo, up = M.trig_bounds(b, 2 * uj - 1, alpha) if uj < 1 else (1.0, 1.0)
        out[j] = b[0] * min(max(lo + beta * (up - lo), 0.0), 1.0)
    return out


@pytest.mark.parametrize("n,warp", [(2, "linear"), (3, "log"), (4, "linear")])
def test_trigonometric_moments_and_bounds_match_reference(n, warp, rng):
    """Coefficients against quadrature, and the bounds of the Cayley-transform route (the
    kernel) against the Toeplitz route of the reference (roots of the kernel polynomial on
    the unit circle by numpy.roots, weights by least squares on t_0..t_n).  Bounds: 1e-6
    (the Hankel pivots of nu are floored at alpha = 1e-9 times the uniform distribution's,
    >= 0.004 M_0 for n = 4: cond <~ 3e11, eps64 cond ~ 6e-5 a priori; measured <= 8e-9)."""
    case = random_segments(rng, texels=16, max_count=10, opaque_fraction=0.0, depth_range=(0.05, 1.0))
    seg = to_segments(case, "float64")
    hc = host_case(seg)
    counts = np.diff(hc["offsets"])
    total = np.add.reduceat(np.append(hc["tau"], 0), hc["offsets"][:-1]) * (counts > 0)
    rep = ad.build("moments", seg, family="trigonometric", moments=n, warp=warp)
    b = coefficient_array(rep)
    tol = EPS["float64"] * (16 + (64 if warp == "log" else 0) + counts) * total
    assert np.all(np.abs(b - M.trig_moments(hc, n, warp)) <= tol[:, None] + 1e-300)
    assert rep.nbytes_per_texel == (2 * n + 1) * 8
    tex, d, uu, lo, up = _bounds_on_receivers(rep, hc, warp)
    ref = np.array([M.trig_bounds(b[t], 2 * x - 1, rep.params["bias"]) for t, x in zip(tex, uu)])
    ne = b[tex, 0] > 0
    np.testing.assert_allclose(lo[ne], ref[ne, 0], rtol=0, atol=1e-6)
    np.testing.assert_allclose(up[ne], ref[ne, 1], rtol=0, atol=1e-6)
    # the reference's own check: the canonical points lie on the unit circle and fit t_0..t_n
    t = np.r_[1.0, (b[0, 1::2] + 1j * b[0, 2::2]) / b[0, 0]] if b[0, 0] > 0 else None
    if t is not None:
        _, w, res, off_circle = M.trig_canonical(t, 0.3)
        assert res < 1e-8 and off_circle < 1e-8 and np.all(w > -1e-8)


def test_trigonometric_bounds_bracket_the_true_distribution(rng):
    """L(phi) <= F(phi-) and F(phi) <= U(phi) on the circle (cut at pi) for the biased
    F = (1 - alpha) D_exact / b_0 + alpha (phi + pi) / (2 pi); tolerance 1e-6 as above."""
    case = random_segments(rng, texels=24, max_count=10, opaque_fraction=0.0, zero_fraction=0.3)
    seg = to_segments(case, "float64")
    hc = host_case(seg)
    rep = ad.build("moments", seg, family="trigonometric", moments=4, near=0.0, far=1.0)
    alpha = rep.params["bias"]
    k = 57
    u = (np.arange(k) + 0.5) / k
    tex = np.repeat(np.arange(seg.n_texels), k)
    lo, up = (np.asarray(v).reshape(seg.n_texels, k) for v in
              rep.bounds(uint32(tex), ad.backend.types().Float64(np.tile(u, seg.n_texels))))
    b0 = coefficient_array(rep)[:, 0]
    phi = np.pi / 2 * (2 * u - 1)
    checked = 0
    for t in range(seg.n_texels):
        if b0[t] <= 0:
            continue
        Fl = (1 - alpha) * R.exact_optical_depth(hc, t, u - 1e-12) / b0[t] + alpha * (phi + np.pi) / (2 * np.pi)
        Fr = (1 - alpha) * R.exact_optical_depth(hc, t, u) / b0[t] + alpha * (phi + np.pi) / (2 * np.pi)
        assert np.all(lo[t] <= Fl + 1e-6), np.max(lo[t] - Fl)
        assert np.all(up[t] >= Fr - 1e-6), np.max(Fr - up[t])
        checked += 1
    assert checked > 10


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_log_warp_means_against_quadrature(dtype, rng):
    """E[x^k] for optical depth uniform in z under the log warp vs float64 Gauss-Legendre in
    t = ln z, for kappa = ln(z1 / z0) / 2 on both sides of KAPPA_SWITCH (series /
    recurrence) and up to 40.  Float64: 1e-14 absolute (45 eps: sums of up to 9 binomial
    terms and 17 series terms, each <= 1; series truncation < 1e-16; measured 4.1e-15);
    float32: 2e-6 (the inputs' rounding, eps32 |ln z| / lambda, and
    the recurrence's growth prod i / kappa <= 0.62)."""
    Float = ad.backend.types().Float32 if dtype == "float32" else ad.backend.types().Float64
    lam = np.concatenate([rng.uniform(0.01, 8, 200), [0.5, 4.0, 20.0, 40.0]])
    x0 = rng.uniform(-1, 1, lam.size)
    x1 = np.minimum(x0 + rng.uniform(0, 2, lam.size) * rng.choice([1e-6, 0.1, 1.0], lam.size), 1.0)
    x0[-4:], x1[-4:] = -1.0, 1.0
    x0h, x1h = (np.asarray(Float(v), np.float64) for v in (x0, x1))
    got = np.stack([np.asarray(m, np.float64) for m in MOD.log_warp_means(Float(x0), Float(x1), Float(lam), 8,
                                                                              dtype)], axis=1)
    gx, gw = np.polynomial.legendre.leggauss(64)
    for i in range(lam.size):
        h = 0.5 * (x1h[i] - x0h[i])
        x = 0.5 * (x0h[i] + x1h[i]) + h * gx
        w = gw * np.exp(lam[i] * h * gx)
        ref = (x[None, :] ** np.arange(9)[:, None]) @ w / w.sum()
        tol = 1e-14 if dtype == "float64" else 2e-6
        assert np.all(np.abs(got[i] - ref) <= tol), (lam[i], x0h[i], x1h[i], np.abs(got[i] - ref).max())
    kappa = lam * 0.5 * (x1h - x0h)
    assert np.any(kappa < MOD.KAPPA_SWITCH) and np.any(kappa > MOD.KAPPA_SWITCH)


def test_default_bias_and_target_follow_the_storage():
    seg32 = ad.Segments.from_arrays([0, 1], [0.2], [0.4], optical_depth=[0.5])
    seg64 = ad.Segments.from_arrays([0, 1], [0.2], [0.4], optical_depth=[0.5], dtype="float64")
    for n in (4, 6, 8):
        assert ad.build("moments", seg32, moments=n).params["bias"] == MOD.DEFAULT_BIAS[n]["float32"]
        assert ad.build("moments", seg64, moments=n).params["bias"] == MOD.DEFAULT_BIAS[n]["float64"]
        rep = ad.build("moments", seg32, moments=n)
        assert rep._target == MOD.MBOIT_TARGET[n]
    assert MOD.DEFAULT_BIAS[4]["float32"] == 5e-7 and MOD.MBOIT_TARGET[4] == (0.0, 0.375, 0.0, 0.375)
    assert ad.build("moments", seg32, bias=1e-3).params["bias"] == 1e-3


def test_gradients_8_moments_log_warp(rng):
    """Reverse mode through the quartic (closed form + Newton polish: at a converged root
    the Newton step's derivative is the implicit one) vs central differences, float64."""
    Float64 = ad.backend.types().Float64
    case = random_segments(rng, texels=3, max_count=4, opaque_fraction=0.0, empty_fraction=0.0,
                           zero_fraction=0.0, depth_range=(0.2, 0.8))
    tex = np.repeat(np.arange(3), 7)
    d = np.tile(np.linspace(0.15, 0.95, 7), 3)
    w = rng.normal(size=tex.size)

    def loss(tau):
        seg = ad.Segments.from_arrays(case["offsets"], case["z0"], case["z1"], optical_depth=tau,
                                      dtype="float64")
        rep = ad.build("moments", seg, moments=8, warp="log", near=0.1, far=1.0)
        return dr.sum(rep.eval(tex, d) * Float64(w))

    x = Float64(case["tau"])
    dr.enable_grad(x)
    dr.backward(loss(x))
    rev = np.asarray(dr.grad(x))
    fd = np.zeros(x.shape[0] if hasattr(x, "shape") else len(case["tau"]))
    for i in range(fd.size):
        p, m = case["tau"].copy(), case["tau"].copy()
        p[i] += 1e-6
        m[i] -= 1e-6
        fd[i] = (np.asarray(loss(p))[0] - np.asarray(loss(m))[0]) / 2e-6
    np.testing.assert_allclose(rev, fd, rtol=1e-5, atol=1e-7)
    assert np.any(np.abs(fd) > 1e-3)

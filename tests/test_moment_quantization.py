"""The optimised 16-bit quantisation of 4 power moments (``quantization='msm'``, Peters and
Klein 2015, sec. 5) against tests/reference/msm_quant_ref.py.

Tolerances:
* the transform's image: every moment vector of a distribution on [0, 1] maps into
  [0, 1]^4 up to the rounding of the published 10-digit constants (measured -6.5e-8 at
  point masses): asserted within 2e-7 of the cube;
* float64 transform vs the reference and the round trip: the matrix entries are <= 83 and
  cond(M) = 243, so ~1e3 eps64 ~ 2e-13: asserted 1e-12;
* stored (decoded) moments, float64 segments: the same codes (q agrees to 1e-15, a code
  could only flip at an exact tie), so 1e-12 (1 + b_0); float32 segments: the decoded
  values rounded once to float32, 1 ulp of b_0;
* lookups vs the reference's float64 Hamburger bound on the same stored moments (float64
  segments): as tests/test_moments.py, the fraction to 1e-7 times b_0 (the Hankel matrix's
  condition number ~ 1 / (alpha p_min) is smaller at the 16-bit alpha than at float64's).
"""
from __future__ import annotations

import drjit as dr
import numpy as np
import pytest

import avsm_dr as ad
from avsm_dr import backend
from avsm_dr.representations import moments as MOD
from cases import random_segments, to_segments
from reference import moments_ref as MR
from reference import msm_quant_ref as ref
from helpers import optical_depth


def random_distributions(rng, n=3000):
    """x-moments (n, 4) of random discrete distributions on u in [0, 1]: 1..8 atoms, some at
    the end points (the extreme points of the moment space are the point masses)."""
    out = np.empty((n, 4))
    for i in range(n):
        k = rng.integers(1, 9)
        u = rng.random(k)
        u[rng.random(k) < 0.15] = rng.integers(0, 2)
        w = rng.exponential(size=k)
        x = 2 * u - 1
        out[i] = [(w * x ** j).sum() / w.sum() for j in range(1, 5)]
    return out


def stored(rep):
    return np.asarray(dr.detach(rep._coef).numpy(), np.float64).reshape(-1, 5)


def test_transform_maps_moment_vectors_into_the_unit_cube(rng):
    m = random_distributions(rng)
    q = MOD.msm_forward(m)
    assert q.min() >= -2e-7 and q.max() <= 1 + 2e-7, (q.min(), q.max())
    qr = np.array([ref.forward(v) for v in m])
    np.testing.assert_allclose(q, qr, rtol=0, atol=1e-12)
    z = np.linspace(0, 1, 2001)                              # the point masses themselves
    qz = MOD.msm_forward(np.stack([(2 * z - 1) ** j for j in range(1, 5)], axis=1))
    assert qz.min() >= -2e-7 and qz.max() <= 1 + 2e-7
    assert qz.min() < 1e-3 and qz.max() > 1 - 1e-3           # and spans the code range


def test_float64_round_trip(rng):
    m = random_distributions(rng, 500)
    np.testing.assert_allclose(MOD.msm_inverse(MOD.msm_forward(m)), m, rtol=0, atol=1e-12)
    np.testing.assert_allclose(MOD.u_to_x(MOD.x_to_u(m)), m, rtol=0, atol=1e-14)
    np.testing.assert_allclose(MOD.MSM_INVERSE @ MOD.MSM_MATRIX, np.eye(4), rtol=0, atol=1e-12)
    q = MOD.msm_forward(m[:50])
    np.testing.assert_allclose(MOD.msm_inverse(q), [ref.inverse(v) for v in q], rtol=0, atol=1e-12)


@pytest.mark.parametrize("precision", MOD.MSM_PRECISIONS)
@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_stored_moments_match_reference(precision, dtype, rng):
    case = random_segments(rng, texels=40, max_count=10)
    seg = to_segments(case, dtype)
    native = stored(ad.build("moments", seg))
    rep = ad.build("moments", seg, precision=precision, quantization="msm")
    want = np.array([ref.stored(b, precision) for b in native])
    got = stored(rep)
    if dtype == "float64":
        assert np.all(np.abs(got - want) <= 1e-12 * (1 + want[:, :1])), np.abs(got - want).max()
    else:
        assert np.all(np.abs(got - want) <= 2.0 ** -23 * want[:, :1] + 1e-30), np.abs(got - want).max()
    np.testing.assert_array_equal(got[:, 0], native[:, 0].astype(np.float32))       # b_0 in float32
    assert rep.nbytes_per_texel == MOD.MSM_BYTES == 12
    texel = ad.build("moments", seg, precision=precision, quantization="msm", depth_range="texel")
    assert texel.nbytes_per_texel == 12 + 8                                         # + float32 range


@pytest.mark.parametrize("beta", [0.0, 0.25, 1.0])
def test_lookup_matches_reference(beta, rng):
    case = random_segments(rng, texels=24, max_count=10, opaque_fraction=0.0)
    seg = to_segments(case, "float64")
    rep = ad.build("moments", seg, precision="unorm16", overestimation=beta)
    assert rep.params["quantization"] == "msm" and rep.params["bias"] == MOD.MSM_UNORM16_BIAS
    b = np.array([ref.stored(v, "unorm16") for v in stored(ad.build("moments", seg))])
    k = 19
    u = (np.arange(k) + 0.37) / k
    tex = np.repeat(np.arange(seg.n_texels), k)
    d = rep.near + np.tile(u, seg.n_texels) * (rep.far - rep.near)
    uu = (d - rep.near) / (rep.far - rep.near)
    Dref = np.concatenate([MR.optical_depth(b[t], uu[tex == t], rep.params["bias"], beta)
                           for t in range(seg.n_texels)])
    D = np.asarray(optical_depth(rep, tex, d))
    tol = 1e-7 * (1 + b[tex, 0])
    assert np.all(np.abs(D - Dref) <= tol), np.max(np.abs(D - Dref))
    T = np.asarray(rep.eval(tex, d))
    assert np.all(np.abs(T - np.exp(-Dref)) <= tol)


def test_defaults_and_scaled_unchanged(rng):
    """Only 4 power moments in unorm16 default to 'msm'; every other build is the
    per-texel scaling, bit for bit the build without the parameter."""
    seg = to_segments(random_segments(rng, texels=16, max_count=8))
    tex = np.repeat(np.arange(16), 9)
    d = np.tile(np.linspace(-0.1, 1.1, 9), 16)
    cases = [({}, "scaled"), ({"precision": "float32"}, "scaled"), ({"precision": "float16"}, "scaled"),
             ({"precision": "unorm8"}, "scaled"), ({"moments": 6, "precision": "unorm16"}, "scaled"),
             ({"family": "trigonometric", "moments": 2, "precision": "unorm16"}, "scaled"),
             ({"precision": "unorm16"}, "msm")]
    for params, want in cases:
        rep = ad.build("moments", seg, **params)
        assert rep.params["quantization"] == want, params
        explicit = ad.build("moments", seg, **dict(params, quantization=want))
        np.testing.assert_array_equal(np.asarray(rep.eval(tex, d)), np.asarray(explicit.eval(tex, d)))
    plain = ad.build("moments", seg, precision="unorm16", quantization="scaled")
    assert plain.params["bias"] == MOD.DEFAULT_BIAS[4]["unorm16"] and plain.nbytes_per_texel == 14
    assert ad.build("moments", seg, precision="float16", quantization="msm").params["bias"] == \
        MOD.DEFAULT_BIAS[4]["float16"]


@pytest.mark.parametrize("params", [
    {"quantization": "msm"}, {"quantization": "msm", "precision": "float32"},
    {"quantization": "msm", "precision": "unorm8"},
    {"quantization": "msm", "precision": "unorm16", "moments": 6},
    {"quantization": "msm", "precision": "unorm16", "moments": 8},
    {"quantization": "msm", "precision": "float16", "family": "trigonometric", "moments": 2},
    {"quantization": "bogus", "precision": "unorm16"}, {"quantization": 16, "precision": "unorm16"}])
def test_bad_arguments(params):
    seg = ad.Segments.from_arrays([0, 1, 2], [0.2, 0.1], [0.4, 0.5], optical_depth=[0.5, 1.0])
    with pytest.raises(ValueError, match="^quantization:"):
        ad.build("moments", seg, **params)
    if params.get("moments", 4) != 4 or "family" in params:         # the schema constraint says so too
        assert not ad.allows("moments", params)


def test_straight_through_gradient():
    """The stored moments carry the native moments' derivative (straight through), so
    dT/dtau is finite and the derivative of the store equals the native one."""
    Float = backend.types().Float
    data = random_segments(np.random.default_rng(9), texels=2, max_count=6, empty_fraction=0.0,
                           opaque_fraction=0.0)
    grads = {}
    for q in ("scaled", "msm"):
        tau = Float(data["tau"].astype(np.float32))
        dr.enable_grad(tau)
        s = ad.Segments.from_arrays(data["offsets"], data["z0"], data["z1"], optical_depth=tau)
        rep = ad.build("moments", s, precision="unorm16", quantization=q)
        dr.backward(dr.sum(rep._coef))
        grads[q] = np.asarray(dr.grad(tau).numpy())
        dr.set_grad(tau, 0)
        T = rep.eval([0], [0.9])
        dr.backward(T)
        assert np.all(np.isfinite(np.asarray(dr.grad(tau).numpy())))
    np.testing.assert_array_equal(grads["msm"], grads["scaled"])


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_adversarial_texels_finite(dtype):
    """One segment (rank-1 moments), a point mass at near / far, a huge optical depth."""
    seg = ad.Segments.from_arrays([0, 1, 2, 3, 4, 4], [0.3, 0.0, 1.0, 0.2], [0.3, 0.0, 1.0, 0.6],
                                  optical_depth=[0.7, 2.0, 1.0, 1e4], dtype=dtype)
    for p in MOD.MSM_PRECISIONS:
        rep = ad.build("moments", seg, precision=p, quantization="msm", near=0.0, far=1.0)
        tex = np.repeat(np.arange(5), 11)
        T = np.asarray(rep.eval(tex, np.tile(np.linspace(-0.1, 1.1, 11), 5)))
        assert np.all(np.isfinite(T)) and np.all((T >= 0) & (T <= 1))
        np.testing.assert_array_equal(stored(rep)[4], 0.0)                     # empty texel

"""Linear representations (FOM, OSM, any orthonormal basis) against the float64 NumPy
reference in tests/reference/linear_ref.py, plus properties, gradients and bad input.

Tolerances (eps = unit roundoff: 2^-24 for float32, 2^-53 for float64), derived, not fitted:

* coefficient k of a texel with N segments, S_k = max|f_k| sum_i tau_i:
      |a_k - ref| <= eps (C_k + N) S_k + max|f_k| sum_{i near a boundary} tau_i min(1, 8 eps / du_i)
  ``C_k`` bounds one term's rounding (Fourier: the angle 2 pi k u carries ~(6 pi k + 2 pi) eps,
  so C_k = 20 k + 16; slices/polynomials: their evaluation), ``N eps S_k`` the running float
  sum of N terms (atomic adds in any order).  The last term is the conditioning of the data,
  not the kernel: a segment's normalised depths carry ~4 eps error, which moves
  ``tau / du`` per unit of u across a slice boundary or near/far (a delta within 8 eps of
  a slice boundary may land in the neighbour slice).
* D(u) = sum_k a_k g_k(u):  sum_k (|da_k| max|g_k| + |a_k| dg_k) + 2 K eps sum_k |a_k g_k|,
  ``dg_k`` the rounding of g_k at a float receiver (Fourier 8 eps; slices 8 n eps, since
  g_k = clamp(n u - k) has slope n; Legendre 8 (k + 1) eps; cosine 8 eps).
* T = clamp(exp(-D), 0, 1) is 1-Lipschitz in D where D >= 0 and flat below:
      |T - ref| <= exp(-max(min(D, Dref), 0)) tolD + 4 eps.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import avsm_dr as ad
import drjit as dr
from avsm_dr.representations.basis import Basis
from avsm_dr.representations.fom import FourierBasis
from avsm_dr.representations.osm import PiecewiseConstantBasis

from cases import random_segments, to_segments
from reference import linear_ref as R
from helpers import optical_depth

EPS = {"float32": 2.0 ** -24, "float64": 2.0 ** -53}
DTYPES = ["float32", "float64"]

#: (kind, params) of the linear representations under test.
LINEAR = [
    ("fom", {"harmonics": 1}),
    ("fom", {"harmonics": 3}),
    ("fom", {"harmonics": 8}),
    ("osm", {"slices": 1}),
    ("osm", {"slices": 7}),
    ("osm", {"slices": 32}),
    ("basis", {"basis": "legendre", "n": 6}),
    ("basis", {"basis": "cosine", "n": 6}),
]


def lin_id(c):
    return c[0] + "".join(f"-{k}={v}" for k, v in c[1].items())


# ----------------------------------------------------------------------------
# Reference model of one configuration: coefficients, D, and the error bounds
# ----------------------------------------------------------------------------
class Model:
    """Reference coefficients and the per-coefficient constants of the tolerance."""

    def __init__(self, kind, params, case, rng_kw):
        self.kind, self.case = kind, case
        if kind == "fom":
            n = params["harmonics"]
            self.coeffs = R.fourier_coefficients(case, n, **rng_kw)
            ks = [0] + [k for k in range(1, n + 1) for _ in (0, 1)]
            self.fmax = np.full(2 * n + 1, 2.0)
            self.C = np.array([20.0 * k + 16 for k in ks])
            self.gmax = np.array([0.5] + [1 / (math.pi * k) for k in ks[1:]])
            self.dg = np.full(2 * n + 1, 8.0)
            self.boundaries = np.array([0.0, 1.0])
        elif kind == "osm":
            n = params["slices"]
            self.coeffs = R.slice_coefficients(case, n, **rng_kw)
            self.fmax = np.ones(n)
            self.C = np.full(n, 8.0)
            self.gmax = np.ones(n)
            self.dg = np.full(n, 8.0 * n)
            self.boundaries = np.arange(n + 1) / n
        else:
            n = params["n"]
            fs = (R.legendre_functions if params["basis"] == "legendre" else R.cosine_functions)(n)
            self.fs = fs
            self.coeffs = R.basis_coefficients(case, fs, **rng_kw)
            if params["basis"] == "legendre":
                self.fmax = np.sqrt(2 * np.arange(n) + 1.0)
                self.C = 8.0 * (np.arange(n) + 2) ** 2        # recurrence rounding grows ~k^2
                self.gmax = 1 / np.sqrt(2 * np.arange(n) + 1.0)
                self.dg = 8.0 * (np.arange(n) + 1)
            else:
                self.fmax = np.array([1.0] + [math.sqrt(2)] * (n - 1))
                self.C = 20.0 * np.arange(n) + 16
                self.gmax = np.array([1.0] + [math.sqrt(2) / (math.pi * k) for k in range(1, n)])
                self.dg = np.full(n, 8.0)
            self.boundaries = np.array([0.0, 1.0])
        self.near, self.span = R.ranges(case, **rng_kw)

    def optical_depth(self, t, u):
        c = self.coeffs[t]
        if self.kind == "fom":
            return R.fourier_optical_depth(c, u)
        if self.kind == "osm":
            return R.slice_optical_depth(c, u)
        return R.basis_optical_depth(c, self.fs, u)

    def coeff_tol(self, eps):
        """(T, K) absolute bound on the coefficient error (module docstring)."""
        off = self.case["offsets"]
        T = len(off) - 1
        tol = np.zeros_like(self.coeffs)
        for t in range(T):
            z0 = self.case["z0"][off[t]:off[t + 1]]
            z1 = self.case["z1"][off[t]:off[t + 1]]
            tau = self.case["tau"][off[t]:off[t + 1]]
            u0, u1 = (z0 - self.near[t]) / self.span[t], (z1 - self.near[t]) / self.span[t]
            du = u1 - u0
            near_b = np.zeros(tau.size, bool)
            for b in self.boundaries:
                near_b |= (u0 - 8 * eps <= b) & (b <= u1 + 8 * eps)
            cond = np.where(du > 0, np.minimum(1, 8 * eps / np.where(du > 0, du, 1)), 1)
            cond_sum = np.sum(tau * cond * near_b)
            tol[t] = eps * (self.C + tau.size) * self.fmax * tau.sum() + self.fmax * cond_sum
        return tol

    def depth_tol(self, t, u, coeff_tol, eps):
        a = np.abs(self.coeffs[t])
        K = a.size
        return (np.sum(coeff_tol[t] * self.gmax) + eps * np.sum(a * self.dg)
                + 2 * K * eps * np.sum(a * self.gmax)) * np.ones_like(u)


def host_case(seg):
    h = seg.numpy()
    return dict(offsets=h["offsets"], z0=h["z0"], z1=h["z1"], tau=h["optical_depth"], dtype=seg.dtype)


def coefficient_array(rep):
    return np.stack([np.asarray(c, np.float64) for c in rep.coefficients], axis=1)


def receivers(case, t, near, span, dtype):
    """Depths for texel t: its segment ends, near/far, in front and behind, random."""
    off = case["offsets"]
    z = np.concatenate([case["z0"][off[t]:off[t + 1]], case["z1"][off[t]:off[t + 1]]])
    extra = near + span * np.array([-0.5, 0.0, 0.123, 0.5, 0.77, 1.0, 1.5])
    d = np.concatenate([z[:40], extra])
    return d.astype(np.float32).astype(np.float64) if dtype == "float32" else d


def check_against_reference(kind, params, case, dtype, **rng_kw):
    seg = to_segments(case, dtype)
    hc = host_case(seg)
    rep = ad.build(kind, seg, **params, **rng_kw)
    model = Model(kind, params, hc, rng_kw)
    eps = EPS[dtype]

    # ---- coefficients
    got = coefficient_array(rep)
    ctol = model.coeff_tol(eps)
    assert np.all(np.isfinite(got))
    bad = np.abs(got - model.coeffs) > ctol
    assert not bad.any(), (f"coefficients: max excess "
                           f"{np.max((np.abs(got - model.coeffs) - ctol)[bad]):.3g}")

    # ---- optical depth and transmittance at receivers
    T = seg.n_texels
    tex, dep, Dref, Dtol = [], [], [], []
    for t in range(T):
        d = receivers(hc, t, model.near[t], model.span[t], dtype)
        u = np.clip((d - model.near[t]) / model.span[t], 0, 1)
        tex.append(np.full(d.size, t))
        dep.append(d)
        Dref.append(model.optical_depth(t, u))
        Dtol.append(model.depth_tol(t, u, ctol, eps))
    tex, dep, Dref, Dtol = map(np.concatenate, (tex, dep, Dref, Dtol))
    D = np.asarray(optical_depth(rep, tex, dep), np.float64)
    assert np.all(np.abs(D - Dref) <= Dtol), f"D: max error {np.max(np.abs(D - Dref)):.3g}"
    Tgot = np.asarray(rep.eval(tex, dep), np.float64)
    Tref = R.transmittance(Dref)
    Ttol = np.exp(-np.maximum(np.minimum(D, Dref), 0)) * Dtol + 4 * eps
    assert np.all((Tgot >= 0) & (Tgot <= 1))
    assert np.all(np.abs(Tgot - Tref) <= Ttol), f"T: max error {np.max(np.abs(Tgot - Tref)):.3g}"
    return rep


# ----------------------------------------------------------------------------
# Inputs
# ----------------------------------------------------------------------------
def adversarial_case(rng):
    """Overlapping, identical, zero-length (also on slice boundaries and at near/far),
    nested and touching segments; empty texels at both ends and in the middle."""
    texels = [
        [],                                                      # empty
        [(0.2, 0.6, 0.7), (0.2, 0.6, 0.7), (0.3, 0.4, 1.2)],     # identical + nested
        [(0.5, 0.5, 0.9), (0.25, 0.25, 0.3), (0.0, 0.0, 0.2)],   # zero-length (boundaries)
        [(1.0, 1.0, 0.4), (0.1, 0.30000001, 0.5)],               # zero-length at far
        [],                                                      # empty
        [(0.0, 1.0, 2.0)],                                       # spans the whole range
        [(0.1, 0.2, 0.3), (0.2, 0.3, 0.3), (0.3, 0.4, 0.3)],     # touching
        [(0.45, 0.45 + 1e-6, 0.8), (0.7, 0.7 + 1e-4, 0.6)],      # tiny lengths
        [],
    ]
    offsets = np.concatenate([[0], np.cumsum([len(t) for t in texels])])
    segs = [s for t in texels for s in t]
    z0, z1, tau = (np.array([s[i] for s in segs]) for i in range(3))
    return dict(offsets=offsets, z0=z0, z1=z1, tau=tau)


def dense_case(rng, n=1200):
    """One texel with 1000+ overlapping segments, an empty texel, a short texel."""
    z0 = rng.uniform(0.0, 0.9, n)
    z1 = z0 + rng.uniform(0.0, 0.1, n)
    z1[:50] = z0[:50]
    tau = rng.exponential(0.01, n)
    z0 = np.concatenate([z0, [0.3, 0.5]])
    z1 = np.concatenate([z1, [0.4, 0.5]])
    tau = np.concatenate([tau, [0.5, 0.2]])
    return dict(offsets=np.array([0, n, n, n + 2]), z0=z0, z1=z1, tau=tau)


CASES = {
    "random": lambda rng: random_segments(rng, texels=24, max_count=12, opaque_fraction=0.0),
    "adversarial": adversarial_case,
    "dense": dense_case,
    "shifted": lambda rng: random_segments(rng, texels=12, max_count=8, opaque_fraction=0.0,
                                           depth_range=(10.0, 14.0)),
}


# ----------------------------------------------------------------------------
# Agreement with the reference
# ----------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("case_name", sorted(CASES))
@pytest.mark.parametrize("config", LINEAR, ids=lin_id)
def test_matches_reference_global(config, case_name, dtype, rng):
    kind, params = config
    check_against_reference(kind, params, CASES[case_name](rng), dtype)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("case_name", ["random", "adversarial"])
@pytest.mark.parametrize("config", LINEAR, ids=lin_id)
def test_matches_reference_per_texel_range(config, case_name, dtype, rng):
    kind, params = config
    rep = check_against_reference(kind, params, CASES[case_name](rng), dtype,
                                  depth_range="texel")
    assert rep.params["depth_range"] == "texel"


#: Sizes beyond LIST_UNROLL (legendre: the chunked list path) and large indexed sizes.
#: Legendre only in float64 (its float32 recurrence exceeds the model's bound at n = 45,
#: before and after the chunking: a limit of the error model, not of the chunks); cosine
#: n <= 36 (the reference's 64-point Gauss-Legendre resolves cos(pi k u) to k ~ 40).
LARGE = [(("fom", {"harmonics": 45}), "float32"), (("fom", {"harmonics": 45}), "float64"),
         (("osm", {"slices": 300}), "float32"), (("osm", {"slices": 300}), "float64"),
         (("basis", {"basis": "legendre", "n": 45}), "float64"),
         (("basis", {"basis": "cosine", "n": 36}), "float32"),
         (("basis", {"basis": "cosine", "n": 36}), "float64")]


@pytest.mark.parametrize("config, dtype", LARGE, ids=lambda c: c if isinstance(c, str) else lin_id(c))
def test_matches_reference_large_sizes(config, dtype, rng):
    """The indexed kernels (one lane per segment x coefficient) and the chunked list
    path hold the same error bounds as the small sizes."""
    kind, params = config
    check_against_reference(kind, params, CASES["random"](rng), dtype)


class _ListOnly:
    """Mixin: the same basis through its list forms (indexed = False)."""
    indexed = False


@pytest.mark.parametrize("basis", [FourierBasis(5), PiecewiseConstantBasis(9),
                                   ad.representations.basis.CosineBasis(7)], ids=repr)
def test_indexed_forms_equal_list_forms(basis, rng):
    """f_at / F_at / g_at / average_at are the list forms, coefficient by coefficient:
    coefficients and T agree to float64 rounding (1e-13 relative to the largest
    coefficient: opaque segments make coefficients ~1e4)."""
    listed = type("List" + type(basis).__name__, (_ListOnly, type(basis)), {})(basis.n)
    seg = to_segments(random_segments(rng, texels=10, max_count=8), "float64")
    a = ad.build("basis", seg, basis=basis)
    b = ad.build("basis", seg, basis=listed)
    ca, cb = coefficient_array(a), coefficient_array(b)
    np.testing.assert_allclose(ca, cb, rtol=0, atol=1e-13 * np.abs(cb).max())
    tex = np.repeat(np.arange(10), 7)
    d = np.tile(np.linspace(-0.1, 1.1, 7), 10)
    np.testing.assert_allclose(np.asarray(a.eval(tex, d)), np.asarray(b.eval(tex, d)), rtol=0, atol=1e-13)


@pytest.mark.parametrize("kind, arg", [("fom", "harmonics"), ("osm", "slices"), ("basis", "n")])
def test_trace_does_not_grow_with_size(kind, arg, rng):
    """Build + eval trace the same kernels whatever the size (indexed bases) or a number
    of fixed-size chunks (legendre): the operations per kernel do not grow with N (one
    kernel for all N made the cost quadratic).  A structural check via
    dr.kernel_history, not a timing."""
    seg = to_segments(random_segments(rng, texels=8, max_count=10), "float32")
    extra = {"basis": "cosine"} if kind == "basis" else {}
    biggest = {}
    for N in (40, 400):
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history()
        rep = ad.build(kind, seg, **extra, **{arg: N})
        np.asarray(rep.eval(np.arange(8), np.full(8, 0.5)))
        hist = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        biggest[N] = max(k["operation_count"] for k in hist)
    assert biggest[400] == biggest[40], biggest
    # the list path: chunks of LIST_CHUNK coefficients, so its kernels stay bounded too
    ops = []
    for n in (40, 200):
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history()
        rep = ad.build("basis", seg, basis="legendre", n=n)
        np.asarray(rep.eval(np.arange(8), np.full(8, 0.5)))
        ops.append(max(k["operation_count"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT))
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert ops[1] <= ops[0] * 1.2, ops


@pytest.mark.parametrize("config", LINEAR, ids=lin_id)
def test_explicit_range_wider_than_content(config, rng):
    """An explicit [near, far] around the content (tight on one side, loose on both) matches
    the reference; one that cuts the content is refused (tests/test_depth_range.py)."""
    kind, params = config
    case = random_segments(rng, texels=16, max_count=10, opaque_fraction=0.0, depth_range=(0.3, 0.6))
    lo = float(np.min(case["z0"]))
    check_against_reference(kind, params, case, "float64", near=lo, far=0.7)
    check_against_reference(kind, params, case, "float32", near=-0.5, far=2.0)


def test_fourier_zero_length_is_eqs_5_6(rng):
    """A zero-length segment at d_i adds a'_k = 2 tau cos(2 pi k d_i), b'_k = 2 tau sin(...)."""
    d = np.array([0.0, 0.13, 0.5, 0.77, 1.0])
    tau = np.array([0.3, 0.7, 1.1, 0.2, 0.5])
    seg = ad.Segments.from_arrays(np.arange(6), d, d, optical_depth=tau, dtype="float64")
    rep = ad.build("fom", seg, harmonics=4, near=0.0, far=1.0)
    c = rep.coefficients                       # [a'_0, a'_1, b'_1, ..., a'_4, b'_4]
    for k in range(5):
        np.testing.assert_allclose(np.asarray(c[max(2 * k - 1, 0)]), 2 * tau * np.cos(2 * np.pi * k * d),
                                   rtol=0, atol=64 * EPS["float64"])
    for k in range(1, 5):
        np.testing.assert_allclose(np.asarray(c[2 * k]), 2 * tau * np.sin(2 * np.pi * k * d),
                                   rtol=0, atol=64 * EPS["float64"])


def test_osm_coefficients_are_slice_optical_depths():
    """One segment over [0.1, 0.6] with tau = 1, 4 slices of [0, 1]: fractions 0.15/0.5,
    0.25/0.5, 0.1/0.5, 0; D is exact at slice boundaries."""
    seg = ad.Segments.from_arrays([0, 1], [0.1], [0.6], optical_depth=[1.0], dtype="float64")
    rep = ad.build("osm", seg, slices=4, near=0.0, far=1.0)
    np.testing.assert_allclose(coefficient_array(rep)[0], [0.3, 0.5, 0.2, 0.0], atol=1e-15)
    T = np.asarray(rep.eval([0] * 5, [0.0, 0.25, 0.5, 0.75, 1.0]))
    np.testing.assert_allclose(T, np.exp(-np.array([0, 0.3, 0.8, 1.0, 1.0])), rtol=1e-15)
    assert rep.nbytes_per_texel == 4 * 8


@pytest.mark.parametrize("dtype", DTYPES)
def test_deltas_on_slice_boundaries_near_and_far(dtype):
    """Zero-length segments exactly on slice boundaries go to the slice starting there,
    one at far to the last slice (closed), one at near to the first; exact in any
    precision (u = k/4 is exact).  A delta outside [near, far] is refused (base.py's
    depth-range rule), not clipped."""
    d = np.array([0.0, 0.25, 0.5, 0.75, 1.0])
    tau = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    seg = ad.Segments.from_arrays([0, 5], d, d, optical_depth=tau, dtype=dtype)
    osm = ad.build("osm", seg, slices=4, near=0.0, far=1.0)
    np.testing.assert_array_equal(coefficient_array(osm)[0], [1.0, 2.0, 3.0, 9.0])
    T = np.asarray(osm.eval([0] * 3, [-1.0, 1.0, 2.0]), np.float64)
    Tfar = np.float64(np.exp(np.float64(-15.0)).astype(dtype))
    np.testing.assert_allclose(T, [1.0, Tfar, Tfar], rtol=4 * EPS[dtype])
    fom = ad.build("fom", seg, harmonics=2, near=0.0, far=1.0)
    ref = 2 * np.array([[np.cos(2 * np.pi * k * u), np.sin(2 * np.pi * k * u)] for k in (1, 2) for u in d])
    w = np.tile(tau, 2)
    a, b = ref[:, 0] * w, ref[:, 1] * w
    expect = [2 * 15.0, a[:5].sum(), b[:5].sum(), a[5:].sum(), b[5:].sum()]
    np.testing.assert_allclose(coefficient_array(fom)[0], expect, rtol=0,
                               atol=64 * EPS[dtype] * 2 * 15.0)
    np.testing.assert_allclose(np.asarray(fom.eval([0, 0], [0.0, 1.0]), np.float64),
                               [1.0, Tfar], rtol=8 * EPS[dtype])
    outside = ad.Segments.from_arrays([0, 7], np.r_[-0.5, d, 1.5], np.r_[-0.5, d, 1.5],
                                      optical_depth=np.r_[0.5, tau, 6.0], dtype=dtype)
    for kind, p in (("osm", {"slices": 4}), ("fom", {"harmonics": 2})):
        with pytest.raises(ValueError, match=r"^near: 0\.0 .* and far: 1\.0 "):
            ad.build(kind, outside, near=0.0, far=1.0, **p)


# ----------------------------------------------------------------------------
# Exactness, empty and opaque texels
# ----------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("depth_range", ["global", "texel"])
@pytest.mark.parametrize("harmonics", [1, 3, 7, 16])
def test_fom_exact_at_near_and_far(harmonics, depth_range, dtype, rng):
    """T(near) = 1 exactly; T(far) = exp(-sum tau) up to the float sum of the N taus:
    |T - Tref| <= Tref eps (N + 4) S + 4 eps  (a'_0 = sum 2 tau, eq. 3 has sin(2 pi k) = 0)."""
    case = random_segments(rng, texels=32, max_count=20, opaque_fraction=0.0)
    seg = to_segments(case, dtype)
    hc = host_case(seg)
    rep = ad.build("fom", seg, harmonics=harmonics, depth_range=depth_range)
    near, span = R.ranges(hc, depth_range=depth_range)
    tex = np.arange(seg.n_texels)
    far = near + span if depth_range == "texel" else np.full(seg.n_texels, hc["z1"].max())
    assert np.all(np.asarray(rep.eval(tex, near)) == 1.0)
    total = np.add.reduceat(np.append(hc["tau"], 0), hc["offsets"][:-1])
    total[np.diff(hc["offsets"]) == 0] = 0
    counts = np.diff(hc["offsets"])
    eps = EPS[dtype]
    Tref = np.exp(-total)
    T = np.asarray(rep.eval(tex, far), np.float64)
    assert np.all(np.abs(T - Tref) <= Tref * eps * (counts + 4) * total + 4 * eps)


@pytest.mark.parametrize("config", LINEAR, ids=lin_id)
def test_empty_texels_are_one(config):
    kind, params = config
    off = np.array([0, 0, 2, 2, 2])
    seg = ad.Segments.from_arrays(off, [0.2, 0.5], [0.4, 0.5], optical_depth=[1.0, 2.0])
    for rng_kw in ({}, {"depth_range": "texel"}, {"near": -1.0, "far": 3.0}):
        rep = ad.build(kind, seg, **params, **rng_kw)
        d = np.linspace(-2, 4, 25)
        for t in (0, 2, 3):
            assert np.all(np.asarray(rep.eval(np.full(d.size, t), d)) == 1.0)
        assert np.all(coefficient_array(rep)[[0, 2, 3]] == 0)
    none = ad.Segments.from_arrays([0, 0, 0], [], [], optical_depth=[])
    rep = ad.build(kind, none, **params)
    assert np.all(np.asarray(rep.eval([0, 1, 1], [0.0, 0.5, 2.0])) == 1.0)


@pytest.mark.parametrize("config", LINEAR, ids=lin_id)
@pytest.mark.parametrize("depth_range", ["global", "texel"])
def test_degenerate_range(config, depth_range):
    """All segments zero-length at one depth: near = far, the range is widened to
    1e-6 |near|; T = 1 at near, exp(-sum tau) behind it, finite everywhere."""
    kind, params = config
    seg = ad.Segments.from_arrays([0, 2], [3.0, 3.0], [3.0, 3.0], optical_depth=[1.0, 0.5])
    rep = ad.build(kind, seg, **params, depth_range=depth_range)
    T = np.asarray(rep.eval([0] * 4, [2.0, 3.0, 3.001, 5.0]), np.float64)
    np.testing.assert_allclose(T, [1.0, 1.0, np.exp(-1.5), np.exp(-1.5)], rtol=4 * EPS["float32"])


@pytest.mark.parametrize("config", LINEAR, ids=lin_id)
def test_opaque_segments_stay_finite(config, rng):
    """Transmittance 0 -> tau = OPAQUE_OPTICAL_DEPTH = 1e4: coefficients ~1e4, no NaN/inf,
    T in [0, 1], and T = 0 behind everything (D(far) = sum tau >= 1e4 -> exp underflows)."""
    kind, params = config
    case = random_segments(rng, texels=32, max_count=10, opaque_fraction=0.3, empty_fraction=0.0)
    seg = ad.Segments.from_arrays(case["offsets"], case["z0"], case["z1"],
                                  transmittance=np.where(case["tau"] >= 1e4, 0.0,
                                                         np.exp(-case["tau"])))
    rep = ad.build(kind, seg, **params)
    assert np.all(np.isfinite(coefficient_array(rep)))
    tex = np.repeat(np.arange(32), 50)
    d = np.tile(np.linspace(-0.1, 1.1, 50), 32)
    T = np.asarray(rep.eval(tex, d))
    assert np.all(np.isfinite(T)) and np.all((T >= 0) & (T <= 1))
    hc = host_case(seg)
    opaque = np.add.reduceat(hc["tau"] >= 1e4, hc["offsets"][:-1]) > 0
    opaque &= np.diff(hc["offsets"]) > 0
    Tfar = np.asarray(rep.eval(np.arange(32), np.full(32, hc["z1"].max())))
    assert np.all(Tfar[opaque] == 0)


# ----------------------------------------------------------------------------
# Convergence on a smooth medium
# ----------------------------------------------------------------------------
def gaussian_medium(M=1600):
    """A Gaussian density bump (sigma 0.08, total optical depth 2) cut into M abutting
    segments over [0.1, 0.9], each holding the exact integral of the density."""
    from scipy.special import erf
    edges = np.linspace(0.1, 0.9, M + 1)
    cdf = 0.5 * (1 + erf((edges - 0.5) / (0.08 * math.sqrt(2))))
    return ad.Segments.from_arrays([0, M], edges[:-1], edges[1:],
                                   optical_depth=2.0 * np.diff(cdf), dtype="float64")


@pytest.mark.parametrize("kind,key,ns,floor", [
    ("fom", "harmonics", [2, 4, 8, 16], 2e-6),
    ("osm", "slices", [8, 16, 32, 64], 2e-3),
    ("basis:legendre", "n", [8, 16, 24, 32], 2e-6),
    ("basis:cosine", "n", [4, 8, 16, 32], 2e-6),
])
def test_converges_on_smooth_medium(kind, key, ns, floor):
    """Error vs the exact curve shrinks with the basis size.  FOM: the bump's spectrum decays
    like exp(-(2 pi k 0.1)^2 / 2) (width 0.1 in u), so 16 harmonics leave only the
    staircase of 1600 uniform segments (~1e-6).  OSM: D is interpolated linearly between
    slice boundaries, error ~ D'' / (8 n^2)."""
    seg = gaussian_medium()
    d = np.linspace(0.0, 1.0, 301)
    exact = np.asarray(ad.build("exact", seg).eval(np.zeros(d.size, int), d))
    errors = []
    for n in ns:
        if kind.startswith("basis:"):
            rep = ad.build("basis", seg, basis=kind.split(":")[1], n=n)
        else:
            rep = ad.build(kind, seg, **{key: n})
        errors.append(np.abs(np.asarray(rep.eval(np.zeros(d.size, int), d)) - exact).max())
    assert all(b < a for a, b in zip(errors, errors[1:])) or errors[-1] < floor, errors
    assert errors[-1] < floor, errors
    assert errors[0] > 10 * errors[-1], errors


# ----------------------------------------------------------------------------
# Properties (hypothesis)
# ----------------------------------------------------------------------------
@st.composite
def segment_sets(draw, max_texels=3, max_count=8, opaque=True):
    texels = draw(st.integers(1, max_texels))
    counts = [draw(st.integers(0, max_count)) for _ in range(texels)]
    n = sum(counts)
    depth = st.floats(-5.0, 5.0, allow_nan=False, width=32)
    z0 = np.array([draw(depth) for _ in range(n)])
    length = np.array([draw(st.one_of(st.just(0.0), st.floats(0.0, 3.0, width=32)))
                       for _ in range(n)])
    taus = st.floats(0.0, 5.0, width=32)
    if opaque:
        taus = st.one_of(taus, st.just(ad.OPAQUE_OPTICAL_DEPTH))
    tau = np.array([draw(taus) for _ in range(n)])
    offsets = np.concatenate([[0], np.cumsum(counts)])
    return dict(offsets=offsets, z0=z0, z1=z0 + length, tau=tau)


@settings(max_examples=40, deadline=None)
@given(case=segment_sets(), config=st.sampled_from(LINEAR),
       depth_range=st.sampled_from(["global", "texel"]),
       depths=st.lists(st.floats(-10, 10, width=32), min_size=1, max_size=12))
def test_property_transmittance_in_unit_interval(case, config, depth_range, depths):
    kind, params = config
    seg = to_segments(case)
    rep = ad.build(kind, seg, **params, depth_range=depth_range)
    d = np.array(depths)
    for t in range(seg.n_texels):
        T = np.asarray(rep.eval(np.full(d.size, t), d))
        assert np.all((T >= 0) & (T <= 1)), T


@settings(max_examples=40, deadline=None)
@given(case=segment_sets(), slices=st.integers(1, 40),
       depth_range=st.sampled_from(["global", "texel"]))
def test_property_osm_non_increasing(case, slices, depth_range):
    """OSM is monotone: a_k >= 0 and every g_k non-decreasing, so D is non-decreasing
    exactly, also across slice boundaries under float rounding (the min() in the
    lookup).  T = exp(-D) only to one float32 ulp (2^-24 below 1): Dr.Jit's float32 exp
    is not monotone at the ulp level (found here: exp(-0.2586691) < exp(-0.25866917))."""
    seg = to_segments(case)
    rep = ad.build("osm", seg, slices=slices, depth_range=depth_range)
    for t in range(seg.n_texels):
        lo, hi = (float(np.asarray(rep.near)[t]), float(np.asarray(rep.far)[t])) \
            if depth_range == "texel" else (rep.near, rep.far)
        d = np.sort(np.concatenate([np.linspace(lo - 1, hi + 1, 200),
                                    lo + (hi - lo) * np.arange(slices + 1) / slices]))
        d = d.astype(np.float32)
        tex = np.full(d.size, t)
        D = np.asarray(optical_depth(rep, tex, d))
        assert np.all(np.diff(D) >= 0), np.diff(D).min()
        T = np.asarray(rep.eval(tex, d))
        assert np.all(np.diff(T) <= 2.0 ** -24), np.diff(T).max()


@settings(max_examples=40, deadline=None)
@given(case=segment_sets(opaque=False, max_count=6), harmonics=st.integers(1, 12),
       depth_range=st.sampled_from(["global", "texel"]))
def test_property_fom_exact_at_near_and_far(case, harmonics, depth_range):
    """T(near) = 1 and T(far) = exp(-sum tau).  A degenerate range (all of a texel's
    segments zero-length at one depth) is widened to 1e-6 |near| + 1.2e-38, shorter than
    float32 resolves there, so its far end is probed at near + 2 span (clamped to u = 1)."""
    seg = to_segments(case)
    hc = host_case(seg)
    rep = ad.build("fom", seg, harmonics=harmonics, depth_range=depth_range)
    near, span = R.ranges(hc, depth_range=depth_range)
    T = seg.n_texels
    degenerate = span <= (R.MIN_SPAN_REL["float32"] * np.abs(near) + R.MIN_SPAN_ABS["float32"]) * (1 + 1e-9)
    far = np.where(degenerate, near + 2 * span, near + span)
    tex = np.arange(T)
    assert np.all(np.asarray(rep.eval(tex, near.astype(np.float32))) == 1.0)
    counts = np.diff(hc["offsets"])
    total = np.array([hc["tau"][hc["offsets"][t]:hc["offsets"][t + 1]].sum() for t in range(T)])
    eps = EPS["float32"]
    Tref = np.exp(-total)
    got = np.asarray(rep.eval(tex, far.astype(np.float32)), np.float64)
    assert np.all(np.abs(got - Tref) <= Tref * eps * (counts + 4) * total + 4 * eps)


# ----------------------------------------------------------------------------
# Gradients (float64, central finite differences)
# ----------------------------------------------------------------------------
GRAD_CONFIGS = [
    ("fom", {"harmonics": 4}),
    ("osm", {"slices": 8}),
    ("basis", {"basis": "legendre", "n": 5}),
    ("basis", {"basis": "cosine", "n": 5}),
]


def _grad_setup(rng):
    case = random_segments(rng, texels=4, max_count=5, opaque_fraction=0.0, empty_fraction=0.0,
                           zero_fraction=0.0, depth_range=(0.2, 0.8))
    case["tau"] = np.minimum(case["tau"], 2.0)
    tex = np.repeat(np.arange(4), 9)
    d = np.tile(np.linspace(0.0, 1.0, 9), 4) + 0.013
    w = rng.normal(size=tex.size)
    return case, tex, d, w


def _loss(kind, params, case, tex, d, w, z0=None, z1=None, tau=None, **rng_kw):
    Float64 = ad.backend.types().Float64
    seg = ad.Segments.from_arrays(case["offsets"], case["z0"] if z0 is None else z0,
                                  case["z1"] if z1 is None else z1,
                                  optical_depth=case["tau"] if tau is None else tau,
                                  dtype="float64")
    rep = ad.build(kind, seg, **params, **rng_kw)
    return dr.sum(rep.eval(tex, d) * Float64(w))


def _fd(kind, params, case, tex, d, w, field, h=1e-6, **rng_kw):
    g = np.zeros(case[field].size)
    for i in range(g.size):
        vals = []
        for s in (+h, -h):
            c = dict(case)
            c[field] = case[field].copy()
            c[field][i] += s
            vals.append(float(np.asarray(_loss(kind, params, c, tex, d, w, **rng_kw))[0]))
        g[i] = (vals[0] - vals[1]) / (2 * h)
    return g


@pytest.mark.parametrize("config", GRAD_CONFIGS, ids=lin_id)
def test_gradients_match_finite_differences(config, rng):
    """Reverse mode (dr.backward) and forward mode vs central differences (h = 1e-6,
    truncation ~h^2 f''' and rounding ~eps / h ~ 1e-10: rtol 1e-6, atol 1e-8) w.r.t.
    optical depth, z0 and z1, with the depth range held fixed (explicit near/far)."""
    kind, params = config
    Float64 = ad.backend.types().Float64
    case, tex, d, w = _grad_setup(rng)
    rk = {"near": 0.0, "far": 1.0}
    for field, arg in (("tau", "tau"), ("z0", "z0"), ("z1", "z1")):
        x = Float64(case[field])
        dr.enable_grad(x)
        loss = _loss(kind, params, case, tex, d, w, **{arg: x}, **rk)
        dr.backward(loss)
        rev = np.asarray(dr.grad(x))
        fd = _fd(kind, params, case, tex, d, w, field, **rk)
        np.testing.assert_allclose(rev, fd, rtol=1e-6, atol=1e-8, err_msg=f"reverse d/d{field}")
        # forward mode along a random direction
        v = rng.normal(size=x.shape[0] if hasattr(x, "shape") else dr.width(x))
        y = Float64(case[field])
        dr.enable_grad(y)
        loss = _loss(kind, params, case, tex, d, w, **{arg: y}, **rk)
        dr.set_grad(y, Float64(v))
        fwd = float(np.asarray(dr.forward_to(loss))[0])
        np.testing.assert_allclose(fwd, fd @ v, rtol=1e-6, atol=1e-8, err_msg=f"forward d/d{field}")
    assert np.any(np.abs(fd) > 1e-3)


@pytest.mark.parametrize("config", GRAD_CONFIGS[:2], ids=lin_id)
def test_gradients_per_texel_range(config, rng):
    """Per-texel range: d/dtau (the bounds depend only on z) matches finite differences."""
    kind, params = config
    Float64 = ad.backend.types().Float64
    case, tex, d, w = _grad_setup(rng)
    x = Float64(case["tau"])
    dr.enable_grad(x)
    dr.backward(_loss(kind, params, case, tex, d, w, tau=x, depth_range="texel"))
    fd = _fd(kind, params, case, tex, d, w, "tau", depth_range="texel")
    np.testing.assert_allclose(np.asarray(dr.grad(x)), fd, rtol=1e-6, atol=1e-8)


# ----------------------------------------------------------------------------
# A new basis is a few lines
# ----------------------------------------------------------------------------
class SineBasis(Basis):
    """sqrt(2) sin(pi (k + 1) u), k < n: orthonormal on [0, 1] (a user-defined basis)."""

    def f(self, u):
        return [math.sqrt(2) * dr.sin(math.pi * (k + 1) * u) for k in range(self.n)]

    def F(self, u):
        return [math.sqrt(2) / (math.pi * (k + 1)) * (1 - dr.cos(math.pi * (k + 1) * u))
                for k in range(self.n)]


def test_user_defined_basis(rng):
    case = random_segments(rng, texels=8, max_count=6, opaque_fraction=0.0)
    seg = to_segments(case, "float64")
    hc = host_case(seg)
    rep = ad.build("basis", seg, basis=SineBasis(4))
    fs = [(lambda u, k=k: math.sqrt(2) * np.sin(math.pi * (k + 1) * u)) for k in range(4)]
    ref = R.basis_coefficients(hc, fs)
    np.testing.assert_allclose(coefficient_array(rep), ref, rtol=0, atol=1e-12)
    assert rep.nbytes_per_texel == 4 * 8 and rep.monotone is False


def test_registered_bases_match_named_representations(rng):
    """'fom' and 'osm' are the basis form with the Fourier / piecewise-constant bases
    (OSM projects with its own difference-array kernel: equal to float64 rounding)."""
    seg = to_segments(random_segments(rng, texels=8, max_count=6, opaque_fraction=0.0),
                      "float64")
    for kind, params, basis in (("fom", {"harmonics": 3}, FourierBasis(3)),
                                ("osm", {"slices": 5}, PiecewiseConstantBasis(5))):
        a = ad.build(kind, seg, **params)
        b = ad.build("basis", seg, basis=basis)
        np.testing.assert_allclose(coefficient_array(a), coefficient_array(b),
                                   rtol=0, atol=64 * EPS["float64"] * 20)
        tex = np.repeat(np.arange(8), 5)
        d = np.tile(np.linspace(0, 1, 5), 8)
        np.testing.assert_allclose(np.asarray(a.eval(tex, d)), np.asarray(b.eval(tex, d)),
                                   rtol=1e-13, atol=1e-15)
    assert ad.build("basis", seg, basis="fourier", n=2).basis.n_coefficients == 5


# ----------------------------------------------------------------------------
# Storage and bad input
# ----------------------------------------------------------------------------
def test_nbytes_per_texel():
    s32 = ad.Segments.from_arrays([0, 1], [0.1], [0.2], optical_depth=[1.0])
    s64 = ad.Segments.from_arrays([0, 1], [0.1], [0.2], optical_depth=[1.0], dtype="float64")
    assert ad.build("fom", s32, harmonics=3).nbytes_per_texel == 7 * 4
    assert ad.build("fom", s32, harmonics=3, depth_range="texel").nbytes_per_texel == 9 * 4
    assert ad.build("fom", s64, harmonics=3).nbytes_per_texel == 7 * 8
    assert ad.build("osm", s32, slices=16).nbytes_per_texel == 16 * 4
    assert ad.build("osm", s64, slices=16, depth_range="texel").nbytes_per_texel == 18 * 8
    assert ad.build("basis", s32, basis="legendre", n=5).nbytes_per_texel == 5 * 4


def test_named_basis_defaults_to_eight_functions():
    """The schema's documented default: a named basis without n= has 8 functions."""
    seg = ad.Segments.from_arrays([0, 2], [0.1, 0.5], [0.3, 0.9], optical_depth=[1.0, 0.5])
    rep = ad.build("basis", seg, basis="legendre")
    assert rep.basis.n == 8 and rep.params["n"] == 8


@pytest.mark.parametrize("kind,params,arg", [
    ("fom", {"harmonics": 0}, "harmonics"),
    ("fom", {"harmonics": -2}, "harmonics"),
    ("fom", {"harmonics": 2.5}, "harmonics"),
    ("fom", {"harmonics": "3"}, "harmonics"),
    ("fom", {"harmonics": True}, "harmonics"),
    ("osm", {"slices": 0}, "slices"),
    ("osm", {"slices": 3.0}, "slices"),
    ("fom", {"near": 0.5, "far": 0.5}, "near"),
    ("osm", {"near": 0.9, "far": 0.1}, "near"),
    ("fom", {"near": 0.95}, "near"),               # far defaults to max z1 = 0.9
    ("fom", {"near": float("nan")}, "near"),
    ("osm", {"far": float("inf")}, "far"),
    ("osm", {"far": "1"}, "far"),
    ("fom", {"depth_range": "local"}, "depth_range"),
    ("fom", {"depth_range": "texel", "near": 0.0}, "near"),
    ("basis", {"basis": "wavelet", "n": 3}, "basis"),
    ("basis", {"basis": 3}, "basis"),
    ("basis", {"basis": "legendre", "n": 0}, "n"),
    ("basis", {"basis": "legendre", "n": True}, "n"),
    ("basis", {"basis": SineBasis(2), "n": 3}, "n"),
])
def test_bad_input(kind, params, arg):
    seg = ad.Segments.from_arrays([0, 2], [0.1, 0.5], [0.3, 0.9], optical_depth=[1.0, 0.5])
    with pytest.raises(ValueError, match=f"^{arg}:"):
        ad.build(kind, seg, **params)

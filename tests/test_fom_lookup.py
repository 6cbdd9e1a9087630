"""FOM lookups by the angle-addition recurrence (FourierOpacityMap._reconstruct_from: one
lane per receiver, one ``sincos`` of x = pi u, then e^{i(k+1)x} = e^{ikx} e^{ix}) against a
float64 NumPy reference of eq. 3 and against the per-harmonic ``sincos`` lanes of the base
class (the lookup before it), on random and adversarial input: up to the schema's most
harmonics, depths at the range ends and outside it, coefficients of one sign (every
term's error adds up) and of large magnitude.

Tolerance (u_r = 2^-24 in float32, 2^-53 in float64: the unit roundoff).  The reference
uses the same stored coefficients and the same u (float32 inputs are exact in float64, k u
too), so only the lookup's rounding is measured:

* sin(kx), cos(kx): the base e^{ix} carries ~7 u_r (pi and pi u rounded: 1.5 pi u_r; sincos
  2 ulp), each complex product sqrt(2) gamma_2 ~ 2.8 u_r (Higham 2002, sec. 3.6), so the
  recurrence error grows linearly in k: <= k delta with delta = 12 u_r.  (The per-harmonic
  form grows linearly too: rounding k u costs pi k u u_r of angle.)
* the term (a'_k cos(kx) + b'_k sin(kx)) sin(kx) / (pi k) then errs by at most
  2 (|a'_k| + |b'_k|) k delta / (pi k) = (2 delta / pi) (|a'_k| + |b'_k|): the 1 / (pi k)
  weight cancels the growth in k, so the bound does not grow with k per term;
* the term's own roundings and the sum of n + 1 terms: gamma_{n+4} sum_k |term_k| (Higham
  2002, sec. 4.2).

The old per-harmonic lanes obey the same bound (angle error pi k u_r + 7 u_r), so the two
lookups differ by at most twice it.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

import avsm_dr as ad
import drjit as dr
from avsm_dr import backend
from avsm_dr.representations import fom as FOM
from avsm_dr.representations.basis import BasisRepresentation

from cases import random_segments, to_segments
from helpers import optical_depth

UR = {"float32": 2.0 ** -24, "float64": 2.0 ** -53}
#: Per-harmonic growth of the recurrence's sin / cos error, in unit roundoffs (docstring).
DELTA = 12.0
MAX_HARMONICS = ad.describe("fom")["params"]["harmonics"]["max"]


def _build(harmonics, dtype, texels=8, seed=0, opaque_fraction=0.05):
    case = random_segments(np.random.default_rng(seed), texels=texels, max_count=12,
                           opaque_fraction=opaque_fraction)
    return ad.build("fom", to_segments(case, dtype), harmonics=harmonics)


def _adversarial_u(dtype, R, rng):
    """Receivers' u: random, the ends, the smallest positive and the largest below 1, a
    denormal, halves and quarters, k / n points."""
    f = np.float32 if dtype == "float32" else np.float64
    special = np.array([0.0, 1.0, np.finfo(f).tiny, np.finfo(f).smallest_subnormal, np.nextafter(f(1), f(0)),
                        np.nextafter(f(0), f(1)), 0.5, 0.25, 0.75, 1 / 3, 2 / 3, 1e-3, 1 - 1e-3], f)
    return np.concatenate([special, rng.uniform(0, 1, R - special.size).astype(f)])


def _reference(coef, tex, u):
    """float64 eq. 3 in the half-angle form, every sin(pi k u) from an exact k u mod 2."""
    coef, u = np.asarray(coef, np.float64), np.asarray(u, np.float64)
    n = (coef.shape[1] - 1) // 2
    k = np.arange(1, n + 1, dtype=np.float64)
    c = coef[tex]                                          # (R, 2n+1)
    a, b = c[:, 1::2], c[:, 2::2]
    x = np.pi * np.mod(u[:, None] * k[None, :], 2.0)       # exact k u (24 + 15 bits), reduced
    s, co = np.sin(x), np.cos(x)
    terms = (a * s * co + b * s * s) / (np.pi * k)
    D = c[:, 0] * 0.5 * u + terms.sum(axis=1)
    mag = np.abs(c[:, 0] * 0.5 * u) + np.abs(terms).sum(axis=1)
    return D, mag, (np.abs(a) + np.abs(b)).sum(axis=1)


def _tolerance(dtype, n, mag, ab):
    ur = UR[dtype]
    return (2 * DELTA / math.pi) * ur * ab + (n + 4) * ur * mag


def _lookups(rep, store, tex, u):
    """(recurrence, per-harmonic sincos lanes of the base class) of the same store."""
    t = backend.types()
    row, uu = t.UInt32(tex.astype(np.uint32)), rep.Float(u)
    new = np.asarray(rep._reconstruct_from(store, row, uu).numpy(), np.float64)
    old = np.asarray(BasisRepresentation._reconstruct_from(rep, store, row, uu).numpy(), np.float64)
    return new, old


def _check(rep, coef, dtype, R=257, seed=1):
    rng = np.random.default_rng(seed)
    T, K = coef.shape
    tex = rng.integers(0, T, R)
    u = _adversarial_u(dtype, R, rng)
    store = rep.Float(np.ascontiguousarray(coef.reshape(-1)))
    new, old = _lookups(rep, store, tex, u)
    ref, mag, ab = _reference(coef, tex, u)
    tol = _tolerance(dtype, (K - 1) // 2, mag, ab)
    assert np.all(np.abs(new - ref) <= tol), np.max(np.abs(new - ref) - tol)
    assert np.all(np.abs(old - ref) <= tol), np.max(np.abs(old - ref) - tol)
    assert np.all(np.abs(new - old) <= 2 * tol)
    # the range ends are exact: sin(pi u) = 0 keeps every sin(k x) = 0
    ends = (u == 0) | (u == 1)
    np.testing.assert_array_equal(new[ends], (coef[tex, 0] * 0.5 * u)[ends].astype(coef.dtype))


HARMONICS = [1, 3, 8, 16, FOM.LOOKUP_UNROLL_HARMONICS, FOM.LOOKUP_UNROLL_HARMONICS + 1, 100]


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("harmonics", HARMONICS)
def test_built_maps_match_reference(harmonics, dtype):
    """Built maps (opaque blockers among the segments), unrolled and block paths."""
    rep = _build(harmonics, dtype)
    coef = np.asarray(rep._coef.numpy()).reshape(rep.n_texels, -1)
    _check(rep, coef, dtype)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("harmonics", [8, FOM.LOOKUP_UNROLL_HARMONICS + 1, 1000])
@pytest.mark.parametrize("kind", ["ones", "signed", "large"])
def test_adversarial_coefficients_match_reference(kind, harmonics, dtype):
    """Coefficients of one sign (no term's error cancels another's), random signs, and
    large ones (an opaque texel: 2 tau = 2e4) over the whole range of u."""
    rep = _build(harmonics, dtype, texels=4)
    rng = np.random.default_rng(harmonics)
    shape = (4, 2 * harmonics + 1)
    coef = {"ones": np.ones(shape), "signed": rng.uniform(-2, 2, shape),
            "large": 2e4 * rng.uniform(0, 1, shape)}[kind].astype(dtype)
    _check(rep, coef, dtype)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_schema_maximum_harmonics(dtype):
    """The schema's most harmonics (32767: 1024 blocks): the error per term stays bounded
    as k grows (the 1 / (pi k) weight against the k delta growth)."""
    rep = _build(MAX_HARMONICS, dtype, texels=2, opaque_fraction=0.0)
    coef = np.asarray(rep._coef.numpy()).reshape(rep.n_texels, -1)
    _check(rep, coef, dtype, R=48)
    rng = np.random.default_rng(3)
    _check(rep, rng.uniform(-1, 1, coef.shape).astype(dtype), dtype, R=48)


@pytest.mark.parametrize("harmonics", [4, FOM.LOOKUP_UNROLL_HARMONICS + 5])
def test_depths_outside_and_at_the_range_ends(harmonics):
    """Public lookups clamp u to [0, 1]: T = 1 at and in front of near, exp(-a'_0 / 2) at
    and behind far, bit for bit."""
    rep = _build(harmonics, "float32")
    near, far = rep.near, rep.far
    T = rep.n_texels
    tex = np.repeat(np.arange(T), 4)
    d = np.tile([near - 10.0, near, far, far + 1e6], T)
    out = np.asarray(rep.eval(tex, d))
    a0 = np.asarray(rep.coefficients[0].numpy())
    expect = np.stack([np.ones(T, np.float32), np.ones(T, np.float32),
                       np.asarray(dr.exp(-rep.Float(a0 * np.float32(0.5))).numpy()),
                       np.asarray(dr.exp(-rep.Float(a0 * np.float32(0.5))).numpy())], axis=1).reshape(-1)
    np.testing.assert_array_equal(out, np.clip(expect, 0, 1))


def test_one_sincos_per_lookup(monkeypatch):
    """One ``sincos`` per receiver whatever n (the base class' lanes ran one per harmonic)."""
    calls, sincos_pi = [], FOM.sincos_pi

    def counted(y):
        calls.append(dr.width(y))
        return sincos_pi(y)

    for n in (8, 70):
        rep = _build(n, "float32")
        calls.clear()
        monkeypatch.setattr(FOM, "sincos_pi", counted)
        optical_depth(rep, np.arange(5), np.full(5, 0.5)).numpy()
        monkeypatch.undo()
        assert calls == [5], (n, calls)


@pytest.mark.parametrize("harmonics", [5, FOM.LOOKUP_UNROLL_HARMONICS + 7])
def test_gradients_equal_the_per_harmonic_lookup(harmonics):
    """Reverse and forward mode through the recurrence (unrolled and in evaluated blocks)
    w.r.t. optical depth and receiver depth agree with the per-harmonic lanes' (float64:
    both within ~1e-13 of the exact derivative)."""
    t = backend.types()
    case = random_segments(np.random.default_rng(7), texels=6, max_count=8, opaque_fraction=0.0)
    rng = np.random.default_rng(8)
    tex = rng.integers(0, 6, 40)
    d = rng.uniform(-0.05, 1.05, 40)
    w = t.Float64(rng.normal(size=40))
    lookups = {"new": FOM.FourierOpacityMap._reconstruct_from, "old": BasisRepresentation._reconstruct_from}
    grads = {}
    for name, fn in lookups.items():
        tau, depth = t.Float64(case["tau"]), t.Float64(d)
        dr.enable_grad(tau, depth)
        seg = ad.Segments.from_arrays(case["offsets"], case["z0"], case["z1"], optical_depth=tau, dtype="float64")
        rep = ad.build("fom", seg, harmonics=harmonics, near=-0.1, far=1.2)
        row = t.UInt32(tex.astype(np.uint32))
        loss = dr.sum(fn(rep, rep._store, row, rep.normalized_depth(row, depth)) * w)
        dr.backward(loss)
        g_tau, g_d = np.asarray(dr.grad(tau).numpy()), np.asarray(dr.grad(depth).numpy())
        tau2, depth2 = t.Float64(case["tau"]), t.Float64(d)
        dr.enable_grad(tau2, depth2)
        seg = ad.Segments.from_arrays(case["offsets"], case["z0"], case["z1"], optical_depth=tau2, dtype="float64")
        rep = ad.build("fom", seg, harmonics=harmonics, near=-0.1, far=1.2)
        dr.set_grad(tau2, t.Float64(np.linspace(-1, 1, dr.width(tau2))))
        dr.set_grad(depth2, t.Float64(np.linspace(1, 2, 40)))
        row = t.UInt32(tex.astype(np.uint32))
        loss = dr.sum(fn(rep, rep._store, row, rep.normalized_depth(row, depth2)) * w)
        grads[name] = (g_tau, g_d, float(np.asarray(dr.forward_to(loss).numpy())[0]))
    for a, b in zip(grads["new"], grads["old"]):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)
    assert np.any(np.abs(grads["new"][0]) > 1e-3) and np.any(np.abs(grads["new"][1]) > 1e-3)

"""The two projection paths of indexed bases (avsm_dr/representations/basis.py, "Kernel"):
one lane per (texel, coefficient) looping over the texel's segments (no atomics, used
without gradients) and the scatter-add over (segment, coefficient) lanes (used under AD).

Tolerance: both paths add the same N_t terms x_i of a texel (the same float expression,
:func:`clip_segment` then ``average_at`` / ``f_at``) in different orders.  Any order of a
float sum of N terms is within (N - 1) eps sum_i |x_i| of the exact sum (Higham 2002,
"Accuracy and Stability of Numerical Algorithms", sec. 4.2), so the paths differ by at
most 2 (N_t - 1) eps sum_i |x_i|, with sum_i |x_i| <= max|f_k| sum_i tau_i (|mean of f_k|
<= max|f_k|, tau_in + tau_front <= tau).  A slack of one more eps S per term covers a
compiler rounding a term differently (e.g. a contracted multiply-add): 2 N_t eps S.

FOM on float32 segments builds by the recurrence path (FourierOpacityMap._project_texels:
one lane per texel, cos/sin(k a) and sinc(k h) by angle-addition recurrences), so its
terms differ from the scatter path's by the two evaluations' rounding, from the same
clipped c0, c1: recurrence ~(3.6 k + 3 k + 4) eps, per-coefficient sincos ~(2 pi k + 8) eps
(the rounding of the angle 2 k m, the reduction and sincos/sinc), relative to 2 tau.  Both
fit the one-term constant of tests/test_linear.py, C_k = 20 k + 16 (harmonic k, 0 for
a'_0), so the bound gains C_k eps S per texel (S = 2 sum tau).
"""
from __future__ import annotations

import math

import numpy as np
import pytest

import avsm_dr as ad
import drjit as dr
from avsm_dr.representations import basis as B

from cases import random_segments, to_segments

EPS = {"float32": 2.0 ** -24, "float64": 2.0 ** -53}
#: max |f_k| on [0, 1]: Fourier 2 (2, 2 cos, 2 sin), cosine sqrt(2), slices 1.
CONFIGS = [
    ("fom", {"harmonics": 8}, 2.0),
    ("fom", {"harmonics": 16}, 2.0),         # the most harmonics of the recurrence path
    ("fom", {"harmonics": 3, "depth_range": "texel"}, 2.0),
    ("fom", {"harmonics": 4, "near": 0.2, "far": 0.7}, 2.0),     # clipped in front and behind
    ("basis", {"basis": "cosine", "n": 6}, math.sqrt(2)),
    ("basis", {"basis": "piecewise_constant", "n": 5}, 1.0),
]


def _np(x):
    return np.asarray(x.numpy(), np.float64)


def _bound(case, K, fmax, eps, term=None):
    """(T * K,) bound 2 N_t eps fmax sum tau of the texel, plus term_k eps fmax sum tau for
    paths whose terms differ (``term``: K constants; module docstring)."""
    off, tau = case["offsets"], case["tau"]
    counts = np.diff(off)
    sums = np.add.reduceat(tau, off[:-1]) * (counts > 0) if tau.size else np.zeros(counts.size)
    term = np.zeros(K) if term is None else np.asarray(term, np.float64)
    return (np.repeat(2 * counts * eps * fmax * sums, K) + np.outer(eps * fmax * sums, term).ravel())


def _fourier_term(rep, dtype):
    """C_k = 20 k + 16 per coefficient where the build uses the recurrence path, else None."""
    if rep.kind != "fom" or dtype != "float32":
        return None
    n = rep.params["harmonics"]
    return [20.0 * ((j + 1) // 2) + 16 for j in range(2 * n + 1)]


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("kind, params, fmax", CONFIGS)
def test_texel_path_equals_scatter_path(kind, params, fmax, dtype, rng):
    """The build (texel path) equals the scatter-add path to summation-order rounding,
    with clipping at near/far and the per-texel range, empty texels 0."""
    case = random_segments(rng, texels=96, max_count=30)
    seg = to_segments(case, dtype)
    rep = ad.build(kind, seg, **params)
    a, b = _np(rep._coef), _np(rep._project_scatter())
    h = seg.numpy()      # the stored (dtype-rounded) segments
    tol = _bound(dict(offsets=h["offsets"], tau=np.asarray(h["optical_depth"], np.float64)),
                 rep.basis.n_coefficients, fmax, EPS[dtype], _fourier_term(rep, dtype))
    assert np.all(np.abs(a - b) <= tol), np.max(np.abs(a - b) - tol)
    empty = np.repeat(np.diff(case["offsets"]) == 0, rep.basis.n_coefficients)
    assert empty.any() and np.all(a[empty] == 0)
    assert np.abs(a).max() > 1      # not trivially zero


@pytest.mark.parametrize("kind, params, fmax", CONFIGS[:1] + CONFIGS[4:5])
def test_texel_path_is_deterministic(kind, params, fmax, rng):
    """Same bits on every run (no atomics), and the build uses this path."""
    case = random_segments(rng, texels=64, max_count=60, opaque_fraction=0)
    seg = to_segments(case, "float32")
    rep = ad.build(kind, seg, **params)
    first = _np(rep._coef)
    for _ in range(3):
        assert np.array_equal(_np(rep._project_texels()), first)
    assert np.array_equal(_np(ad.build(kind, to_segments(case, "float32"), **params)._coef), first)


def test_texel_path_in_coefficient_batches(rng, monkeypatch):
    """More (texel, coefficient) lanes than LANES_PER_BATCH: one loop per batch of
    coefficients, the same coefficients as one batch (bit for bit: each lane's sum does not
    depend on the batching).  Float64 segments: on float32 FOM takes the recurrence path."""
    seg = to_segments(random_segments(rng, texels=40, max_count=12), "float64")
    whole = _np(ad.build("fom", seg, harmonics=6)._coef)
    monkeypatch.setattr(B, "LANES_PER_BATCH", 100)      # 3 coefficients per batch
    rep = ad.build("fom", seg, harmonics=6)
    assert len(rep._coefficient_batches(int(np.count_nonzero(seg.counts)))) > 1
    assert np.array_equal(_np(rep._coef), whole)


def test_gradients_take_the_scatter_path(rng):
    """Segments carrying gradients project by scatter-add (reverse mode through the
    texel loop is unavailable): same coefficients to summation-order rounding, and
    d(sum_k a_0)/d tau = 2 for every segment inside the range (a'_0 = 2 sum tau)."""
    case = random_segments(rng, texels=20, max_count=10, opaque_fraction=0)
    Float = ad.backend.types().Float32
    tau = Float(case["tau"])
    dr.enable_grad(tau)
    seg = ad.Segments.from_arrays(case["offsets"], case["z0"], case["z1"], optical_depth=tau,
                                  dtype="float32")
    assert seg.requires_grad
    rep = ad.build("fom", seg, harmonics=3, near=-1.0, far=2.0)    # every segment inside
    plain = ad.build("fom", to_segments(case, "float32"), harmonics=3, near=-1.0, far=2.0)
    tol = _bound(case, 7, 2.0, EPS["float32"], _fourier_term(plain, "float32"))
    assert np.all(np.abs(_np(dr.detach(rep._coef)) - _np(plain._coef)) <= tol)
    dr.backward(dr.sum(rep.coefficients[0]))
    np.testing.assert_allclose(_np(dr.grad(tau)), 2.0, rtol=1e-6)    # float32 rounding of 2


@pytest.mark.parametrize("harmonics", [1, 8, 16])
def test_fom_recurrence_path(harmonics, rng):
    """Float32 FOM builds by the one-lane-per-texel recurrence (bits differ from the
    per-(texel, coefficient) sincos lanes), within the module's bound: the two sums'
    rounding plus C_k eps S for the two term evaluations."""
    case = random_segments(rng, texels=64, max_count=40, opaque_fraction=0)
    seg = to_segments(case, "float32")
    rep = ad.build("fom", seg, harmonics=harmonics)
    a, b = _np(rep._coef), _np(B.BasisRepresentation._project_texels(rep))
    assert not np.array_equal(a, b)
    h = seg.numpy()
    tol = _bound(dict(offsets=h["offsets"], tau=np.asarray(h["optical_depth"], np.float64)),
                 2 * harmonics + 1, 2.0, EPS["float32"], _fourier_term(rep, "float32"))
    assert np.all(np.abs(a - b) <= tol), np.max(np.abs(a - b) - tol)

"""The projection paths of the linear kinds (avsm_dr/representations/basis.py, "Kernel"):
without gradients one lane per (texel, coefficient) looping over the texel's segments
(indexed bases) or one lane per texel summing the per-segment terms (list-form bases,
moments), no atomics; under AD the scatter-add over (segment, coefficient) lanes.  Bit
determinism of every linear kind's build (after other builds, on other thread counts).

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
    ("fom", {"harmonics": 4, "near": -0.3, "far": 1.4}, 2.0),    # an explicit range around the content
    ("basis", {"basis": "cosine", "n": 6}, math.sqrt(2)),
    ("basis", {"basis": "piecewise_constant", "n": 5}, 1.0),
    # list-form bases (no indexed forms): per-segment terms, then per-texel sums in CSR order
    ("basis", {"basis": "legendre", "n": 6}, math.sqrt(11)),
    ("basis", {"basis": "legendre", "n": 40}, math.sqrt(79)),     # chunks of LIST_CHUNK terms
    ("moments", {"moments": 8}, 1.0),
    ("moments", {"family": "trigonometric", "moments": 3, "depth_range": "texel"}, 1.0),
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
    """The build (texel path; list-form bases: per-texel sums of the per-segment terms)
    equals the scatter-add path to summation-order rounding, with an explicit global range
    and the per-texel range, empty texels 0.  max|f_k|: Legendre sqrt(2k + 1), power and
    trigonometric moments 1 (|x| <= 1)."""
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
    assert len(rep._lane_batches(int(np.count_nonzero(seg.counts)))) > 1
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


#: Every linear kind's projection path without gradients: indexed lanes (cosine), the FOM
#: recurrence and its float64 / many-harmonics lanes, list-form bases (Legendre: terms in
#: the loop below LIST_UNROLL coefficients, evaluated first and chunked from it on),
#: power / trigonometric moments (linear and log warp, per-texel range), OSM's slices,
#: Beer's sum.
DETERMINISTIC = [
    ("basis", {"basis": "cosine", "n": 6}, "float32"),
    ("basis", {"basis": "legendre", "n": 8}, "float32"),
    ("basis", {"basis": "legendre", "n": 32}, "float32"),      # the first K summed after the terms
    ("basis", {"basis": "legendre", "n": 40}, "float32"),
    ("fom", {"harmonics": 4}, "float32"),
    ("fom", {"harmonics": 4}, "float64"),
    ("fom", {"harmonics": 20}, "float32"),
    ("osm", {"slices": 16}, "float32"),
    ("moments", {"moments": 8}, "float32"),
    ("moments", {"moments": 6, "depth_range": "texel"}, "float64"),
    ("moments", {"moments": 4, "warp": "log"}, "float32"),
    ("moments", {"family": "trigonometric", "moments": 3}, "float32"),
    ("moments", {"family": "trigonometric", "moments": 2, "warp": "log"}, "float32"),
    ("beer", {}, "float32"),
]


def _stored(rep):
    """The buffer a kind's lookups read (host copy)."""
    attr = {"osm": "_cum", "beer": "tau_max"}.get(rep.kind, "_coef")
    return np.asarray(getattr(rep, attr).numpy())


@pytest.mark.parametrize("kind, params, dtype", DETERMINISTIC)
def test_builds_are_bit_deterministic(kind, params, dtype):
    """The same bits when the same segments are built again after other kinds ran, and on
    1, 3 or the default number of Dr.Jit threads: each texel's segments are summed in CSR
    order by one lane (no float atomics, whose order follows the thread schedule: moments-8
    changed by 1e-8..2e-7 between such builds).  4000 texels of 0-40 segments and two of
    200000: many work blocks, which threads add to a texel and in which order follows the
    schedule (the scatter-add path failed this test for 7 of these 13 builds)."""
    rng = np.random.default_rng(8)
    case = random_segments(rng, texels=4000, max_count=40, depth_range=(0.5, 2.0))
    n_big = 400000
    big = {k: rng.uniform(0.5, 1.5, n_big) for k in ("z0", "tau")}
    big["z1"] = big["z0"] + rng.uniform(0, 0.5, n_big)
    case = dict(offsets=np.concatenate([case["offsets"], case["offsets"][-1] + [n_big // 2, n_big]]),
                **{k: np.concatenate([case[k], big[k]]) for k in ("z0", "z1", "tau")})
    first = _stored(ad.build(kind, to_segments(case, dtype), **params))
    other = to_segments(random_segments(rng, texels=500, max_count=20))
    threads = dr.thread_count()
    try:
        for n in (1, 3, threads):
            dr.set_thread_count(n)
            for k, p in (("avsm", {}), ("fom", {"harmonics": 2}), ("osm", {"slices": 4}), ("moments", {})):
                ad.build(k, other, **p)
            again = _stored(ad.build(kind, to_segments(case, dtype), **params))
            assert np.array_equal(again, first), (n, np.max(np.abs(again - first)))
    finally:
        dr.set_thread_count(threads)


def test_gradients_take_the_scatter_path_for_list_bases(rng):
    """Moments on grad-enabled segments (reverse mode needs the scatter-add path): the
    deterministic build's moments to summation-order rounding, d b_0 / d tau = 1."""
    case = random_segments(rng, texels=20, max_count=10, opaque_fraction=0)
    Float = ad.backend.types().Float32
    tau = Float(case["tau"])
    dr.enable_grad(tau)
    seg = ad.Segments.from_arrays(case["offsets"], case["z0"], case["z1"], optical_depth=tau, dtype="float32")
    rep = ad.build("moments", seg, moments=4, near=-1.0, far=2.0)
    plain = ad.build("moments", to_segments(case, "float32"), moments=4, near=-1.0, far=2.0)
    tol = _bound(case, 5, 1.0, EPS["float32"])
    assert np.all(np.abs(_np(dr.detach(rep._coef)) - _np(plain._coef)) <= tol)
    dr.backward(dr.sum(rep.coefficients[0]))
    np.testing.assert_allclose(_np(dr.grad(tau)), 1.0, rtol=1e-6)


def test_projection_only_basis_is_refused_with_the_kind_to_use():
    """``basis='trigonometric_moments'`` was listed as known and raised a bare
    NotImplementedError (it has projection functions only): now a ValueError naming the
    build that reconstructs from it, and it is no longer listed."""
    import avsm_dr as ad
    from avsm_dr.representations import moments as M
    seg = ad.Segments.from_arrays([0, 2], [0.1, 0.35], [0.3, 0.5], optical_depth=[0.5, 0.7])
    hint = r"use build\('moments', segments, family='trigonometric', moments=n\)$"
    with pytest.raises(ValueError, match=r"^basis: 'trigonometric_moments' has projection functions only.*" + hint):
        ad.build("basis", seg, basis="trigonometric_moments", n=3)
    with pytest.raises(ValueError, match=r"^basis: TrigMomentBasis has projection functions only.*" + hint):
        ad.build("basis", seg, basis=M.TrigMomentBasis(3))
    with pytest.raises(ValueError, match=r"^basis: unknown basis 'nope'; known: \[") as err:
        ad.build("basis", seg, basis="nope", n=3)
    assert "trigonometric_moments" not in str(err.value) and "legendre" in str(err.value)
    assert 0 < float(ad.build("moments", seg, family="trigonometric", moments=3).eval(texel=[0], depth=[0.4])[0]) < 1

"""Prefiltered coefficient maps (``eval(..., prefilter=True)``): the linear kinds filter
their stored per-texel map and reconstruct once, next to filtering the reconstructed T.

Tolerances (float64 unless stated): rounding of a sum of at most K (taps x coefficients)
terms of size <= the texel's total optical depth S, so ``1e-12 (1 + S)``, where
eps = 2^-53 ~ 1.1e-16 times a few hundred terms stays far below."""
from __future__ import annotations

import math

import numpy as np
import pytest

import avsm_dr as ad
import drjit as dr

from cases import random_segments, to_segments
from reference import linear_ref as R
from reference import moments_ref as M

FILTERS = ("bilinear", "box", "gaussian")
#: (kind, params) of the prefilterable kinds under test.
LINEAR = [
    ("fom", {"harmonics": 4}),
    ("osm", {"slices": 8}),
    ("basis", {"basis": "legendre", "n": 6}),
    ("basis", {"basis": "cosine", "n": 6}),
    ("moments", {}),
]
W, H = 6, 5


def lin_id(c):
    return c[0] + "".join(f"-{k}={v}" for k, v in c[1].items())


def _case(rng, texels=W * H):
    return random_segments(rng, texels=texels, max_count=8, opaque_fraction=0.0)


def _receivers(rng, n=40):
    coords = np.stack([rng.uniform(-0.5, W + 0.5, n), rng.uniform(-0.5, H + 0.5, n)], axis=1)
    return coords, rng.uniform(-0.1, 1.1, n)


# ---------------------------------------------------------------------------- bad input
def test_prefilter_refused_where_undefined(rng):
    seg = to_segments(_case(rng), "float64")
    coords, depth = _receivers(rng, 4)
    fom = ad.build("fom", seg, harmonics=2)
    with pytest.raises(ValueError, match="^prefilter: needs a non-point"):
        fom.eval(coords, depth, filter="point", width=W, height=H, prefilter=True)
    with pytest.raises(ValueError, match="^prefilter: needs a non-point"):
        fom.eval(np.arange(4), depth, prefilter=True)
    with pytest.raises(ValueError, match="^prefilter: expected a bool"):
        fom.eval(coords, depth, filter="bilinear", width=W, height=H, prefilter="yes")
    with pytest.raises(ValueError, match="^prefilter: kind 'avsm'"):
        ad.build("avsm", seg).eval(coords, depth, filter="bilinear", width=W, height=H, prefilter=True)
    texel = ad.build("osm", seg, slices=4, depth_range="texel")
    with pytest.raises(ValueError, match="^prefilter: needs depth_range='global'"):
        texel.eval(coords, depth, filter="box", width=W, height=H, prefilter=True)


def _class_trait(kind: str, name: str) -> bool:
    """A trait of the kind's class, without an instance: a class attribute or a property."""
    value = getattr(ad.REGISTRY[kind], name)
    return value.fget(None) if isinstance(value, property) else value


def test_prefilterable_trait():
    assert all(_class_trait(k, "prefilterable") for k in ("fom", "osm", "basis", "moments"))
    assert not _class_trait("avsm", "prefilterable")
    assert not _class_trait("exact", "prefilterable")


# -------------------------------------------------------------------- constant map
@pytest.mark.parametrize("case", LINEAR, ids=lin_id)
@pytest.mark.parametrize("filter", FILTERS)
def test_constant_map_prefilter_equals_per_tap(case, filter, rng):
    """Every texel holds the same segments: the filtered coefficients are the texel's own,
    so both orders give the point lookup."""
    one = random_segments(rng, texels=1, max_count=8, opaque_fraction=0.0, empty_fraction=0.0)
    n = len(one["z0"])
    T = W * H
    const = dict(offsets=np.arange(T + 1) * n, z0=np.tile(one["z0"], T), z1=np.tile(one["z1"], T),
                 tau=np.tile(one["tau"], T))
    rep = ad.build(case[0], to_segments(const, "float64"), **case[1])
    coords, depth = _receivers(rng)
    pre = np.asarray(rep.eval(coords, depth, filter=filter, width=W, height=H, radius=1.7,
                              prefilter=True))
    tap = np.asarray(rep.eval(coords, depth, filter=filter, width=W, height=H, radius=1.7))
    point = np.asarray(rep.eval(np.zeros(len(depth), np.int64), depth))
    np.testing.assert_allclose(pre, tap, rtol=0, atol=1e-12)
    np.testing.assert_allclose(pre, point, rtol=0, atol=1e-12)


# ---------------------------------------------------- bilinear against NumPy (float64)
def _bilinear_taps(coords):
    """Independent bilinear taps: the 2x2 texel centres around p, clamped to the map."""
    out = []
    for x, y in coords:
        x0, y0 = math.floor(x - 0.5), math.floor(y - 0.5)
        fx, fy = x - 0.5 - x0, y - 0.5 - y0
        taps = []
        for dx, dy, w in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)),
                          (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
            tx, ty = min(max(x0 + dx, 0), W - 1), min(max(y0 + dy, 0), H - 1)
            taps.append((ty * W + tx, w))
        out.append(taps)
    return out


def _reference_D(kind, params, a, u, rep):
    """The kind's reconstruction formula (tests/reference) from one coefficient vector."""
    if kind == "fom":
        return R.fourier_optical_depth(a, u)
    if kind == "osm":
        return R.slice_optical_depth(a, u)
    if kind == "moments":
        return M.optical_depth(a, u, rep.params["bias"], rep.params["overestimation"])
    fs = (R.legendre_functions if params["basis"] == "legendre" else R.cosine_functions)(params["n"])
    return R.basis_optical_depth(a, fs, u)


@pytest.mark.parametrize("case", LINEAR, ids=lin_id)
def test_prefiltered_bilinear_matches_numpy(case, rng):
    """T = exp(-D(sum_j w_j a[tex_j], u)) with the kernel's own coefficients (checked
    against tests/reference in test_linear.py / test_moments.py), filtered and
    reconstructed in NumPy."""
    kind, params = case
    data = _case(rng)
    rep = ad.build(kind, to_segments(data, "float64"), **params)
    coords, depth = _receivers(rng)
    got = np.asarray(rep.eval(coords, depth, filter="bilinear", width=W, height=H, prefilter=True))
    a = np.stack([np.asarray(c) for c in rep.coefficients], axis=1)       # (T, K)
    near, span = R.ranges(data)
    u = np.clip((depth - near[0]) / span[0], 0, 1)
    want = np.empty(len(depth))
    for i, taps in enumerate(_bilinear_taps(coords)):
        af = sum(w * a[t] for t, w in taps)
        D = _reference_D(kind, params, af, u[i:i + 1], rep)[0]
        want[i] = min(max(math.exp(-D), 0.0), 1.0)
    scale = 1 + np.abs(a).sum(axis=1).max()
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * scale)   # measured <= 3e-15


# ----------------------------------------------------------------------- Jensen (OSM)
@pytest.mark.parametrize("filter", FILTERS)
def test_osm_prefilter_is_darker_than_per_tap(filter, rng):
    """OSM: D(u) = sum_k a_k g_k(u) >= 0 is linear in the coefficients at fixed u and
    exp(-x) is convex, so exp(-sum_j w_j D_j) <= sum_j w_j exp(-D_j) (Jensen): the
    prefiltered map is never lighter; strictly darker where the taps differ."""
    rep = ad.build("osm", to_segments(_case(rng), "float64"), slices=16)
    coords, depth = _receivers(rng, 200)
    pre = np.asarray(rep.eval(coords, depth, filter=filter, width=W, height=H, radius=1.5,
                              prefilter=True))
    tap = np.asarray(rep.eval(coords, depth, filter=filter, width=W, height=H, radius=1.5))
    assert np.all(pre <= tap + 1e-12)
    assert np.mean(pre < tap - 1e-6) > 0.3


# -------------------------------------------------------------------------- gradients
@pytest.mark.parametrize("case", LINEAR, ids=lin_id)
def test_prefilter_gradients_match_finite_differences(case, rng):
    """Reverse-mode d(sum T)/d tau_i through the filtered coefficients vs central
    differences (float64: step 1e-6, truncation ~1e-12 x |d2T|, rounding ~1e-10)."""
    kind, params = case
    data = random_segments(rng, texels=4, max_count=4, opaque_fraction=0.0, empty_fraction=0.0)
    coords = np.array([[0.8, 0.9], [1.3, 1.6], [1.0, 1.0]])
    depth = np.array([0.5, 0.7, 0.9])

    def total(tau):
        d = dict(data, tau=tau)
        rep = ad.build(kind, to_segments(d, "float64"), **params)
        return rep.eval(coords, depth, filter="bilinear", width=2, height=2, prefilter=True)

    Float64 = ad.backend.types().Float64
    tau = Float64(data["tau"])
    dr.enable_grad(tau)
    seg = ad.Segments.from_arrays(data["offsets"], data["z0"], data["z1"], optical_depth=tau,
                                  dtype="float64")
    out = dr.sum(ad.build(kind, seg, **params).eval(coords, depth, filter="bilinear", width=2,
                                                      height=2, prefilter=True))
    dr.backward(out)
    grad = np.asarray(dr.grad(tau))
    h = 1e-6
    for i in range(0, len(data["tau"]), max(1, len(data["tau"]) // 4)):
        up, dn = data["tau"].copy(), data["tau"].copy()
        up[i] += h
        dn[i] -= h
        fd = (np.asarray(total(up)).sum() - np.asarray(total(dn)).sum()) / (2 * h)
        assert abs(grad[i] - fd) <= 1e-6 * (1 + abs(fd)), (i, grad[i], fd)
    assert np.any(np.abs(grad) > 1e-3)

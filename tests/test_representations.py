"""Contract of every representation (base.py), driven by the registry (cases.py reads it)."""
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

import avsm_dr as ad
import drjit as dr
from avsm_dr import backend
from cases import case_id, random_segments, representations, to_segments
from reference import exact_ref

CASES = representations()


@pytest.mark.parametrize("case", CASES, ids=case_id)
def test_bounds_monotone_and_unity_in_front(rng, case):
    kind, params = case
    data = random_segments(rng, texels=50, max_count=30)
    seg = to_segments(data)
    rep = ad.build(kind, seg, **params)
    monotone = rep.monotone
    depth = np.linspace(-0.5, 1.5, 101)
    tex = np.repeat(np.arange(50), depth.size)
    T = np.asarray(rep.eval(tex, np.tile(depth, 50))).reshape(50, -1)
    assert np.all(np.isfinite(T))
    assert np.all((T >= 0) & (T <= 1))
    if monotone:
        assert np.all(np.diff(T, axis=1) <= 1e-6)  # float32 rounding of equal neighbours
    # in front of the texel's first blocker nothing is shadowed; basis methods (OSM slices,
    # FOM ringing) spread absorption over their depth resolution, so only node methods
    near, _ = seg.texel_bounds()
    front = depth[None, :] < near[:, None] - 1e-6
    if rep.unity_in_front:
        np.testing.assert_allclose(T[front], 1.0, atol=1e-6)
    empty = np.diff(data["offsets"]) == 0
    np.testing.assert_allclose(T[empty], 1.0, atol=1e-6)
    assert rep.nbytes_per_texel > 0


@pytest.mark.parametrize("case", CASES, ids=case_id)
def test_adversarial_input_stays_finite(case):
    kind, params = case
    # coincident, zero-length, opaque, huge optical depth, tiny and huge depth ranges
    z0 = np.array([0.0, 0.0, 0.5, 0.5, 0.5, 1e-7, 0.9, 1.0])
    z1 = np.array([0.0, 1.0, 0.5, 0.5, 0.6, 2e-7, 1.0, 1.0])
    tr = np.array([0.0, 0.5, 1.0, 0.0, 1e-30, 0.9, 0.0, 0.3])
    for scale in (1e-4, 1.0, 1e6):
        seg = ad.Segments.from_arrays([0, 8, 8, 9], np.r_[z0, 0.2] * scale, np.r_[z1, 0.2] * scale,
                                      transmittance=np.r_[tr, 0.5])
        rep = ad.build(kind, seg, **params)
        d = np.linspace(-0.1, 1.1, 61) * scale
        for tx in (0, 1, 2):
            T = np.asarray(rep.eval(np.full(d.size, tx), d))
            assert np.all(np.isfinite(T)) and np.all((T >= 0) & (T <= 1))


@pytest.mark.parametrize("case", CASES, ids=case_id)
def test_behind_everything_matches_exact(rng, case):
    kind, params = case
    # node methods keep the last node; bases whose first function is constant and whose
    # others integrate to 0 over [near, far] (Fourier, slices, Legendre, cosine) and the
    # moments keep the total optical depth exactly
    data = random_segments(rng, texels=40, max_count=30)
    seg = to_segments(data, "float64")
    rep = ad.build(kind, seg, **params)
    far = seg.bounds()[1]
    T = np.asarray(rep.eval(np.arange(40), np.full(40, far + 1)))
    ref = exact_ref.evaluate(data["offsets"], data["z0"], data["z1"],
                             np.minimum(data["tau"], ad.OPAQUE_OPTICAL_DEPTH), np.arange(40), np.full(40, far + 1))
    # float64 throughout; FOM/moments evaluate sums of ~1e3 terms: 1e-9 absolute
    tol = rep.params.get("tolerance", 1e-12 if kind in ("exact", "avsm") else 1e-9)
    np.testing.assert_allclose(T, ref, atol=tol)


def _fd_check(kind, params, rng, texels=12, max_count=10):
    """Reverse- and forward-mode gradients of sum(w T) w.r.t. optical depth vs central
    differences, float64.  Depths stay away from node/segment ends and FD steps do not
    change the AVSM node layout (eps = 1e-6 << gaps); tolerance 1e-6 absolute:
    FD truncation O(eps^2) plus float64 cancellation ~1e-16/eps."""
    F64 = backend.types().Float64
    data = random_segments(rng, texels=texels, max_count=max_count, opaque_fraction=0.0, zero_fraction=0.0)
    tex = np.repeat(np.arange(texels), 6)
    depth = rng.uniform(0, 1, tex.size)
    w = rng.normal(size=tex.size)

    def loss(tau, grad=False):
        t = F64(tau)
        if grad:
            dr.enable_grad(t)
        seg = ad.Segments.from_arrays(data["offsets"], data["z0"], data["z1"], optical_depth=t)
        L = dr.sum(ad.build(kind, seg, **params).eval(tex, depth) * F64(w))
        return t, L

    t, L = loss(data["tau"], grad=True)
    dr.backward(L)
    g = dr.grad(t).numpy()
    idx = rng.choice(data["tau"].size, size=min(12, data["tau"].size), replace=False)
    eps = 1e-6
    for j in idx:
        tp, tm = data["tau"].copy(), data["tau"].copy()
        tp[j] += eps
        tm[j] -= eps
        fd = (loss(tp)[1][0] - loss(tm)[1][0]) / (2 * eps)
        assert abs(g[j] - fd) < 1e-6, (j, g[j], fd)
    # forward mode along one random direction
    direction = rng.normal(size=data["tau"].size)
    t = F64(data["tau"])
    dr.enable_grad(t)
    seg = ad.Segments.from_arrays(data["offsets"], data["z0"], data["z1"], optical_depth=t)
    L = dr.sum(ad.build(kind, seg, **params).eval(tex, depth) * F64(w))
    dr.set_grad(t, F64(direction))
    dr.forward_to(L)
    fwd = dr.grad(L)[0]
    np.testing.assert_allclose(fwd, np.dot(g, direction), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("case", CASES, ids=case_id)
def test_gradients_match_finite_differences(rng, case):
    kind, params = case
    seg = ad.Segments.from_arrays([0, 1], [0.2], [0.4], optical_depth=[0.5])
    if not ad.build(kind, seg, **params).differentiable:
        pytest.skip(f"{case_id(case)} is not differentiable")
    if kind == "dsm":
        pytest.skip("dsm node depths move with the optical depth: FD crosses layout changes "
                    "(tests/test_dsm.py checks its gradients at fixed node depths)")
    _fd_check(kind, params, rng)


def test_unknown_kind():
    seg = ad.Segments.from_arrays([0, 1], [0.3], [0.4], transmittance=[0.5])
    with pytest.raises(ValueError, match="kind"):
        ad.build("nope", seg)


@pytest.mark.parametrize("kwargs, name", [
    (dict(texel=[0, 5], depth=[0.1, 0.2]), "texel"),
    (dict(texel=[0.5], depth=[0.1]), "texel"),
    (dict(texel=[0, 1], depth=[np.nan, 0.2]), "depth"),
    (dict(texel=[0, 1], depth=[0.1, 0.2, 0.3]), "depth"),
    (dict(texel=[], depth=[]), "texel"),
    (dict(texel=np.zeros((2, 3)), depth=[0.1, 0.2]), "texel"),
    (dict(texel=[0, 1], depth=[0.1, 0.2], filter="lanczos"), "filter"),
    (dict(texel=[0, 1], depth=[0.1, 0.2], filter="bilinear"), "width"),
    (dict(texel=[0, 1], depth=[0.1, 0.2], filter="bilinear", width=3, height=3), "width"),
])
def test_eval_bad_input(kwargs, name):
    seg = ad.Segments.from_arrays([0, 1, 1, 2, 2], [0.3, 0.1], [0.4, 0.2], transmittance=[0.5, 0.5])
    rep = ad.build("exact", seg)
    with pytest.raises(ValueError, match=name):
        rep.eval(**kwargs)


def test_bilinear_filter_against_reference(rng):
    """Bilinear = weighted sum of the 2x2 neighbours' exact values (clamped at the edge)."""
    W, H = 5, 4
    data = random_segments(rng, texels=W * H, max_count=8)
    seg = to_segments(data, "float64")
    rep = ad.build("exact", seg)
    xy = rng.uniform(0, [W, H], size=(300, 2))
    depth = rng.uniform(0, 1, 300)
    got = np.asarray(rep.eval(xy, depth, filter="bilinear", width=W, height=H))
    ref = np.zeros(300)
    for k, ((x, y), d) in enumerate(zip(xy, depth)):
        fx, fy = x - 0.5, y - 0.5
        x0, y0 = int(np.floor(fx)), int(np.floor(fy))
        wx, wy = fx - x0, fy - y0
        for dx, dy, wgt in ((0, 0, (1 - wx) * (1 - wy)), (1, 0, wx * (1 - wy)), (0, 1, (1 - wx) * wy), (1, 1, wx * wy)):
            ix, iy = min(max(x0 + dx, 0), W - 1), min(max(y0 + dy, 0), H - 1)
            t = iy * W + ix
            s = slice(data["offsets"][t], data["offsets"][t + 1])
            ref[k] += wgt * exact_ref.transmittance(data["z0"][s], data["z1"][s], np.minimum(data["tau"][s], 1e4), d)
    np.testing.assert_allclose(got, ref, atol=1e-12)


@pytest.mark.parametrize("flt", ["point", "bilinear", "box", "gaussian"])
def test_filters_preserve_constant_maps(flt):
    """Every filter's weights sum to one: a map where all texels agree is unchanged."""
    W = H = 6
    seg = ad.Segments.from_arrays(np.arange(W * H + 1), np.full(W * H, 0.2), np.full(W * H, 0.4),
                                  transmittance=np.full(W * H, 0.3))
    rep = ad.build("exact", seg)
    xy = np.random.default_rng(0).uniform(0, W, size=(50, 2))
    T = np.asarray(rep.eval(xy, np.full(50, 0.5), filter=flt, width=W, height=H, radius=2))
    np.testing.assert_allclose(T, 0.3, rtol=1e-6)


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31 - 1))
def test_property_bounds_all_kinds(seed):
    rng = np.random.default_rng(seed)
    data = random_segments(rng, texels=6, max_count=15, opaque_fraction=0.2, zero_fraction=0.3)
    seg = to_segments(data)
    d = rng.uniform(-0.2, 1.2, 40)
    tex = rng.integers(0, 6, 40)
    for kind, params in CASES:
        T = np.asarray(ad.build(kind, seg, **params).eval(tex, d))
        assert np.all(np.isfinite(T)) and np.all((T >= 0) & (T <= 1)), kind

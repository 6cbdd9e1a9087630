"""Contract of every representation (base.py), driven by the registry (cases.py reads it),
run on every available backend (the ``backend`` fixture: LLVM here, LLVM and CUDA on a GPU host)."""
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
def test_bounds_monotone_and_unity_in_front(backend, rng, case):
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
def test_adversarial_input_stays_finite(backend, case):
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
def test_behind_everything_matches_exact(backend, rng, case):
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
def test_gradients_match_finite_differences(backend, rng, case):
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


# ----------------------------------------------------------------------------
# filters under hostile parameters
# ----------------------------------------------------------------------------
def _map(W, H, rng):
    data = random_segments(rng, texels=W * H, max_count=4, empty_fraction=0.0)
    return ad.build("exact", to_segments(data, "float64"))


@pytest.mark.parametrize("kwargs, name", [
    (dict(radius=-1.0), "radius"), (dict(radius=0.0), "radius"), (dict(radius=float("inf")), "radius"),
    (dict(radius=float("nan")), "radius"), (dict(radius=True), "radius"), (dict(radius="2"), "radius"),
    (dict(radius=7.5), "radius"),                       # larger than the 6 x 5 map
    (dict(width=1.5, height=20), "width"), (dict(width=-4, height=-5), "width"),
    (dict(width=True, height=30), "width"), (dict(width=6, height=5.0), "height"),
])
@pytest.mark.parametrize("flt", ["box", "gaussian"])
def test_filter_bad_parameters(flt, kwargs, name, rng):
    """radius: finite, > 0, at most max(width, height); width/height: integers >= 1.
    (radius=-1 gave T = 0 from zero taps; width=1.5 was accepted; width=-4 failed in Dr.Jit.)"""
    rep = _map(6, 5, rng)
    args = dict(width=6, height=5, radius=1.0)
    args.update(kwargs)
    with pytest.raises(ValueError, match=f"^{name}:"):
        rep.eval(np.array([[1.2, 2.3]]), [0.5], filter=flt, **args)


def test_gaussian_tiny_radius_is_the_point_filter(rng):
    """All weights used to underflow (0/0 = NaN) at radius 0.01: weights are relative to
    the receiver's own texel (weight 1), so a tiny radius is the point filter."""
    rep = _map(6, 5, rng)
    xy = rng.uniform(0, [6, 5], size=(40, 2))
    d = rng.uniform(0, 1, 40)
    point = np.asarray(rep.eval(xy, d, filter="point", width=6, height=5))
    for radius in (0.01, 1e-6):
        g = np.asarray(rep.eval(xy, d, filter="gaussian", width=6, height=5, radius=radius))
        np.testing.assert_allclose(g, point, rtol=0, atol=1e-15)


def test_box_and_gaussian_against_direct_sum(rng):
    """Batched taps = the direct double sum over the (2r+1)^2 clamped texels."""
    W, H = 7, 5
    rep = _map(W, H, rng)
    xy = np.r_[rng.uniform(-2, [W + 2, H + 2], size=(25, 2)), [[0.0, 0.0], [W - 1e-9, H - 1e-9]]]
    d = rng.uniform(0, 1.2, xy.shape[0])
    for flt, radius in (("box", 2.0), ("gaussian", 2.6), ("box", 7.0)):
        got = np.asarray(rep.eval(xy, d, filter=flt, width=W, height=H, radius=radius))
        r = int(np.ceil(radius))
        sigma = radius / 2
        for k, ((x, y), dk) in enumerate(zip(xy, d)):
            cx, cy = np.floor(x), np.floor(y)
            num = den = 0.0
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    w = 1.0 if flt == "box" else np.exp(-((cx + dx + 0.5 - x) ** 2 + (cy + dy + 0.5 - y) ** 2)
                                                        / (2 * sigma ** 2))
                    t = int(np.clip(cy + dy, 0, H - 1) * W + np.clip(cx + dx, 0, W - 1))
                    num += w * float(np.asarray(rep.eval([t], [dk]))[0])
                    den += w
            assert got[k] == pytest.approx(num / den, abs=1e-12), (flt, k)


def test_coordinates_beyond_int32_clamp_to_the_edge(rng):
    """x >= 2^31 used to wrap in Int32 and land on texel 0; coordinates are split on the
    host (int64, clamped) and clamp to the edge for every filter."""
    W, H = 4, 3
    rep = _map(W, H, rng)
    far = np.array([[2.0**31 + 5, 1.2], [1e30, -1e30], [-2.0**40, 2.5]])
    edge = np.array([[W - 0.5, 1.2], [W - 0.5, 0.5], [0.5, 2.5]])
    for flt in ("point", "bilinear", "box", "gaussian"):
        a = np.asarray(rep.eval(far, [0.7] * 3, filter=flt, width=W, height=H))
        b = np.asarray(rep.eval(edge, [0.7] * 3, filter=flt, width=W, height=H))
        if flt in ("point", "bilinear"):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-15, err_msg=flt)
        else:   # the support sees only clamped edge texels far outside: still in [0, 1]
            assert np.all((a >= 0) & (a <= 1))
    # a coordinate near 2^24 selects its texel exactly (float32 coordinates could not)
    from avsm_dr.filtering import filtered_eval
    t = backend.types()
    W = 2**25
    x = np.array([[2.0**24 + 1.5, 0.5], [2.0**24 + 2.25, 0.5], [W - 0.5, 0.5]])
    ident = lambda tex, depth: t.Float64(tex)            # noqa: E731  (texel index as value)
    got = np.asarray(filtered_eval(ident, x, t.Float64(np.zeros(3)), W, 1, "point", 1.0,
                                   t.Float64, t.UInt32, t.Int32))
    np.testing.assert_array_equal(got, [2**24 + 1, 2**24 + 2, W - 1])


def test_filter_trace_does_not_grow_with_radius(rng):
    """Taps run as batched (receiver, tap) lanes: the same kernels for radius 2 and 15
    (Python-unrolled taps made a trace growing as r^2: radius 15 took 18-38 s for 10
    receivers).  A structural check via dr.kernel_history, not a timing."""
    rep = _map(16, 16, rng)
    xy = rng.uniform(0, 16, size=(10, 2))
    ops = {}
    for radius in (2.0, 15.0):
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history()
        T = np.asarray(rep.eval(xy, np.full(10, 0.6), filter="gaussian", width=16, height=16, radius=radius))
        hist = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        ops[radius] = max(k["operation_count"] for k in hist)   # (kernel count varies by caching)
        assert np.all(np.isfinite(T)) and np.all((T >= 0) & (T <= 1))
    assert ops[2.0] == ops[15.0], ops


def test_filtered_gradients_match_finite_differences(rng):
    """Reverse mode through the batched taps (gathers and block sums), gaussian radius
    1.7 on a 4 x 4 map, float64, vs central differences (eps 1e-6, atol 1e-8)."""
    F64 = backend.types().Float64
    data = random_segments(rng, texels=16, max_count=4, opaque_fraction=0.0)
    xy = rng.uniform(0, 4, size=(7, 2))
    d = rng.uniform(0, 1.2, 7)
    w = rng.normal(size=7)

    def loss(tau, grad=False):
        t = F64(tau)
        if grad:
            dr.enable_grad(t)
        seg = ad.Segments.from_arrays(data["offsets"], data["z0"], data["z1"], optical_depth=t)
        L = dr.sum(ad.build("exact", seg).eval(xy, d, filter="gaussian", width=4, height=4, radius=1.7) * F64(w))
        if grad:
            dr.backward(L)
            return dr.grad(t).numpy()
        return float(L[0])

    tau = np.minimum(data["tau"], 3.0)
    g = loss(tau, grad=True)
    eps = 1e-6
    fd = np.array([(loss(tau + eps * e) - loss(tau - eps * e)) / (2 * eps) for e in np.eye(tau.size)])
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-8)
    assert np.abs(g).max() > 1e-3

"""Storage precision (``precision=`` on every kind that takes one): the codecs against the
float64 references of tests/reference/precision_ref.py, the stored buffers against the
reference decoding of the native buffers, T against the native T within the codecs'
bounds propagated through each lookup, monotonicity, bytes, the default left untouched,
straight-through gradients and the refusals."""
from __future__ import annotations

import math

import drjit as dr
import numpy as np
import pytest

import avsm_dr as ad
from avsm_dr import backend
from avsm_dr.representations import _precision as P
from cases import random_segments, to_segments
from reference import precision_ref as ref

PRECISIONS = list(P.PRECISIONS)
NODE_KINDS = ["avsm", "greedy", "optimal", "dsm", "avsm_march"]
#: Linear interpolation for the window bound: exponential interpolation t_l (t_r / t_l)^w
#: amplifies an absolute error e of a tiny t_r by w (t_l / t_r)^(1 - w) (not Lipschitz in
#: the values), so only the relative unorm8 code carries the bound over to it.
NODE_PARAMS = {"optimal": {"nodes": 4}, "avsm_march": {"interpolation": "linear"}}
BASIS_KINDS = ["basis", "fom", "osm", "moments"]
#: float32 lookups round each interpolation / exp: slack on T (as the contract tests' 1e-6)
T_SLACK = 2e-6


@pytest.fixture(scope="module")
def seg():
    data = random_segments(np.random.default_rng(13), texels=24, max_count=12)
    return to_segments(data)


def receivers(seg, per=24):
    lo, hi = seg.bounds()
    d = np.linspace(lo - 0.05, hi + 0.05, per)
    return np.repeat(np.arange(seg.n_texels), per), np.tile(d, seg.n_texels)


# ------------------------------------------------------------------ codecs
@pytest.mark.parametrize("precision", PRECISIONS)
def test_codec_matches_reference_within_bound(precision):
    q = np.concatenate([np.random.default_rng(1).random(4000), [0.0, 1.0, 0.5, 2.0**-20, 1 - 2.0**-13]])
    got = P.round_unit(q, precision)
    want = ref.code(q, precision)
    np.testing.assert_array_equal(got, want)
    assert np.max(np.abs(got - q)) <= ref.code_bound(precision)
    assert np.all(np.diff(got[np.argsort(q)]) >= 0)          # rounding is monotone
    if precision in P.UNORM_MAX:                              # on the code grid
        c = got * P.UNORM_MAX[precision]
        np.testing.assert_array_equal(c, np.round(c))


def test_half_reference_against_numpy_cast():
    """The exponent-based reference rounding agrees with the IEEE cast (normals and
    subnormals, ties to even)."""
    x = np.concatenate([np.random.default_rng(2).uniform(-1, 1, 2000), [2.0**-24 * 1.5, 2.0**-24 * 2.5,
                                                                         1 + 2.0**-11, 1 + 3 * 2.0**-11]])
    np.testing.assert_array_equal(ref.half(x), x.astype(np.float16).astype(np.float64))


@pytest.mark.parametrize("precision", PRECISIONS)
def test_encoders_match_reference_per_texel(precision):
    """Depth / transmittance / coefficient encoders over 3 texels equal the one-texel
    reference, and their errors stay within its stated bounds."""
    rng = np.random.default_rng(3)
    counts = np.array([5, 1, 7])
    tex = np.repeat(np.arange(3), counts)
    d = np.concatenate([rng.uniform(1e3, 1e3 + 2, 5), [4.0], rng.uniform(-1, 1, 7)])
    t = np.concatenate([np.sort(rng.random(5))[::-1], [1.0], [1.0, 0.5, 0.1, 1e-3, 1e-6, 0.0, 0.0]])
    a = rng.normal(0, 2, counts.sum())
    for k in range(3):
        m = tex == k
        for meaning, x, fn in (("depth", d, ref.depths), ("transmittance", t, ref.transmittances),
                               ("coefficient", a, ref.coefficients)):
            got, _ = P.encode(meaning, x, tex, 3, precision)
            want, bound = fn(x[m], precision)
            np.testing.assert_allclose(got[m], want, rtol=1e-15, atol=0, err_msg=f"{meaning} texel {k}")
            if meaning == "transmittance" and precision == "unorm8":
                err = np.abs(got[m] - x[m]) - bound * x[m]
                assert np.all(err <= math.exp(-ref.TAU_CAP) * 1.001), meaning
            else:
                assert np.max(np.abs(got[m] - x[m])) <= bound * (1 + 1e-9), meaning


def test_transmittance_code_thin_smoke_before_dark_node():
    """unorm8 T: a dark node (T = 1e-4, tau_max = 9.2) must not coarsen the thin smoke in
    front: |dT| <= T^ |dtau|, |dtau| <= tau_max (2 q + 1/508) / 508 with q = sqrt(tau /
    tau_max) (0.0029 at T = 0.97; codes linear in tau err by up to tau_max / 508 = 0.018);
    relative error <= exp(tau_max / 254) - 1 at every node; T = 1 and T = 0 exact."""
    t = np.array([1.0, 0.999, 0.97, 0.9, 0.6, 0.1, 1e-4, 0.0])
    got, extra = P.encode("transmittance", t, np.zeros(t.size, np.int64), 1, "unorm8")
    assert extra == 4.0 and got[0] == 1 and got[-1] == 0
    tau, tmax = -np.log(t[:-1]), -math.log(1e-4)
    q = np.sqrt(tau / tmax)
    dtau = tmax * (2 * q + 1 / 508) / 508
    err = np.abs(got[:-1] - t[:-1])
    assert np.all(err <= np.maximum(got[:-1], t[:-1]) * dtau * (1 + 1e-9))
    assert np.all(err <= t[:-1] * math.expm1(tmax / 254) * (1 + 1e-9))
    assert np.all(err[1:4] <= 0.0029)
    assert np.all(np.diff(got) <= 0)


@pytest.mark.parametrize("precision", PRECISIONS)
def test_optical_depth_encoder(precision):
    """OSM's cumulative optical depths: the encoder equals the one-texel reference; below
    TAU_CAP the error is within s / (M - 1) however large the texel's largest value (an
    opaque 1e4 behind thin smoke used to set the scale: every 8-bit step 39, the smoke 0);
    beyond it every value decodes to the first one past the cap; zeros stay zero, sequences
    stay non-decreasing; floating formats are the non-negative coefficient code, bit for bit."""
    rng = np.random.default_rng(4)
    texels = [np.array([0, 0, 0.01, 0.05, 0.2, 0.2, 1e4 + 0.2, 1e4 + 0.2]),   # thin smoke, opaque
              np.zeros(3),                                                  # empty texel
              np.array([0, 0.5, 3, 9, 12, 20, 40]),                         # dense: crosses the cap
              np.array([20.0, 30.0]),                                       # past the cap at once
              np.cumsum(rng.exponential(0.05, 9)),                          # thin smoke only
              np.array([1e-9, 1e-9, 2e-9])]                                 # faint
    tex = np.concatenate([np.full(t.size, k) for k, t in enumerate(texels)])
    c = np.concatenate(texels)
    got, extra = P.encode("optical_depth", c, tex, len(texels), precision)
    if precision not in P.UNORM_MAX:
        want, extra_c = P.encode("coefficient", c, tex, len(texels), precision, signed=False)
        np.testing.assert_array_equal(got, want)
        assert extra == extra_c
    else:
        assert extra == 8.0
    for k, ck in enumerate(texels):
        g = got[tex == k]
        want, bound, far = ref.optical_depths(ck, precision)
        np.testing.assert_allclose(g, want, rtol=1e-15, atol=0, err_msg=f"texel {k}")
        assert np.all(np.diff(g) >= 0) and np.all(g[ck == 0] == 0), k
        low = ck <= P.TAU_CAP if far is not None else np.ones(ck.size, bool)
        assert np.all(np.abs(g[low] - ck[low]) <= bound * (1 + 1e-9)), k
        if far is not None and np.any(~low):
            first = ck[~low][0]
            assert np.all(g[~low] == far) and 0 <= far - first <= np.spacing(np.float32(first)), k
    if precision == "unorm8":                         # the thin smoke keeps its resolution:
        g0, c0 = got[tex == 0][:6], texels[0][:6]     # |dC| <= s (2 sqrt(C / s) + 1/508) / 508
        assert np.all(np.abs(g0 - c0) <= 0.2 * (2 * np.sqrt(c0 / 0.2) + 1 / 508) / 508 * (1 + 1e-6))


# ------------------------------------------------------- stored buffers
def _texel_lists(rep):
    """Per texel (depths, values) of a node kind (native or quantised), float64."""
    if isinstance(rep, ad.REGISTRY["avsm"].__mro__[1]):        # NodeList (avsm, greedy, optimal)
        d, v = rep.nodes_numpy()
        return [(d[t], v[t]) for t in range(rep.n_texels)]
    off = rep.node_offsets
    if rep.kind == "dsm":
        return [rep.nodes_numpy(t) for t in range(rep.n_texels)]
    z, v = rep.node_depths(), np.asarray(dr.detach(rep.node_value).numpy(), np.float64)
    return [(z[off[t]:off[t + 1]], v[off[t]:off[t + 1]]) for t in range(rep.n_texels)]


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("kind", NODE_KINDS)
def test_node_kinds(seg, kind, precision):
    """Stored nodes = reference decoding of the native nodes; T within the window bound:
    with node depths moved by <= delta (order kept) and values by <= eps, T^(x) is the
    native T at some y with |y - x| <= delta, +- eps (a monotone reparametrisation of each
    piece), so it lies in [min, max] of the native T over the window +- eps."""
    params = NODE_PARAMS.get(kind, {})
    native = ad.build(kind, seg, **params)
    rep = ad.build(kind, seg, precision=precision, **params)
    nat, got = _texel_lists(native), _texel_lists(rep)
    delta, eps = np.zeros(seg.n_texels), np.zeros(seg.n_texels)
    for t, ((dn, vn), (dq, vq)) in enumerate(zip(nat, got)):
        if dn.size == 0:
            continue
        if kind == "avsm_march":       # native: fp16 relative depths; here q from float64
            span = float(rep.range_hi.numpy()[t] - rep.range_lo.numpy()[t])
            delta[t] = span * (ref.code_bound(precision) + 2.0**-12)
            assert np.max(np.abs(dq - dn)) <= delta[t] + 4 * np.spacing(np.float32(abs(dn).max()))
        else:
            want_d, delta[t] = ref.depths(dn, precision)
            np.testing.assert_array_equal(dq, want_d.astype(np.float32))
        want_v, eps[t] = ref.transmittances(vn, precision)
        np.testing.assert_array_equal(vq, want_v.astype(np.float32))
        assert np.all(np.diff(dq) >= 0)                       # still sorted
    tex, x = receivers(seg)
    T = np.asarray(rep.eval(tex, x), np.float64)
    assert np.all(np.isfinite(T)) and np.all((T >= 0) & (T <= 1))
    # window [x - delta, x + delta]: its ends and every native node depth inside it (both
    # sides of a step) hold the native curve's extremes (piecewise monotone between nodes)
    dl = delta[tex] + 4 * np.spacing(np.float32(np.abs(x).max() + 1))
    pts = [x - dl, x + dl]
    for t_nodes in range(max(d.size for d, _ in nat)):
        dk = np.array([d[min(t_nodes, d.size - 1)] if d.size else 0.0 for d, _ in nat])[tex]
        pts += [np.clip(dk, x - dl, x + dl), np.clip(np.nextafter(dk.astype(np.float32), -np.inf), x - dl, x + dl)]
    vals = np.stack([np.asarray(native.eval(tex, p.astype(np.float32)), np.float64) for p in pts])
    slack = eps[tex] + T_SLACK
    assert np.all(T <= vals.max(axis=0) + slack), np.max(T - vals.max(axis=0) - slack)
    assert np.all(T >= vals.min(axis=0) - slack), np.max(vals.min(axis=0) - slack - T)


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("kind", BASIS_KINDS)
def test_basis_kinds(seg, kind, precision):
    """Stored map = reference decoding of the native map per texel; |T^ - T| <= |D^ - D|
    <= sum_k |da_k| |g_k(u)| (min(1, exp(-D)) is 1-Lipschitz); OSM stores C_j and
    interpolates two of them, so |dD| <= eps_C.  Moments: the Hamburger bound is not
    Lipschitz in the moments (no propagated bound): T finite and in [0, 1]."""
    native = ad.build(kind, seg)
    scaled = {"quantization": "scaled"} if kind == "moments" else {}     # msm: tests/test_moment_quantization.py
    rep = ad.build(kind, seg, precision=precision, **scaled)
    field = rep._stored()[0]
    K = dr.width(getattr(native, field.attr)) // seg.n_texels      # stored values per texel
    a_n = np.asarray(dr.detach(getattr(native, field.attr)).numpy(), np.float64).reshape(-1, K)
    a_q = np.asarray(dr.detach(getattr(rep, field.attr)).numpy(), np.float64).reshape(-1, K)
    bound = np.zeros(seg.n_texels)
    for t in range(seg.n_texels):
        if field.meaning == "optical_depth":     # osm (the data hold opaque 1e4 segments)
            want, bound[t], _ = ref.optical_depths(a_n[t], precision)
        else:
            want, bound[t] = ref.coefficients(a_n[t], precision, signed=field.signed)
        np.testing.assert_array_equal(a_q[t], want.astype(np.float32))
    tex, x = receivers(seg)
    T = np.asarray(rep.eval(tex, x), np.float64)
    assert np.all(np.isfinite(T)) and np.all((T >= 0) & (T <= 1))
    if kind == "moments":
        return
    T0 = np.asarray(native.eval(tex, x), np.float64)
    if kind == "osm":
        # |dD| <= bound where D comes from codes below the cap (or one below and the exact
        # first value past it); past the cap T and T^ are both below exp(-TAU_CAP) = 2^-16
        if precision in P.UNORM_MAX:
            bound = np.maximum(bound, math.exp(-P.TAU_CAP))
        g_sum = np.ones_like(x)
    else:
        u = np.asarray(native.normalized_depth(backend.types().UInt32(tex), native.Float(x)), np.float64)
        g = native.basis.g(backend.types().Float64(u))
        g_sum = np.sum([np.abs(np.asarray(gk.numpy(), np.float64)) for gk in g], axis=0)
    assert np.all(np.abs(T - T0) <= bound[tex] * g_sum + T_SLACK)


@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("variant", ["cloud", "two_node"])
def test_beer(variant, precision):
    """Stored fronts = reference decoding over one global range (empty texels, whose T is 1
    whatever their bounds, take the global front: they must not widen it), extents = the
    non-negative coefficient code over the largest extent, tau_max = the scalar code
    (:func:`scalar_ref`), T behind = the transmittance code; T within the window bound
    (the ramp's ends move by <= delta_front + delta_extent) plus eps: tau_max relative
    error r - 1 gives |dT| <= (r - 1) / e; T behind errs by the transmittance bound.
    Depths offset by 100: a range anchored at 0 would be caught."""
    data = random_segments(np.random.default_rng(17), texels=24, max_count=12)
    seg = to_segments(dict(data, z0=data["z0"] + 100, z1=data["z1"] + 100))
    native = ad.build("beer", seg, variant=variant)
    rep = ad.build("beer", seg, variant=variant, precision=precision)
    empty = seg.counts == 0
    front = np.where(empty, seg.bounds()[0], np.asarray(native.front.numpy(), np.float64))
    want, d_front = ref.depths(front, precision)
    np.testing.assert_array_equal(np.asarray(rep.front.numpy()), want.astype(np.float32))
    ext = np.asarray(native.extent.numpy(), np.float64)
    assert np.all(ext[empty] == 0)
    want, d_ext = ref.coefficients(ext, precision, signed=False)
    np.testing.assert_array_equal(np.asarray(rep.extent.numpy()), want.astype(np.float32))
    if variant == "cloud":
        tau = np.asarray(native.tau_max.numpy(), np.float64)
        want, r1, _, floor = scalar_ref(tau, precision)
        np.testing.assert_array_equal(np.asarray(rep.tau_max.numpy()), want.astype(np.float32))
        eps = r1 / math.e + floor
    else:
        want, eps = ref.transmittances(np.asarray(native.t_back.numpy(), np.float64), precision)
        np.testing.assert_array_equal(np.asarray(rep.t_back.numpy()), want.astype(np.float32))
        if precision == "unorm8":
            eps += math.exp(-ref.TAU_CAP)              # relative bound + the cap's floor, T <= 1
    tex, x = receivers(seg)
    T = np.asarray(rep.eval(tex, x), np.float64)
    assert np.all(np.isfinite(T)) and np.all((T >= 0) & (T <= 1))
    dl = d_front + d_ext + 4 * np.spacing(np.float32(np.abs(x).max() + 1))
    lo = np.asarray(native.eval(tex, (x + dl).astype(np.float32)), np.float64)
    hi = np.asarray(native.eval(tex, (x - dl).astype(np.float32)), np.float64)
    slack = eps + T_SLACK
    assert np.all((T >= lo - slack) & (T <= hi + slack))


def scalar_ref(x, precision):
    """Reference of the ``scalar`` code (beer's tau_max), one global scale: (decoded,
    r - 1 with x^ / x in [1/r, r] for x >= the floor, the floor, the absolute error below it).
    float16: fp16(x / 2^p) 2^p, 2^p the smallest power of two keeping max x / 2^p <= 65504;
    unorm: codes 1..M of ln x over [lo, hi] (M - 1 steps), 0 for zero, the nearer of 0 and
    lo below lo."""
    x = np.asarray(x, np.float64)
    if precision == "float32":
        return x.astype(np.float32).astype(np.float64), 2.0**-24, 0.0, 0.0
    top = x.max(initial=0.0)
    if precision == "float16":
        p = 0
        while top / 2.0**p > 65504:
            p += 1
        return ref.half(x / 2.0**p) * 2.0**p, 2.0**-11 / (1 - 2.0**-11), 2.0 ** (p - 14), 2.0 ** (p - 25)
    M, octaves = ref.UNORM_MAX[precision], P.LOG_OCTAVES[precision]
    if top == 0:
        return np.zeros_like(x), 0.0, 0.0, 0.0
    hi = ref.f32_up(top)
    lo = max(ref.f32_down(x[x > 0].min()), ref.f32_up(hi / 2.0**octaves))
    L = math.log(hi / lo)
    out = []
    for v in x:
        if v >= lo:
            c = round((M - 1) * math.log(v / lo) / L) if L > 0 else 0
            out.append(min(lo * math.exp(L * c / (M - 1)), hi))
        else:
            out.append(lo if v >= lo / 2 else 0.0)
    return np.array(out), math.expm1(L / (2 * (M - 1))) * (1 + 1e-12), lo, lo / 2


@pytest.mark.parametrize("precision", PRECISIONS)
def test_scalar_encoder(precision):
    """The ``scalar`` code against :func:`scalar_ref` (the encoder's decoded values bit for
    bit) and its bound: x^ / x within [1/r, r] at and above the floor, r - 1 <= 2^-11
    (float16), exp(ln 2^octaves / (2 (M - 1))) - 1 (unorm: 3.3 % unorm8, 3.4e-4 unorm16),
    below it within lo / 2; 0 stays 0; monotone.  Values from 1e-12 to 1e6: a linear code
    over the largest one would zero every thin texel, saturating float16 at 65504 would
    flatten the ramp of the 1e6 one."""
    x = np.array([0.0, 1e-12, 3e-9, 1e-6, 1e-3, 0.02, 0.5, 1.0, 2.3, 17.0, 1e4, 7e4, 1e6])
    got = P.encode("scalar", x, None, x.size, precision)[0]
    want, r1, lo, floor = scalar_ref(x, precision)
    np.testing.assert_allclose(got, want, rtol=1e-13, atol=0)
    assert got[0] == 0 and np.all(np.diff(got) >= 0)
    if precision in P.UNORM_MAX:
        assert r1 <= math.expm1(P.LOG_OCTAVES[precision] * math.log(2) / (2 * (P.UNORM_MAX[precision] - 1))) * 1.001
    big = (x >= lo) & (x > 0)
    ratio = got[big] / x[big]
    assert np.all((ratio <= 1 + r1) & (ratio >= 1 / (1 + r1))), ratio
    assert np.all(np.abs(got[~big] - x[~big]) <= floor * (1 + 1e-9))


@pytest.mark.parametrize("precision", ["unorm8", "unorm16"])
def test_osm_opaque_behind_thin_smoke(precision):
    """An opaque blocker (optical depth 1e4) behind thin smoke, and a dense medium crossing
    TAU_CAP inside one slice: T^ / T within exp(+-s / (M - 1)) (s: the texel's largest
    cumulative optical depth below the cap, so the smoke's own), or both below 2^-16 past the
    cap; T = 1 exactly in the slices in front of the content; T^ non-increasing.  The former
    per-texel max scale left the smoke at code 0 (T = 1, errors up to 1 - T)."""
    smoke = [0.001, 0.02, 0.1, 0.4, 1.0, 3.0]
    offsets, z0, z1, tau = [0], [], [], []
    for k, total in enumerate(smoke):                      # two smoke segments, then the table
        z0 += [0.30, 0.45, 0.80 + 0.003 * k]
        z1 += [0.50, 0.62, 0.81 + 0.003 * k]
        tau += [0.4 * total, 0.6 * total, ad.OPAQUE_OPTICAL_DEPTH]
        offsets.append(len(z0))
    for dense in (12.0, 30.0, 200.0):                      # C crosses the cap inside a slice
        z0 += [0.3, 0.55]
        z1 += [0.5, 0.555]
        tau += [0.5, dense]
        offsets.append(len(z0))
    seg = ad.Segments.from_arrays(offsets, z0, z1, optical_depth=tau)
    native = ad.build("osm", seg, slices=32, near=0.0, far=1.0)
    rep = ad.build("osm", seg, slices=32, near=0.0, far=1.0, precision=precision)
    steps = P.UNORM_MAX[precision] - 1
    cum = np.asarray(native._cum.numpy(), np.float64).reshape(seg.n_texels, -1)
    eps = np.array([ref.optical_depths(c, precision)[1] for c in cum])
    per = 513
    tex = np.repeat(np.arange(seg.n_texels), per)
    x = np.tile(np.linspace(0, 1, per), seg.n_texels)
    T0 = np.asarray(native.eval(tex, x), np.float64)
    T = np.asarray(rep.eval(tex, x), np.float64)
    # float32 lookups: decoded C rounded to float32 (relative 6e-8, C <= TAU_CAP) and exp
    slack = 4e-6 * T0 + 1e-12
    tol = np.maximum(T0 * np.expm1(eps[tex]), math.exp(-P.TAU_CAP)) + slack
    assert np.all(np.abs(T - T0) <= tol), np.max(np.abs(T - T0) - tol)
    front = x < 9 / 32                                     # slices 0..8 hold no content
    assert np.all(T[front] == 1) and np.all(T0[front] == 1)
    assert np.all(np.diff(T.reshape(seg.n_texels, -1), axis=1) <= 1e-7)
    smoke_only = (x < 0.78) & (tex < len(smoke))           # in front of the table
    rel = np.abs(T - T0)[smoke_only] / T0[smoke_only]
    assert np.max(rel) <= math.expm1(max(smoke) / steps) + 4e-6
    # the old scale (the texel's largest C, the table's 1e4): the thinnest smoke rounds to 0
    old, _ = P.encode("coefficient", cum[0], np.zeros(cum.shape[1], np.int64), 1, precision, signed=False)
    assert np.all(old[cum[0] < 1e3] == 0) and np.any(cum[0][cum[0] < 1e3] > 0)


# ------------------------------------------------------------ contract
def expected_nbytes(rep) -> float:
    """The storage formula per kind (module docstring of _precision)."""
    p = rep.precision
    c = P.CODE_BYTES[p]
    rng_d = 0 if p == "float32" else 8                       # per-texel depth range
    t8 = 4 if p == "unorm8" else 0                           # per-texel max optical depth
    scale = 0 if p == "float32" else 4                       # per-texel coefficient scale
    if rep.kind in ("avsm", "greedy", "optimal"):
        return rep.N * 2 * c + rng_d + t8
    if rep.kind == "dsm":
        return rep.node_counts.mean() * 2 * c + rng_d + t8 + 4
    if rep.kind == "avsm_march":
        return 4 + 8 + rep.node_counts.mean() * 2 * c + t8
    if rep.kind == "beer":
        return 3 * c
    if rep.kind == "moments" and rep.params["quantization"] == "msm":    # 4 codes + b_0 in float32
        return 4 * c + 4 + (8 if rep._per_texel else 0)
    if rep.kind == "osm" and p in P.UNORM_MAX:
        scale = 8                                            # cap scale s and far value F
    return rep.basis.n_coefficients * c + scale + (8 if rep._per_texel else 0)


@pytest.mark.parametrize("kind", sorted(set(NODE_KINDS + BASIS_KINDS + ["beer"])))
def test_nbytes_monotone_and_default(seg, kind):
    """nbytes_per_texel follows the formula; monotone kinds stay monotone; precision=None
    is the build without the parameter, bit for bit; 'float32' on float32 storage too
    (except avsm_march, whose default keeps float16 relative depths)."""
    params = {"depth_range": "texel"} if kind == "fom" else {}
    plain = ad.build(kind, seg, **params)
    tex, x = receivers(seg, per=40)
    T0 = np.asarray(plain.eval(tex, x))
    none = ad.build(kind, seg, precision=None, **params)
    np.testing.assert_array_equal(np.asarray(none.eval(tex, x)), T0)
    assert none.nbytes_per_texel == plain.nbytes_per_texel
    for p in plain.precisions:
        rep = ad.build(kind, seg, precision=p, **params)
        assert rep.nbytes_per_texel == pytest.approx(expected_nbytes(rep), rel=1e-12), p
        T = np.asarray(rep.eval(tex, x)).reshape(seg.n_texels, -1)
        if rep.monotone:
            assert np.all(np.diff(T, axis=1) <= 1e-6), p      # float32 rounding of equal neighbours
        if p == "float32" and kind != "avsm_march":
            np.testing.assert_array_equal(T.ravel(), T0)
            assert rep.nbytes_per_texel == plain.nbytes_per_texel


def test_float32_of_float64_storage(seg):
    """float64 segments stored as float32: the nodes are the float32 roundings."""
    data = random_segments(np.random.default_rng(5), texels=8, max_count=8)
    s64 = to_segments(data, dtype="float64")
    native = ad.build("avsm", s64)
    rep = ad.build("avsm", s64, precision="float32")
    d0, v0 = native.nodes_numpy()
    d1, v1 = rep.nodes_numpy()
    np.testing.assert_array_equal(d1, d0.astype(np.float32))
    np.testing.assert_array_equal(v1, v0.astype(np.float32))
    assert rep.nbytes_per_texel == 2 * 8 * 4 and native.nbytes_per_texel == 2 * 8 * 8


@pytest.mark.parametrize("kind", ["fom", "osm", "avsm"])
def test_straight_through_gradient(kind):
    """The quantised kinds stay differentiable: for the basis kinds dT/dtau with the
    straight-through estimator is -T^ sum_k g_k da_k/dtau, the native one times T^ / T
    (one receiver, so the ratio is exact up to float32 rounding)."""
    Float = backend.types().Float
    # 2 texels: Segments.texel_of_segment fails on a one-texel map (a size-0 comparison)
    data = random_segments(np.random.default_rng(9), texels=2, max_count=6, empty_fraction=0.0,
                           opaque_fraction=0.0)
    grads, Ts = {}, {}
    for p in (None, "unorm8"):
        tau = Float(data["tau"].astype(np.float32))
        dr.enable_grad(tau)
        s = ad.Segments.from_arrays(data["offsets"], data["z0"], data["z1"], optical_depth=tau)
        T = ad.build(kind, s, precision=p).eval([0], [0.9])
        dr.backward(T)
        grads[p], Ts[p] = np.asarray(dr.grad(tau).numpy()), float(np.asarray(dr.detach(T))[0])
    assert np.all(np.isfinite(grads["unorm8"])) and np.any(grads["unorm8"] != 0)
    if kind in ("fom", "osm"):
        np.testing.assert_allclose(grads["unorm8"], grads[None] * Ts["unorm8"] / Ts[None], rtol=1e-4, atol=1e-7)


def test_refusals(seg):
    for kind, p in (("exact", "float16"), ("exact", "float32"), ("beer", "half"), ("avsm", "half"),
                    ("avsm", 16)):
        with pytest.raises(ValueError, match="^precision:"):
            ad.build(kind, seg, precision=p)
    far = ad.Segments.from_arrays([0, 1], [0.0], [1e39], optical_depth=[1.0], dtype="float64")
    with pytest.raises(ValueError, match="^precision:.*float32's range"):
        ad.build("avsm", far, precision="float16")        # a float32 range cannot hold 1e39
    assert ad.describe("beer")["precisions"] == PRECISIONS
    assert ad.describe("exact")["precisions"] == []
    assert ad.describe("avsm")["precisions"] == PRECISIONS


def test_avsm_march_default_unchanged(seg):
    """avsm_march keeps its float16 relative depths and native T without ``precision``."""
    rep = ad.build("avsm_march", seg)
    assert type(rep.node_q).__name__ == "Float16"
    item = seg.itemsize
    assert rep.nbytes_per_texel == 4 + 2 * item + rep.node_counts.mean() * (2 + item)


def test_dsm_float16_dense_bytes_exceed_float32_when_texels_are_mostly_empty():
    """The 8-byte per-texel depth range is charged to every texel in the dense layout: with under
    2 nodes per texel on average (most texels empty) float16 DSM takes more dense bytes than
    float32, as the module says; the sparse layout, ranges on non-empty texels only, does not."""
    counts = np.zeros(400, int)
    counts[::10] = 3                                   # 10 % of texels hold 3 one-segment steps
    offsets = np.concatenate([[0], np.cumsum(counts)])
    z0 = np.concatenate([np.sort(np.random.default_rng(k).uniform(0, 1, c)) for k, c in enumerate(counts)])
    seg = ad.Segments.from_arrays(offsets, z0, z0 + 0.01, transmittance=np.full(z0.size, 0.6))
    f32, f16 = (ad.build("dsm", seg, tolerance=0.01, precision=p) for p in ("float32", "float16"))
    assert f16.nbytes_per_texel > f32.nbytes_per_texel
    assert f16.nbytes_sparse_per_texel < f32.nbytes_sparse_per_texel

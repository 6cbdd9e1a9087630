"""Beer shadow map (beer.py) against the float64 reference (tests/reference/beer_ref.py):
both variants, exactness for one uniform segment, the definition of the mean extinction,
content without extent, storage; every storage precision across depth scales 1e-6..1e8
and beyond float16's range of optical depths; a bit-deterministic tau_max."""
import numpy as np
import pytest

import avsm_dr as ad
from cases import random_segments, to_segments
from reference import beer_ref, exact_ref


@pytest.mark.parametrize("variant", ["cloud", "two_node"])
def test_matches_reference(backend, rng, variant):
    data = random_segments(rng, texels=40, max_count=12)
    seg = to_segments(data, "float64")
    rep = ad.build("beer", seg, variant=variant)
    depth = np.linspace(-0.2, 1.3, 61)
    tex = np.repeat(np.arange(40), depth.size)
    got = np.asarray(rep.eval(tex, np.tile(depth, 40))).reshape(40, -1)
    off = data["offsets"]
    tau = np.minimum(data["tau"], ad.OPAQUE_OPTICAL_DEPTH)
    for t in range(40):
        s = slice(off[t], off[t + 1])
        ref = [beer_ref.transmittance(data["z0"][s], data["z1"][s], tau[s], d, variant) for d in depth]
        # float64 throughout: rounding only (sums of <= 12 optical depths)
        np.testing.assert_allclose(got[t], ref, rtol=1e-12, atol=1e-14)


def test_cloud_is_exact_for_one_uniform_segment(backend):
    seg = ad.Segments.from_arrays([0, 1, 2], [0.25, 3.0], [0.75, 7.0], optical_depth=[1.7, 0.4], dtype="float64")
    beer = ad.build("beer", seg)
    for t, (a, b, tau) in enumerate([(0.25, 0.75, 1.7), (3.0, 7.0, 0.4)]):
        d = np.linspace(a - 1, b + 1, 101)
        ref = [exact_ref.transmittance([a], [b], [tau], x) for x in d]
        np.testing.assert_allclose(np.asarray(beer.eval(np.full(d.size, t), d)), ref, rtol=1e-13, atol=1e-15)


def test_mean_extinction_spreads_the_total_over_the_content():
    # two segments with a gap: sigma_mean = (0.6 + 0.9) / (1.0 - 0.0), gaps included
    seg = ad.Segments.from_arrays([0, 2], [0.0, 0.8], [0.2, 1.0], optical_depth=[0.6, 0.9], dtype="float64")
    rep = ad.build("beer", seg)
    assert float(rep.sigma_mean.numpy()[0]) == pytest.approx(1.5, rel=1e-15)
    assert float(rep.tau_max.numpy()[0]) == pytest.approx(1.5, rel=1e-15)
    T = np.asarray(rep.eval([0, 0, 0], [0.5, 1.0, 2.0]))
    np.testing.assert_allclose(T, np.exp([-0.75, -1.5, -1.5]), rtol=1e-14)


@pytest.mark.parametrize("variant", ["cloud", "two_node"])
def test_content_without_extent_is_a_step(variant):
    # only zero-length segments at one depth: T = 1 in front, exp(-tau) at and behind it
    seg = ad.Segments.from_arrays([0, 2], [0.5, 0.5], [0.5, 0.5], optical_depth=[0.3, 0.4], dtype="float64")
    T = np.asarray(ad.build("beer", seg, variant=variant).eval([0, 0, 0], [0.49, 0.5, 0.9]))
    np.testing.assert_allclose(T, [1.0, np.exp(-0.7), np.exp(-0.7)], rtol=1e-15)


def test_two_node_interpolates_linearly_between_entry_and_exit():
    seg = ad.Segments.from_arrays([0, 1], [1.0], [3.0], optical_depth=[2.0], dtype="float64")
    T = np.asarray(ad.build("beer", seg, variant="two_node").eval([0] * 4, [0.5, 1.0, 2.0, 3.0]))
    tb = np.exp(-2.0)
    np.testing.assert_allclose(T, [1.0, 1.0, 0.5 * (1 + tb), tb], rtol=1e-15)


@pytest.mark.parametrize("dtype, size", [("float32", 12), ("float64", 24)])
def test_storage_is_three_floats(dtype, size):
    seg = ad.Segments.from_arrays([0, 1, 1], [0.1], [0.2], optical_depth=[1.0], dtype=dtype)
    for variant in ("cloud", "two_node"):
        assert ad.build("beer", seg, variant=variant).nbytes_per_texel == size


def test_bad_variant():
    seg = ad.Segments.from_arrays([0, 1], [0.1], [0.2], optical_depth=[1.0])
    with pytest.raises(ValueError, match="^variant"):
        ad.build("beer", seg, variant="clouds")


# ------------------------------------------------------------ storage precision
#: Depth scales of the precision tests: thin (1e-6) to long (1e8) texels.
SCALES = [10.0**k for k in range(-6, 9)]
PRECISIONS = ["float32", "float16", "unorm16", "unorm8"]
#: float32 lookups: rounding of the exp and the interpolation (as tests/test_precision.py)
T_SLACK = 2e-6
EPS32 = 2.0**-24


def _log_code_ratio(precision):
    """r - 1 of the logarithmic unorm code of tau_max (_precision, ``scalar``): half a step
    of ln over LOG_OCTAVES octaves (plus the float32 outward rounding of its ends)."""
    from avsm_dr.representations import _precision as P
    span = P.LOG_OCTAVES[precision] * np.log(2.0) + 4 * EPS32
    return np.expm1(span / (2 * (P.UNORM_MAX[precision] - 1)))


def _format_bounds(precision, variant, fronts, extents, tau_top):
    """(delta_front, delta_extent per texel, eps_T) from the formats alone: the front code
    over the map's range of fronts, the extent code over its largest extent s (float16
    relative 2^-11 down to 2^-14 s, 2^-25 s absolute below), and the third value: tau_max
    relative (``x^ / x`` in ``[1/r, r]`` gives ``|dT| <= (r - 1) / e``), or T behind."""
    M = {"unorm16": 65535, "unorm8": 255}.get(precision)
    span, s = fronts.max() - fronts.min(), extents.max()
    if precision == "float32":
        return 0.0, np.zeros_like(extents), 0.0
    if precision == "float16":
        d_front, d_ext = 2.0**-12 * span, 2.0**-11 * extents + 2.0**-25 * s
        eps = (2.0**-11 / (1 - 2.0**-11)) / np.e + 2.0**-25 if variant == "cloud" else 2.0**-12
        return d_front, d_ext, eps
    d_front, d_ext = span / (2 * M), np.full_like(extents, s / (2 * M))
    if variant == "cloud":
        from avsm_dr.representations import _precision as P
        lo = tau_top * 2.0**-P.LOG_OCTAVES[precision]        # below it: 0 or lo, error lo / 2
        return d_front, d_ext, _log_code_ratio(precision) / np.e + lo
    from avsm_dr.representations import _precision as P
    eps = 1 / 65535 if precision == "unorm16" else np.expm1(P.TAU_CAP / 254) + 2.0**-16
    return d_front, d_ext, eps


def _scale_case(L):
    """Texels at depth scale L (offset 3L): one segment (tau 1, T_exit 0.1), a gap, empty,
    opaque, content without extent, a texel 1e-3 L thin."""
    c = 3 * L
    texels = [[(c, c + L, 1.0)], [(c, c + L, np.log(10.0))],
              [(c + 0.25 * L, c + 0.5 * L, 0.5), (c + 0.9 * L, c + L, 2.0)], [],
              [(c, c + 0.5 * L, ad.OPAQUE_OPTICAL_DEPTH)], [(c + 0.5 * L, c + 0.5 * L, 0.3)],
              [(c + 0.1 * L, c + 0.101 * L, 1e-3)]]
    offsets = np.cumsum([0] + [len(t) for t in texels])
    z0, z1, tau = (np.array([s[i] for t in texels for s in t]) for i in range(3))
    return dict(offsets=offsets, z0=z0, z1=z1, tau=tau)


@pytest.mark.parametrize("variant", ["cloud", "two_node"])
@pytest.mark.parametrize("precision", PRECISIONS)
def test_precision_across_depth_scales(precision, variant):
    """Every precision, texels from 1e-6 to 1e8 long: T within the formats' bounds of the
    float64 reference.  The front and extent codes move the ramp's ends by <= delta_front +
    delta_extent (T^(d) = T(d') with |d' - d| <= that: a window, T monotone), the third
    value adds eps_T; float32 rounds the front, extent and receiver by 2^-24 of the depths
    (4 of them).  The former stored extinction tau / L underflowed float16 for long
    texels (L = 1e8: T(L / 2) = 0.368, exact 0.6065) and saturated it for thin ones."""
    for L in SCALES:
        case = _scale_case(L)
        seg = to_segments(case)
        rep = ad.build("beer", seg, variant=variant, precision=precision)
        assert rep.nbytes_per_texel == 3 * {"float32": 4, "float16": 2, "unorm16": 2, "unorm8": 1}[precision]
        off = case["offsets"]
        n = off.size - 1
        full = [slice(off[t], off[t + 1]) for t in range(n)]
        fronts = np.array([case["z0"][s].min() for s in full if s.stop > s.start])
        extents = np.array([case["z1"][s].max() - case["z0"][s].min() if s.stop > s.start else 0.0 for s in full])
        d_front, d_ext, eps = _format_bounds(precision, variant, fronts, extents, case["tau"].sum())
        x = 3 * L + L * np.linspace(-0.5, 2.0, 101)
        tex = np.repeat(np.arange(n), x.size)
        T = np.asarray(rep.eval(tex, np.tile(x, n)), np.float64).reshape(n, -1)
        assert np.all(np.isfinite(T)) and np.all((T >= 0) & (T <= 1))
        for t in range(n):
            s = full[t]
            zs, ze, ts = case["z0"][s], case["z1"][s], case["tau"][s]
            delta = d_front + d_ext[t] + 4 * EPS32 * 4 * L * (1 + 1e-6)

            def ref(d):
                return np.array([beer_ref.transmittance(zs, ze, ts, v, variant) for v in d])
            lo, hi = ref(x + delta), ref(x - delta)              # T non-increasing in depth
            tol = eps + T_SLACK
            assert np.all((T[t] >= lo - tol) & (T[t] <= hi + tol)), (L, t, np.max(lo - tol - T[t]),
                                                                       np.max(T[t] - hi - tol))


@pytest.mark.parametrize("precision", [None] + PRECISIONS)
def test_issue_cases_long_and_thin(precision):
    """The reported cases, one segment [0, L] alone in its map (its front and extent are
    then exact in every code): optical depth 1, receiver at L / 2: exp(-1/2) for L in
    1e-6..1e8; T_exit 0.1 behind a 1e-5-thin segment: 0.1.  Bound: the tau code only
    (float16 half an ulp of 2.3: 2^-10, relative; unorm: one value per map is its own scale,
    exact up to float32), plus float32 lookup rounding."""
    rel = 2.0**-10 if precision == "float16" else 0.0
    for L in SCALES:
        seg = ad.Segments.from_arrays([0, 1], [0.0], [L], optical_depth=[1.0])
        T = float(np.asarray(ad.build("beer", seg, precision=precision).eval([0], [L / 2]))[0])
        assert abs(T - np.exp(-0.5)) <= 0.5 * rel + T_SLACK, (L, T)
    seg = ad.Segments.from_arrays([0, 1], [0.0], [1e-5], optical_depth=[np.log(10.0)])
    T = float(np.asarray(ad.build("beer", seg, precision=precision).eval([0], [2e-5]))[0])
    assert abs(T - 0.1) <= 0.1 * np.log(10.0) * rel + T_SLACK, T


def test_float16_does_not_saturate_large_optical_depths():
    """tau_max beyond float16's 65504 (seven opaque segments): the float16 code scales the
    map by a power of two instead of saturating, so the ramp keeps its slope (saturated,
    T(a + e / 1e4) = exp(-6.55) = 1.4e-3 instead of exp(-7) = 9.1e-4, and the ramp 15x too
    long for a total of 1e6).  Bound: tau relative 2^-11, so |dT| <= T tau w 2^-11, plus
    float32 lookup rounding (w and the product tau w: 3 eps relative, the exp: 4 eps)."""
    n = 7
    seg = ad.Segments.from_arrays([0, n], np.zeros(n), np.ones(n), optical_depth=np.full(n, 1e4))
    rep = ad.build("beer", seg, precision="float16")
    d = np.array([1e-5, 1e-4, 5e-4])
    T = np.asarray(rep.eval(np.zeros(3, np.int64), d), np.float64)
    want = np.exp(-7e4 * d)
    assert np.all(np.abs(T - want) <= want * (7e4 * d * (2.0**-11 + 3 * EPS32) + 4 * EPS32)), T / want - 1


def test_tau_max_is_bit_deterministic():
    """tau_max summed per texel in CSR order (no float atomics): the same bits after other
    builds and for every thread count."""
    import drjit as dr
    case = random_segments(np.random.default_rng(5), texels=2000, max_count=40)
    seg = to_segments(case)
    first = np.asarray(ad.build("beer", seg).tau_max.numpy())
    threads = dr.thread_count()
    try:
        for n in (1, 3, threads):
            dr.set_thread_count(n)
            ad.build("osm", seg)
            again = np.asarray(ad.build("beer", to_segments(case)).tau_max.numpy())
            assert np.array_equal(again, first), n
    finally:
        dr.set_thread_count(threads)

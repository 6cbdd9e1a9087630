"""Deep shadow maps (Lokovic-Veach): the Dr.Jit kernels against the float64 NumPy
reference (tests/reference/dsm_ref.py), the error bound |DSM - V| <= tolerance, node
counts, monotonicity, gradients of the 'curve' placement and bad input.

Tolerances used below:
* nodes vs reference: depths exactly equal in float32 (both sides round the same
  float64 depth; breakpoints are input values), values to float32 rounding (rtol 2^-23,
  atol 1e-7); float64: 1e-12 (the kernel's prefix sums and the reference's direct sums
  differ by a few ulp).
* error bound: DSM in float32 is evaluated with float32 arithmetic and stores float32
  values: slack 1e-6 (a few ulp of 1); float64: 1e-12.
"""
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

import avsm_dr as ad
import drjit as dr
from avsm_dr import backend
from cases import random_segments
from reference import dsm_ref

PLACEMENTS = ["midslope", "curve"]
DTYPES = ["float32", "float64"]
SLACK = {"float32": 1e-6, "float64": 1e-12}


# ----------------------------------------------------------------------------
# inputs
# ----------------------------------------------------------------------------
def _pack(texels):
    """list of (z0, z1, tau) per texel -> dict(offsets, z0, z1, tau)."""
    counts = [len(t[0]) for t in texels]
    cat = [np.concatenate([np.asarray(t[i], float) for t in texels]) if sum(counts) else np.zeros(0)
           for i in range(3)]
    return dict(offsets=np.r_[0, np.cumsum(counts)].astype(np.int64), z0=cat[0], z1=cat[1], tau=cat[2])


def adversarial(rng):
    """Coincident, zero-length, opaque, steep and crowded texels, with empty ones between."""
    ops = ad.OPAQUE_OPTICAL_DEPTH
    many = rng.uniform(0, 1, 1500)
    tex = [
        ([], [], []),                                                         # empty
        ([0.2] * 4 + [0.5] * 3 + [0.1], [0.5] * 4 + [0.5] * 3 + [0.9],       # coincident + stacked steps
         [0.3, 0.3, 0.1, 0.0, 0.2, 0.2, 0.0, 1.0]),
        ([0.1, 0.3, 0.3, 0.6, 0.7], [0.4, 0.3, 0.5, 0.9, 0.7], [2.0, ops, 1.0, 0.5, 0.2]),   # opaque step
        ([0.2, 0.25, 0.6], [0.3, 0.25, 0.8], [ops, 0.1, 3.0]),                # opaque ramp then more
        ([0.3, 0.3 + 1e-6, 0.0, 0.5], [0.3 + 1e-6, 0.3 + 2e-6, 1.0, 0.5 + 1e-7],  # steep, short, nested
         [5.0, 1e-3, 0.7, 8.0]),
        ([], [], []),
        (many, many + rng.uniform(0, 0.3, 1500) * (rng.random(1500) > 0.1),   # 1500 overlapping, 10% zero-length
         rng.exponential(2e-3, 1500)),
        ([0.4], [0.4], [0.0]),                                                # transparent step only
        ([0.0, 0.0], [1.0, 1.0], [0.0, 0.0]),                                 # transparent ramps
    ]
    return _pack(tex)


def scaled(data, scale):
    return dict(offsets=data["offsets"], z0=data["z0"] * scale, z1=data["z1"] * scale, tau=data["tau"])


def make_seg(data, dtype):
    return ad.Segments.from_arrays(data["offsets"], data["z0"], data["z1"], optical_depth=data["tau"],
                                   dtype=dtype)


def dense_depths(z0, z1, dtype, n=1500):
    """Uniform depths over and around the texel's range, every breakpoint and the
    representable depth just before it (where steps and kinks are)."""
    bps = np.unique(np.r_[z0, z1]).astype(dtype)
    span = max(float(bps[-1] - bps[0]), 1e-3)
    grid = np.linspace(bps[0] - 0.1 * span, bps[-1] + 0.1 * span, n).astype(dtype)
    return np.unique(np.r_[grid, bps, np.nextafter(bps, dtype(-np.inf)),
                           np.nextafter(bps, dtype(np.inf))]).astype(np.float64)


def check_error_bound(data, dtype, placement, tol):
    """max over texels and dense depths of |DSM - V| / tol (asserted <= 1 + slack)."""
    seg = make_seg(data, dtype)
    h = seg.numpy()
    rep = ad.build("dsm", seg, tolerance=tol, placement=placement)
    worst = 0.0
    for t in range(seg.n_texels):
        s = slice(h["offsets"][t], h["offsets"][t + 1])
        if s.stop == s.start:
            continue
        d = dense_depths(h["z0"][s], h["z1"][s], np.float32 if dtype == "float32" else np.float64)
        T = np.asarray(rep.eval(np.full(d.size, t), d), np.float64)
        V = dsm_ref.exact_curve(h["z0"][s], h["z1"][s], h["optical_depth"][s], d)
        err = np.abs(T - V)
        assert err.max() <= tol + SLACK[dtype], (t, err.max(), d[err.argmax()])
        worst = max(worst, err.max() / tol)
    return rep, worst


def check_matches_reference(data, dtype, placement, tol):
    seg = make_seg(data, dtype)
    h = seg.numpy()
    rep = ad.build("dsm", seg, tolerance=tol, placement=placement)
    ref = dsm_ref.build(h["offsets"], h["z0"], h["z1"], h["optical_depth"], tol, placement, dtype)
    assert np.array_equal(rep.node_counts, [z.size for z, _ in ref])
    for t, (rz, rv) in enumerate(ref):
        nz, nv = rep.nodes_numpy(t)
        if dtype == "float32":
            np.testing.assert_array_equal(nz, rz.astype(np.float32))
            np.testing.assert_allclose(nv, rv.astype(np.float32), rtol=2.0**-23, atol=1e-7)
        else:
            np.testing.assert_allclose(nz, rz, rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(nv, rv, rtol=0, atol=1e-12)
    return rep


# ----------------------------------------------------------------------------
# kernel == reference
# ----------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("placement", PLACEMENTS)
@pytest.mark.parametrize("tol", [0.05, 0.002])
def test_nodes_match_reference_random(rng, placement, dtype, tol):
    data = random_segments(rng, texels=30, max_count=30)
    rep = check_matches_reference(data, dtype, placement, tol)
    assert rep.node_counts.sum() > 30        # something was compressed and kept


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("placement", PLACEMENTS)
def test_nodes_match_reference_adversarial(rng, placement, dtype):
    data = adversarial(rng)
    rep = check_matches_reference(data, dtype, placement, 0.01)
    counts = rep.node_counts
    assert counts[0] == 0 and counts[5] == 0              # empty texels store nothing
    assert counts[6] > 2                                  # the crowded texel keeps its shape
    # the compressed form is much smaller than the exact polyline of the crowded texel
    assert counts[6] < rep.n_polyline_vertices[6] / 20


# ----------------------------------------------------------------------------
# the guarantee: |DSM - V| <= tolerance everywhere
# ----------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("placement", PLACEMENTS)
@pytest.mark.parametrize("tol", [0.1, 0.01, 0.001])
def test_error_bound_random(rng, placement, dtype, tol):
    data = random_segments(rng, texels=25, max_count=40, opaque_fraction=0.1, zero_fraction=0.2)
    _, worst = check_error_bound(data, dtype, placement, tol)
    assert worst > 0.2    # the bound is used, not trivially met by storing everything


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("placement", PLACEMENTS)
@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e5])
def test_error_bound_adversarial(rng, placement, dtype, scale):
    for tol in (0.02, 1e-3):
        check_error_bound(scaled(adversarial(rng), scale), dtype, placement, tol)


@pytest.mark.parametrize("placement", PLACEMENTS)
def test_one_ray_with_1e5_segments(rng, placement):
    """1e5 overlapping segments (10% zero-length) on one ray beside small texels: the
    prefix-sum polyline is O(S log S); error checked on 400 depths against the direct sum."""
    n = 100_000
    z0 = np.sort(rng.gamma(2.0, 2.0, n))
    z1 = z0 + rng.exponential(0.5, n) * (rng.random(n) > 0.1)
    tau = rng.exponential(3e-5, n)
    data = _pack([([0.1, 0.2], [0.3, 0.2], [0.5, 0.5]), (z0, z1, tau), ([], [], [])])
    seg = make_seg(data, "float32")
    h = seg.numpy()
    tol = 0.005
    rep = ad.build("dsm", seg, tolerance=tol, placement=placement)
    s = slice(2, 2 + n)
    bps = np.unique(np.r_[h["z0"][s], h["z1"][s]])
    d = np.r_[np.linspace(-1, bps[-1] + 1, 200), rng.choice(bps, 100, replace=False)]
    d = np.unique(np.r_[d, np.nextafter(d.astype(np.float32), np.float32(-np.inf))].astype(np.float32))
    d = d.astype(np.float64)
    T = np.asarray(rep.eval(np.full(d.size, 1), d), np.float64)
    V = dsm_ref.exact_curve(h["z0"][s], h["z1"][s], h["optical_depth"][s], d, chunk=16)
    assert np.abs(T - V).max() <= tol + SLACK["float32"]
    assert 3 <= rep.node_counts[1] < 200
    assert rep.node_counts[2] == 0


# ----------------------------------------------------------------------------
# properties
# ----------------------------------------------------------------------------
@pytest.mark.parametrize("placement", PLACEMENTS)
def test_node_count_decreases_with_tolerance(rng, placement):
    seg = make_seg(random_segments(rng, texels=40, max_count=40, opaque_fraction=0.0), "float32")
    totals = [ad.build("dsm", seg, tolerance=t, placement=placement).node_counts.sum()
              for t in (1e-4, 1e-3, 1e-2, 1e-1)]
    assert all(a > b for a, b in zip(totals, totals[1:])), totals


def test_midslope_needs_no_more_nodes_than_curve(rng):
    """The paper's placement has more freedom (the node may sit off the curve)."""
    seg = make_seg(random_segments(rng, texels=60, max_count=40), "float32")
    for tol in (0.01, 0.001):
        mid = ad.build("dsm", seg, tolerance=tol).node_counts.sum()
        cur = ad.build("dsm", seg, tolerance=tol, placement="curve").node_counts.sum()
        assert mid <= cur


@pytest.mark.parametrize("placement", PLACEMENTS)
def test_monotone_and_in_unit_range(rng, placement):
    data = adversarial(rng)
    seg = make_seg(data, "float32")
    rep = ad.build("dsm", seg, tolerance=0.01, placement=placement)
    for t in range(seg.n_texels):
        z, v = rep.nodes_numpy(t)
        assert np.all(np.diff(z) >= 0) and np.all(np.diff(v) <= 0)     # stored nodes: exactly
        assert np.all((v >= 0) & (v <= 1))
    d = np.linspace(-0.5, 1.5, 801)
    T = np.asarray(rep.eval(np.repeat(np.arange(seg.n_texels), d.size), np.tile(d, seg.n_texels)))
    T = T.reshape(seg.n_texels, -1)
    assert np.all((T >= 0) & (T <= 1))
    assert np.all(np.diff(T, axis=1) <= 1e-6)       # float32 interpolation rounding at nodes


def test_eval_front_behind_and_steps():
    """T = 1 before the first node and in empty texels, the last value behind the last
    node, the value behind a step at the step's depth.  'curve' nodes sit on the curve
    (exact); 'midslope' nodes may sit up to tolerance / 2 off it (the mid-slope line)."""
    seg = ad.Segments.from_arrays([0, 2, 2], [0.3, 0.5], [0.3, 0.5], transmittance=[0.5, 0.2],
                                  dtype="float64")
    tol = 1e-3
    for placement, atol in (("curve", 1e-12), ("midslope", tol / 2)):
        rep = ad.build("dsm", seg, tolerance=tol, placement=placement)
        T = np.asarray(rep.eval([0] * 6 + [1], [0.0, 0.3 - 1e-9, 0.3, 0.4, 0.5, 7.0, 0.4]))
        np.testing.assert_array_equal(T[[0, 1, 6]], 1.0)
        np.testing.assert_allclose(T, [1, 1, 0.5, 0.5, 0.1, 0.1, 1], atol=atol)
        assert rep.node_counts.tolist() == [4, 0]


def test_empty_maps_and_storage():
    seg = ad.Segments.from_arrays([0, 0, 0, 0], [], [], transmittance=[])
    rep = ad.build("dsm", seg, tolerance=0.01)
    assert rep.node_counts.tolist() == [0, 0, 0]
    assert rep.nbytes_per_texel == 4
    np.testing.assert_array_equal(np.asarray(rep.eval([0, 1, 2], [0.0, 0.5, 1e9])), 1.0)
    for dtype, item in (("float32", 4), ("float64", 8)):
        seg = ad.Segments.from_arrays([0, 1, 1, 3], [0.1, 0.2, 0.5], [0.4, 0.2, 0.6],
                                      transmittance=[0.5, 0.5, 0.9], dtype=dtype)
        rep = ad.build("dsm", seg, tolerance=0.01)
        assert rep.nbytes_per_texel == pytest.approx(rep.node_counts.mean() * 2 * item + 4)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31 - 1), tol=st.sampled_from([0.3, 0.03, 0.003]),
       placement=st.sampled_from(PLACEMENTS))
def test_property_error_bound(seed, tol, placement):
    rng = np.random.default_rng(seed)
    data = random_segments(rng, texels=4, max_count=25, opaque_fraction=0.15, zero_fraction=0.3,
                           empty_fraction=0.1)
    check_error_bound(data, "float32", placement, tol)


# ----------------------------------------------------------------------------
# the bound at the float resolution: curves that drop within an ulp
# ----------------------------------------------------------------------------
def ulp_depths(z0, z1, dtype, ulps=6):
    """dense_depths plus the first ``ulps`` representable depths after every breakpoint
    (where a sub-ulp opaque segment drops)."""
    d = dense_depths(z0, z1, dtype).astype(dtype)
    bps = np.unique(np.r_[z0, z1]).astype(dtype)
    more = [bps]
    for _ in range(ulps):
        more.append(np.nextafter(more[-1], dtype(np.inf)))
    d = np.r_[d, np.concatenate(more)]
    d[np.abs(d) < np.finfo(dtype).tiny] = 0      # eval reads subnormal depths as 0 (Segments)
    return np.unique(d).astype(np.float64)


def check_bound_at_ulps(data, dtype, placement, tol):
    """|DSM - V| <= tol + slack at dense depths and every few ulps after a breakpoint, V
    the float64 direct sum over the stored (dtype-rounded) segments at the same depths."""
    seg = make_seg(data, dtype)
    h = seg.numpy()
    rep = ad.build("dsm", seg, tolerance=tol, placement=placement)
    np_dt = np.float32 if dtype == "float32" else np.float64
    for t in range(seg.n_texels):
        s = slice(h["offsets"][t], h["offsets"][t + 1])
        if s.stop == s.start:
            continue
        d = ulp_depths(h["z0"][s], h["z1"][s], np_dt)
        T = np.asarray(rep.eval(np.full(d.size, t), d), np.float64)
        V = dsm_ref.exact_curve(h["z0"][s], h["z1"][s], h["optical_depth"][s], d)
        err = np.abs(T - V)
        assert err.max() <= tol + SLACK[dtype], (dtype, placement, t, err.max(), d[err.argmax()])


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("placement", PLACEMENTS)
def test_opaque_segment_shorter_than_an_ulp_of_its_depth(placement, dtype):
    """An opaque segment of [1, 1.00005] (float32: 420 ulps, the curve drops within the
    first) and [1e6, 1e6 + 4] (float32: 64 ulps): every level crossing rounded onto z0
    used to be dropped, leaving the chord from (z0, 1) to (z1, 0) (T = 0.8 / 0.6 / 0.2 at
    1.00001 / 1.00002 / 1.00004, exact 0).  Float64: [1e6, 1e6 + 1e-9] (9 ulps)."""
    tol = 0.01
    cases = [(1.0, 1.00005, [1.00001, 1.00002, 1.00004]), (1e6, 1e6 + 4, [1e6 + 0.5, 1e6 + 2])]
    if dtype == "float64":
        cases.append((1e6, 1e6 + 1e-9, [1e6 + 2.5e-10, 1e6 + 5e-10]))
    for z0, z1, depths in cases:
        data = _pack([([z0], [z1], [1e4])])
        rep = ad.build("dsm", make_seg(data, dtype), tolerance=tol, placement=placement)
        T = np.asarray(rep.eval([0] * len(depths), depths))
        assert np.all(T <= tol), (z0, T)
        check_bound_at_ulps(data, dtype, placement, tol)


def _adversarial_texel():
    """1-3 segments at one depth offset (up to 3e7, beyond float32's integer range):
    lengths from 0 to a few units down to sub-ulp, optical depths up to opaque."""
    seg = st.tuples(st.floats(0, 4), st.sampled_from([0.0, 1e-12, 1e-9, 1e-7, 1e-5, 1e-3, 0.1, 4.0]),
                    st.floats(0, 1), st.sampled_from([0.0, 1e-3, 0.5, 5.0, 60.0, 1e4]))
    return st.tuples(st.sampled_from([0.0, -1.0, 1.0, 1e3, 1e6, -1e6, 3e7]),
                     st.lists(seg, min_size=1, max_size=3))


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(texels=st.lists(_adversarial_texel(), min_size=1, max_size=3),
       dtype=st.sampled_from(DTYPES), placement=st.sampled_from(PLACEMENTS),
       tol=st.sampled_from([0.1, 0.01, 1e-3]))
def test_property_error_bound_adversarial_texels(texels, dtype, placement, tol):
    """|DSM - V| <= tolerance for tiny segments at large offsets and opaque ones, in both
    dtypes, at dense depths and every ulp just after each breakpoint."""
    packed = []
    for offset, segs in texels:
        z0 = [offset + a for a, _, _, _ in segs]
        z1 = [offset + a + length * u for a, length, u, _ in segs]
        packed.append((z0, z1, [tau for *_, tau in segs]))
    check_bound_at_ulps(_pack(packed), dtype, placement, tol)


# ----------------------------------------------------------------------------
# gradients (placement='curve': node values on the exact curve, depths held fixed)
# ----------------------------------------------------------------------------
def test_curve_gradients_match_finite_differences(rng):
    """d/dtau of sum_k w_k DSM(z_k) with the node depths fixed, vs central differences of
    the same fixed-layout function evaluated by the reference in float64 (eps = 1e-6,
    atol 1e-7: truncation O(eps^2) plus cancellation ~1e-16 / eps)."""
    F64 = backend.types().Float64
    data = random_segments(rng, texels=8, max_count=12, opaque_fraction=0.0, zero_fraction=0.25,
                           empty_fraction=0.1)
    tex = np.repeat(np.arange(8), 10)
    depth = rng.uniform(0, 1, tex.size)
    w = rng.normal(size=tex.size)
    t = F64(data["tau"])
    dr.enable_grad(t)
    seg = ad.Segments.from_arrays(data["offsets"], data["z0"], data["z1"], optical_depth=t)
    rep = ad.build("dsm", seg, tolerance=0.01, placement="curve")
    assert rep.differentiable
    T = rep.eval(tex, depth)
    loss = dr.sum(T * F64(w))
    dr.backward(loss)
    g = dr.grad(t).numpy()

    def fixed_layout(tau):
        out = 0.0
        for k, (tx, d) in enumerate(zip(tex, depth)):
            s = slice(data["offsets"][tx], data["offsets"][tx + 1])
            z, _ = rep.nodes_numpy(tx)
            left = rep.node_left[rep.node_offsets[tx]:rep.node_offsets[tx + 1]]
            v = [np.exp(-dsm_ref.optical_depth(data["z0"][s], data["z1"][s], tau[s], zi, left=li))
                 for zi, li in zip(z, left)]
            out += w[k] * dsm_ref.evaluate_nodes(z, np.asarray(v), d)
        return out

    assert fixed_layout(data["tau"]) == pytest.approx(loss[0], abs=1e-12)   # same primal
    eps = 1e-6
    for j in rng.choice(data["tau"].size, size=10, replace=False):
        tp, tm = data["tau"].copy(), data["tau"].copy()
        tp[j] += eps
        tm[j] -= eps
        fd = (fixed_layout(tp) - fixed_layout(tm)) / (2 * eps)
        assert abs(g[j] - fd) < 1e-7, (j, g[j], fd)
    assert np.any(np.abs(g) > 1e-3)
    # forward mode along a random direction agrees with reverse mode
    direction = rng.normal(size=data["tau"].size)
    t2 = F64(data["tau"])
    dr.enable_grad(t2)
    seg2 = ad.Segments.from_arrays(data["offsets"], data["z0"], data["z1"], optical_depth=t2)
    loss2 = dr.sum(ad.build("dsm", seg2, tolerance=0.01, placement="curve").eval(tex, depth) * F64(w))
    dr.set_grad(t2, F64(direction))
    dr.forward_to(loss2)
    np.testing.assert_allclose(dr.grad(loss2)[0], np.dot(g, direction), rtol=1e-9, atol=1e-12)


def test_midslope_is_marked_not_differentiable(rng):
    seg = make_seg(random_segments(rng, texels=4, max_count=5), "float32")
    assert not ad.build("dsm", seg).differentiable
    assert ad.build("dsm", seg, placement="curve").differentiable


def test_midslope_gradient_request_names_the_differentiable_option():
    """dr.backward through a midslope DSM gave Dr.Jit's generic 'does not depend on the
    input' message; it now says why and names placement='curve' (forward mode too)."""
    F = backend.types().Float
    t = F([1.0, 0.5])
    dr.enable_grad(t)
    seg = ad.Segments.from_arrays([0, 2], [0.0, 0.4], [0.5, 0.9], optical_depth=t)
    T = ad.build("dsm", seg).eval([0, 0], [0.3, 0.7])
    np.testing.assert_allclose(np.asarray(T), np.asarray(ad.build("dsm", make_seg(
        _pack([([0.0, 0.4], [0.5, 0.9], [1.0, 0.5])]), "float32")).eval([0, 0], [0.3, 0.7])))
    with pytest.raises(ValueError, match="^placement: 'midslope'.*placement='curve'"):
        dr.backward(dr.sum(T))
    dr.set_grad(t, F([1.0, 1.0]))
    with pytest.raises(ValueError, match="^placement:"):
        dr.forward_to(ad.build("dsm", seg).eval([0], [0.3]))


def test_polyline_beyond_the_memory_budget_is_refused(monkeypatch):
    """tolerance=1e-9 on texels that go opaque: 44,727 levels, ~2.9 MB per texel (a 256^2
    map would need ~190 GB).  The bound 2 B + crossings is checked before allocating; the
    message names the tolerance that fits, and that tolerance builds."""
    from avsm_dr.representations import _dsm_polyline
    T = 64
    seg = ad.Segments.from_arrays(np.arange(T + 1), np.zeros(T), np.ones(T), optical_depth=np.full(T, 30.0))
    monkeypatch.setattr(_dsm_polyline, "MEMORY_BUDGET_BYTES", 64 * 20_000 * _dsm_polyline.BYTES_PER_VERTEX)
    with pytest.raises(ValueError, match=r"^tolerance: 1e-09 needs a polyline of up to [\d,]+ vertices") as e:
        ad.build("dsm", seg, tolerance=1e-9)
    fits = float(str(e.value).split("tolerance >= ")[1].split(" fits")[0])
    rep = ad.build("dsm", seg, tolerance=fits * 1.1)
    assert rep.n_polyline_vertices.sum() * _dsm_polyline.BYTES_PER_VERTEX <= _dsm_polyline.MEMORY_BUDGET_BYTES
    assert _dsm_polyline.transmittance_levels(0.25e-9).size == 44727


# ----------------------------------------------------------------------------
# bad input
# ----------------------------------------------------------------------------
@pytest.mark.parametrize("kwargs, name", [
    (dict(tolerance=0.0), "tolerance"),
    (dict(tolerance=-0.01), "tolerance"),
    (dict(tolerance=float("nan")), "tolerance"),
    (dict(tolerance=float("inf")), "tolerance"),
    (dict(tolerance="small"), "tolerance"),
    (dict(tolerance=None), "tolerance"),
    (dict(tolerance=1e-12), "tolerance"),
    (dict(tolerance=0.01, placement="vertices"), "placement"),
])
def test_bad_parameters(kwargs, name):
    seg = ad.Segments.from_arrays([0, 1], [0.3], [0.4], transmittance=[0.5])
    with pytest.raises(ValueError, match=name):
        ad.build("dsm", seg, **kwargs)


def test_bad_segments_argument():
    with pytest.raises(ValueError, match="segments"):
        ad.build("dsm", "not segments", tolerance=0.01)

"""Segments: CSR packing, conversions and boundary validation."""
import numpy as np
import pytest

import avsm_dr as ad
import drjit as dr
from avsm_dr import backend


def make(**over):
    args = dict(offsets=[0, 2, 3], z0=[0.1, 0.2, 0.0], z1=[0.3, 0.2, 0.5], transmittance=[0.5, 0.0, 1.0])
    args.update(over)
    return ad.Segments.from_arrays(**args)


def test_basic_properties():
    seg = make()
    assert seg.n_texels == 2 and seg.n_segments == 3 and seg.max_count == 2
    np.testing.assert_array_equal(seg.counts, [2, 1])
    # opaque transmittance 0 becomes the finite opaque optical depth, 1 becomes 0
    np.testing.assert_allclose(np.asarray(seg.optical_depth), [np.log(2), ad.OPAQUE_OPTICAL_DEPTH, 0.0], rtol=1e-6)
    assert seg.bounds() == (0.0, 0.5)
    near, far = seg.texel_bounds()
    np.testing.assert_allclose(near, [0.1, 0.0]) and np.testing.assert_allclose(far, [0.3, 0.5])


@pytest.mark.parametrize("over, name", [
    (dict(offsets=[]), "offsets"),
    (dict(offsets=[[0, 2, 3]]), "offsets"),
    (dict(offsets=[1, 2, 3]), "offsets"),
    (dict(offsets=[0, 3, 2]), "offsets"),
    (dict(offsets=[0, 2, 4]), "z0"),
    (dict(z0=[0.1, np.nan, 0.0]), "z0"),
    (dict(z1=[0.3, np.inf, 0.5]), "z1"),
    (dict(z1=[0.05, 0.2, 0.5]), "z1"),
    (dict(transmittance=[0.5, 1.5, 1.0]), "transmittance"),
    (dict(transmittance=[0.5, -0.1, 1.0]), "transmittance"),
    (dict(transmittance=[0.5, np.nan, 1.0]), "transmittance"),
    (dict(transmittance=[0.5, 1.0]), "transmittance"),
    (dict(transmittance=None, optical_depth=[1.0, -1.0, 0.0]), "optical_depth"),
    (dict(transmittance=None, optical_depth=[1.0, np.nan, 0.0]), "optical_depth"),
    (dict(optical_depth=[1.0, 1.0, 0.0]), "transmittance"),
    (dict(dtype="float16"), "dtype"),
])
def test_bad_input_names_the_argument(over, name):
    with pytest.raises(ValueError, match=name):
        make(**over)


def test_no_segments_is_valid():
    seg = ad.Segments.from_arrays([0, 0, 0], [], [], transmittance=[])
    assert seg.n_segments == 0
    T = ad.build("exact", seg).eval([0, 1], [0.5, 2.0])
    np.testing.assert_array_equal(np.asarray(T), [1.0, 1.0])


def test_sorted_keeps_gradients():
    Float = backend.types().Float
    tau = Float([0.1, 0.2, 0.3, 0.4])
    dr.enable_grad(tau)
    seg = ad.Segments.from_arrays([0, 3, 4], [0.5, 0.1, 0.3, 0.2], [0.6, 0.2, 0.4, 0.3], optical_depth=tau)
    s = seg.sorted()
    np.testing.assert_allclose(np.asarray(s.z0), [0.1, 0.3, 0.5, 0.2])
    dr.backward(dr.sum(s.optical_depth * Float([1, 2, 3, 4])))
    np.testing.assert_allclose(dr.grad(tau).numpy(), [3, 1, 2, 4])


def test_drjit_float64_input_selects_float64():
    F64 = backend.types().Float64
    seg = ad.Segments.from_arrays([0, 1], F64([0.0]), F64([1.0]), optical_depth=F64([0.5]))
    assert seg.dtype == "float64" and type(seg.z0) is F64


# ----------------------------------------------------------------------------
# the storage dtype's range, subnormals, texel selection
# ----------------------------------------------------------------------------
def _run(code):
    import subprocess
    import sys
    return subprocess.run([sys.executable, "-c", "import avsm_dr as ad\n" + code], capture_output=True,
                          text=True, timeout=600)


def test_float32_overflow_is_refused_before_any_kernel_runs():
    """z1 = 1e39 is finite in float64 but inf in the float32 storage: dsm then segfaulted
    ("double free or corruption"); now from_arrays refuses it.  In a subprocess: a
    regression would kill the test process."""
    p = _run("seg = ad.Segments.from_arrays([0, 1], [0.0], [1e39], optical_depth=[1.0])\n"
             "ad.build('dsm', seg)\n")
    assert p.returncode == 1, p.stderr[-500:]
    assert p.stderr.strip().splitlines()[-1].startswith("ValueError: z1: 1e+39 overflows the float32"), p.stderr


@pytest.mark.parametrize("over, name", [
    (dict(z1=[0.3, 0.2, 1e39]), "z1"),
    (dict(z0=[-1e39, 0.2, 0.0]), "z0"),
    (dict(z0=[-3e38, 0.2, 0.0], z1=[0.3, 0.2, 3e38]), "z1"),          # range 6e38 overflows
])
def test_values_beyond_float32_are_refused(over, name):
    with pytest.raises(ValueError, match=f"^{name}: .*float32"):
        make(**over)
    make(**over, dtype="float64")                                     # fine in float64


def test_optical_depth_beyond_float32_is_opaque():
    seg = make(transmittance=None, optical_depth=[1e39, 1.0, 0.5])
    np.testing.assert_allclose(np.asarray(seg.optical_depth), [ad.OPAQUE_OPTICAL_DEPTH, 1.0, 0.5])


def test_check_depth_against_the_storage():
    seg = make()
    assert seg.check_depth(2.0, "far") == 2.0
    np.testing.assert_array_equal(seg.check_depth([1.0, 1e-40], "depth"), [1.0, 0.0])   # subnormal -> 0
    for bad in (1e39, -1e39, np.inf, np.nan):
        with pytest.raises(ValueError, match="^far:"):
            seg.check_depth(bad, "far")
    with pytest.raises(ValueError, match="^far: the range"):
        seg.check_depth_range(-3e38, 3e38)
    assert seg.check_depth_range(-1e38, 1e38) == (-1e38, 1e38)
    assert make(dtype="float64").check_depth(1e39, "far") == 1e39


@pytest.mark.parametrize("kind, params, name", [
    ("fom", dict(far=1e39), "far"), ("osm", dict(near=-1e39), "near"), ("moments", dict(far=1e39), "far"),
    ("basis", dict(near=-3e38, far=3e38), "far"), ("avsm", dict(near=-1e39), "near"),
])
def test_near_far_beyond_the_storage_are_refused(kind, params, name):
    """fom/osm gave T = 1 everywhere with far = 1e39."""
    with pytest.raises(ValueError, match=f"^{name}:"):
        ad.build(kind, make(), **params)


@pytest.mark.parametrize("kind", ["exact", "avsm", "dsm", "osm", "fom"])
def test_receiver_depth_beyond_the_storage_is_refused(kind):
    """avsm gave NaN at depth -1e39 (inf in float32)."""
    rep = ad.build(kind, make())
    with pytest.raises(ValueError, match="^depth:"):
        rep.eval([0], [-1e39])


def test_subnormal_depths_are_stored_as_zero():
    """Dr.Jit's worker threads flush subnormals, the calling thread does not: a receiver
    at -1.4e-45 behind a step at 0 got T = 1 alone and T = 0.61 in a batch of 16.  Depths
    below the dtype's smallest normal number are read as 0 everywhere."""
    seg = ad.Segments.from_arrays([0, 2], [1e-40, 0.0], [2e-40, 0.0], optical_depth=[0.25, 0.5])
    np.testing.assert_array_equal(np.asarray(seg.z0), [0.0, 0.0])
    np.testing.assert_array_equal(np.asarray(seg.z1), [0.0, 0.0])
    rep = ad.build("exact", seg)
    for n in (1, 8, 16, 100):
        T = np.asarray(rep.eval(np.zeros(n, int), np.full(n, -1.4e-45)))
        np.testing.assert_allclose(T, np.exp(-0.75), rtol=1e-6)
    F = backend.types().Float
    T = np.asarray(rep.eval(np.zeros(20, int), F(np.full(20, -1.4e-45, np.float32))))
    np.testing.assert_allclose(T, np.exp(-0.75), rtol=1e-6)


@pytest.mark.parametrize("texels", [[-1], [-2], [2], [0, 5], [0.5], [], [[0, 1]], [np.nan]])
def test_select_texels_refuses_bad_indices(texels):
    """[-2] returned texel 0's count with texel 1's segments; [-1] claimed 2 segments
    with empty arrays; [] made a zero-texel map that osm rejected with 'incompatible sizes'."""
    with pytest.raises(ValueError, match="^texels:"):
        make().select_texels(texels)


def test_select_texels_keeps_order_and_repeats():
    seg = make().select_texels([1, 0, 1])
    np.testing.assert_array_equal(seg.counts, [1, 2, 1])
    np.testing.assert_allclose(np.asarray(seg.z0), [0.0, 0.1, 0.2, 0.0])
    T = np.asarray(ad.build("osm", seg).eval([0, 1, 2], [1.0, 1.0, 1.0]))
    np.testing.assert_allclose(T, [1.0, 0.0, 1.0], atol=1e-6)


def test_float64_lengths_whose_density_overflows_become_steps():
    """[0, 2.3e-308] with optical depth 1e4 in float64: density 4e311 = inf made NaN DSM
    slopes and a segfault.  Lengths below MIN_LENGTH (only near depth 0) are stored as
    zero-length steps; every kind then agrees with exact.  In a subprocess."""
    p = _run("import numpy as np\n"
             "seg = ad.Segments.from_arrays([0, 2], [0.0, 0.0], [2.3e-308, 1e-296], optical_depth=[1e4, 1e4],"
             " dtype='float64')\n"
             "assert np.asarray(seg.z1).tolist() == [0.0, 0.0]\n"
             "for kind in ('exact', 'dsm', 'avsm', 'osm', 'fom'):\n"
             "    T = np.asarray(ad.build(kind, seg).eval([0, 0, 0], [-1.0, 0.0, 1.0]))\n"
             "    assert T[[0, 2]].tolist() == [1.0, 0.0], (kind, T)   # basis kinds: T(near) = 1\n"
             "    assert kind in ('osm', 'fom') or T[1] == 0.0, (kind, T)\n"
             "print('ok')\n")
    assert p.returncode == 0 and p.stdout.strip() == "ok", p.stderr[-800:]
    assert ad.segments.MIN_LENGTH < 1e-294


def test_offsets_beyond_uint32_are_refused():
    """offsets[-1] = 1e20 overflowed int64 silently and blamed z0's length."""
    with pytest.raises(ValueError, match="^offsets: .*2\\^32"):
        ad.Segments.from_arrays([0, 1e20], [0.0], [1.0], optical_depth=[1.0])


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_texel_bounds_match_host_reduction(dtype):
    """The device loop of texel_bounds equals a host min/max reduction exactly (min and max
    round nothing): random texels, empty ones, single segments, equal depths, negative and
    large depths, a texel of 300 segments."""
    rng = np.random.default_rng(5)
    counts = np.concatenate([rng.integers(0, 12, 500), [0, 1, 0, 300, 1, 0]])
    off = np.concatenate([[0], np.cumsum(counts)])
    n = int(off[-1])
    z0 = rng.uniform(-1e6, 1e6, n) * rng.choice([1e-6, 1.0], n)
    z0[:40] = 7.0                                   # ties
    z1 = z0 + rng.exponential(1.0, n) * rng.integers(0, 2, n)   # half zero-length
    seg = ad.Segments.from_arrays(off, z0, z1, optical_depth=rng.uniform(0, 2, n), dtype=dtype)
    h = seg.numpy()
    nz = counts > 0
    want_near, want_far = np.zeros(counts.size), np.ones(counts.size)
    want_near[nz] = np.minimum.reduceat(h["z0"], off[:-1][nz])
    want_far[nz] = np.maximum.reduceat(h["z1"], off[:-1][nz])
    near, far = seg.texel_bounds()
    assert near.dtype == far.dtype == np.float64
    np.testing.assert_array_equal(near, want_near)
    np.testing.assert_array_equal(far, want_far)


def test_drop_cache_makes_the_next_build_recompute_what_it_cached(monkeypatch):
    """greedy caches the exact curve's points and its removal order on the segments: a second
    build reuses them, a build after drop_cache computes them again; the layout (device
    offsets) is kept unless ``keep`` says otherwise; every key a build caches is a CACHE_KEYS
    name; an unknown ``keep`` key is a ValueError naming ``keep``."""
    from avsm_dr import segments
    from avsm_dr.representations import _curve, greedy
    points, ranks = [], []
    real_points, real_rank = _curve.curve_points, greedy.vw_removal_rank
    monkeypatch.setattr(_curve, "curve_points", lambda seg: points.append(1) or real_points(seg))
    monkeypatch.setattr(greedy, "vw_removal_rank", lambda *a: ranks.append(1) or real_rank(*a))
    seg = make(transmittance=[0.5, 0.2, 0.7])
    seg.offsets_dr()                                            # a layout array, cached
    first = np.asarray(ad.build("greedy", seg, nodes=2).eval([0, 1], [0.25, 0.4]))
    once = len(ranks)                                           # one call per bucket of point counts
    assert len(points) == 1 and once > 0 and {"curve_points", "vw_removal_rank", "offsets"} <= set(seg._cache)
    ad.build("greedy", seg, nodes=4)
    assert (len(points), len(ranks)) == (1, once)               # reused
    assert seg.drop_cache() is seg and set(seg._cache) <= set(segments.LAYOUT_KEYS) and "offsets" in seg._cache
    again = np.asarray(ad.build("greedy", seg, nodes=2).eval([0, 1], [0.25, 0.4]))
    assert (len(points), len(ranks)) == (2, 2 * once)           # recomputed, same result
    np.testing.assert_array_equal(again, first)
    for kind in ad.kinds():
        ad.build(kind, seg)
    assert set(seg._cache) <= set(segments.CACHE_KEYS) and {"bounds", "curve_points"} <= set(seg._cache)
    assert set(seg.drop_cache(keep="bounds")._cache) == {"bounds"}
    assert seg.drop_cache(keep=())._cache == {}
    for bad in ("texels", ["offsets", "nope"], None):
        with pytest.raises(ValueError, match="^keep: expected one of"):
            seg.drop_cache(keep=bad)


@pytest.mark.parametrize("high", [1, 300, 70000])
@pytest.mark.parametrize("descending", [False, True])
def test_order_by_count_is_numpys_stable_argsort(high, descending):
    # 16-bit radix keys where the counts' range fits, int64 beyond it (high = 70000)
    from avsm_dr._arrays import order_by_count
    rng = np.random.default_rng(high)
    for c in (rng.integers(0, high + 1, 5000), np.full(7, high), np.array([high, 0, high, 0]), np.zeros(0, int)):
        want = np.argsort(-c if descending else c, kind="stable")
        np.testing.assert_array_equal(order_by_count(c, descending), want)


def test_device_sortable_matches_the_float_sum_and_counts_are_cached():
    from avsm_dr.segments import DEVICE_SORT_WORK, device_sortable
    rng = np.random.default_rng(3)
    for c in (rng.integers(0, 600, 1000), np.array([0]), np.array([2**31, 1]), np.zeros(0, int)):
        x = c.astype(np.float64)
        assert device_sortable(c) == (float(x @ x) <= DEVICE_SORT_WORK * max(float(x.sum()), 1.0))
    seg = ad.Segments.from_arrays([0, 2, 2, 5], np.zeros(5), np.ones(5), optical_depth=np.ones(5))
    assert seg.counts is seg.counts and not seg.counts.flags.writeable
    np.testing.assert_array_equal(seg.counts, [2, 0, 3])

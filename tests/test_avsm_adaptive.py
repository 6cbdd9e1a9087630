"""Adaptive AVSM under a byte budget against its float64 reference
(tests/reference/avsm_adaptive_ref.py): the allocation, the per-texel AVSM with its own
N, the compacted storage and its bytes; the budget is never exceeded."""
import numpy as np
import pytest

import avsm_dr as ad
from avsm_dr.representations import avsm_adaptive as AA
from cases import random_segments, to_segments
from reference import avsm_adaptive_ref as ref


@pytest.mark.parametrize("budget", [24.0, 40.0, 72.0, 160.0])
def test_allocation_matches_reference(rng, budget):
    data = random_segments(rng, texels=120, max_count=25)
    seg = to_segments(data, "float64")
    w = AA.complexity(seg, "complexity")
    np.testing.assert_allclose(w, ref.complexity(data["offsets"], data["z0"], data["z1"],
                                                 np.minimum(data["tau"], ad.OPAQUE_OPTICAL_DEPTH)), rtol=1e-12)
    T = seg.n_texels
    nodes = int((budget * T - 4 * (T + 1)) // 8)
    if nodes < 2 * np.count_nonzero(seg.counts):
        with pytest.raises(ValueError, match="^bytes_per_texel:"):
            ad.build("avsm_adaptive", seg, bytes_per_texel=budget)
        return
    got = AA.allocate(seg.counts, w, nodes, 32)
    want = ref.allocate(seg.counts, w, nodes, 32)
    np.testing.assert_array_equal(got, want)
    assert got.sum() <= nodes
    assert np.all(got[seg.counts == 0] == 0) and np.all(got[seg.counts > 0] >= 2)
    assert np.all(got <= np.maximum(2 * seg.counts, 0)) and np.all(got <= 32)


@pytest.mark.parametrize("dtype, budget, max_nodes, sort, mode", [
    ("float64", 48.0, 32, False, "linear"),
    pytest.param("float64", 120.0, 12, True, "exp", marks=pytest.mark.slow),
    pytest.param("float32", 40.0, 64, False, "linear", marks=pytest.mark.slow)])
def test_build_matches_reference(rng, dtype, budget, max_nodes, sort, mode):
    data = random_segments(rng, texels=60, max_count=20)
    seg = to_segments(data, dtype)
    rep = ad.build("avsm_adaptive", seg, bytes_per_texel=budget, max_nodes=max_nodes, sort=sort,
                   interpolation=mode)
    h = seg.numpy()       # the stored (rounded) segments
    alloc, nodes, nbytes = ref.build(h["offsets"], h["z0"], h["z1"], h["optical_depth"], budget, seg.itemsize,
                                     max_nodes, sort)
    np.testing.assert_array_equal(rep.allocated, alloc)
    assert rep.nbytes_per_texel == pytest.approx(nbytes, rel=1e-15)
    assert rep.nbytes_per_texel <= budget
    np.testing.assert_array_equal(rep.node_counts, [d.size for d, _ in nodes])
    depths = np.linspace(-0.1, 1.25, 37)
    tex = np.repeat(np.arange(60), depths.size)
    got = np.asarray(rep.eval(tex, np.tile(depths, 60)), np.float64).reshape(60, -1)
    want = np.array([[ref.sample(nodes, t, x, mode) for x in depths] for t in range(60)])
    # float64: same operations up to order; float32: one rounding per node product (~1e-6 over 20 segments)
    np.testing.assert_allclose(got, want, atol=1e-12 if dtype == "float64" else 2e-5)


@pytest.mark.slow
def test_groups_equal_fixed_avsm_per_texel(rng):
    """Each texel's lookup equals AVSM-N's with N its kernel (the same kernel, bit for bit)."""
    data = random_segments(rng, texels=80, max_count=30)
    seg = to_segments(data)
    rep = ad.build("avsm_adaptive", seg, bytes_per_texel=96.0)
    assert len(rep.groups) >= 3
    d = np.linspace(-0.1, 1.2, 41)
    for N, tex in rep.groups.items():
        t = np.repeat(tex, d.size)
        a = np.asarray(ad.build("avsm", seg, nodes=N).eval(t, np.tile(d, tex.size)))
        b = np.asarray(rep.eval(t, np.tile(d, tex.size)))
        np.testing.assert_array_equal(a, b)


def test_uniform_score_is_fixed_n_with_compaction(rng):
    """_score='uniform' gives every non-empty texel min(N, 2c): AVSM-N's curves with
    CSR storage (empty texels and texels that fit cost no node slots)."""
    data = random_segments(rng, texels=64, max_count=20, empty_fraction=0.4)
    seg = to_segments(data)
    rep = ad.build("avsm_adaptive", seg, bytes_per_texel=40.0, _score="uniform")
    N = int(rep.allocated.max())
    c = seg.counts
    np.testing.assert_array_equal(rep.allocated, np.where(2 * c <= N, 2 * c, N))
    d = np.linspace(0, 1, 23)
    t = np.repeat(np.arange(64), d.size)
    np.testing.assert_array_equal(np.asarray(rep.eval(t, np.tile(d, 64))),
                                  np.asarray(ad.build("avsm", seg, nodes=N).eval(t, np.tile(d, 64))))


def test_error_falls_with_budget_and_complex_texels_get_more(rng):
    """Against AVSM without compression (N = 32 >= 2c for every texel): the error falls
    as the budget grows and is 0 once every texel fits; the stored bytes grow with it."""
    data = random_segments(rng, texels=100, max_count=16, empty_fraction=0.3)
    seg = to_segments(data, "float64")
    d = np.linspace(0, 1, 40)
    t, x = np.repeat(np.arange(100), d.size), np.tile(d, 100)
    full = np.asarray(ad.build("avsm", seg, nodes=32).eval(t, x))
    errs, used = [], []
    for b in (32.0, 64.0, 128.0, 400.0):
        rep = ad.build("avsm_adaptive", seg, bytes_per_texel=b)
        errs.append(np.sqrt(np.mean((np.asarray(rep.eval(t, x)) - full) ** 2)))
        used.append(rep.nbytes_per_texel)
        assert rep.nbytes_per_texel <= b
    assert errs[0] > errs[1] > errs[2] > 0 and errs[3] == 0
    assert used == sorted(used)
    rep = ad.build("avsm_adaptive", seg, bytes_per_texel=64.0)
    w = AA.complexity(seg, "complexity")
    nz = seg.counts > 0
    # the allocation follows the score (rank correlation over non-empty texels clearly positive)
    r = np.corrcoef(np.argsort(np.argsort(w[nz])), np.argsort(np.argsort(rep.allocated[nz])))[0, 1]
    assert r > 0.5


def test_budget_errors_and_empty_map():
    seg = ad.Segments.from_arrays([0, 3, 3, 5], [0.1, 0.2, 0.3, 0.1, 0.5], [0.2, 0.4, 0.6, 0.3, 0.9],
                                  optical_depth=[0.5, 1.0, 0.2, 0.3, 2.0])
    # 3 texels: 16 bytes of offsets, 2 non-empty texels x 2 nodes x 8 bytes (float32)
    least = (16 + 2 * 2 * 8) / 3
    with pytest.raises(ValueError, match="^bytes_per_texel: .* below"):
        ad.build("avsm_adaptive", seg, bytes_per_texel=least - 0.5)
    rep = ad.build("avsm_adaptive", seg, bytes_per_texel=least)
    assert rep.nbytes_per_texel == pytest.approx(least)
    for bad in (7.9, True, "64", float("nan")):
        with pytest.raises(ValueError, match="^bytes_per_texel:"):
            ad.build("avsm_adaptive", seg, bytes_per_texel=bad)
    with pytest.raises(ValueError, match="^max_nodes:"):
        ad.build("avsm_adaptive", seg, max_nodes=1)
    empty = ad.Segments.from_arrays([0, 0, 0], [], [], optical_depth=[])
    rep = ad.build("avsm_adaptive", empty)
    assert rep.nbytes_per_texel == 6.0                               # 3 offsets / 2 texels
    np.testing.assert_array_equal(np.asarray(rep.eval([0, 1], [0.5, 2.0])), 1.0)

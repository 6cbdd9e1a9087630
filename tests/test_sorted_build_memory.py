"""Sorted AVSM and avsm_adaptive build in chunks of whole texels (``MIN_CHUNK_BYTES`` of
:mod:`avsm_dr.representations.avsm`; chunks of at least ``MIN_LANES`` non-empty texels): every
stored array equals that of a build in one piece bit for bit, whatever the insertion order, on
texels longer than one sorting network (the block merge) and with equal depths (both tie paths);
the water-filling allocation equals its reference with many equal gains; and the build peak stays
within 4x the output on the benchmark's memory map."""
import numpy as np
import pytest

import avsm_dr as ad
from avsm_dr.representations import avsm as AV
from avsm_dr.representations import avsm_adaptive as AA
from cases import random_segments
from experiments.bench.settings import counts_map
from helpers import build_peak
from reference import avsm_adaptive_ref as ref

_INSERT = AV.AVSM._insert


def _maps(rng):
    """(name, Segments): short texels (20% empty) in random order, texels of up to 200
    segments (over 64: blocks and merges) in reverse order, and z0 on 16 levels (ties)."""
    d = random_segments(rng, texels=400, max_count=30)
    yield "short", ad.Segments.from_arrays(d["offsets"], d["z0"], d["z1"], optical_depth=d["tau"]).in_order(
        "random", seed=3)
    counts = rng.integers(0, 200, 160)
    off = np.r_[0, np.cumsum(counts)]
    z0 = rng.uniform(0, 1, off[-1])
    z1 = z0 + rng.exponential(0.01, off[-1])
    tau = rng.exponential(0.05, off[-1])
    yield "long", ad.Segments.from_arrays(off, z0, z1, optical_depth=tau).in_order("reverse_depth")
    zq = np.round(z0 * 16) / 16
    yield "ties", ad.Segments.from_arrays(off, zq, zq + (z1 - z0), optical_depth=tau)
    yield "ties64", ad.Segments.from_arrays(off, zq, zq + (z1 - z0), optical_depth=tau, dtype="float64")


def _chunked(monkeypatch, on: bool) -> list:
    """Chunks of about the output's bytes (``on``) or one piece; returns the list that counts
    the AVSM insertion passes."""
    monkeypatch.setattr(AV, "MIN_CHUNK_BYTES", 0 if on else 1 << 60)
    calls = []

    def counted(self, seg, t0):
        calls.append(seg.n_texels)
        return _INSERT(self, seg, t0)
    monkeypatch.setattr(AV.AVSM, "_insert", counted)
    return calls


def _avsm(rep):
    d, v = rep.nodes_numpy()
    return dict(d=d, v=v, used=rep.used, stats=np.array(list(rep.stats.values())))


def _adaptive(rep):
    return dict(d=rep.node_depths(), v=np.asarray(rep.node_value.numpy()), off=np.asarray(rep.node_offsets),
                alloc=rep.allocated)


@pytest.mark.parametrize("kind, params, snapshot", [
    ("avsm", {"nodes": 8, "sort": True}, _avsm),
    ("avsm", {"nodes": 4, "sort": True, "interpolation": "exp", "insertion": "spare_refit_l2"}, _avsm),
    ("avsm_adaptive", {"bytes_per_texel": 64.0}, _adaptive),
    ("avsm_adaptive", {"bytes_per_texel": 96.0, "sort": True, "_score": "count"}, _adaptive),
])
def test_chunked_build_equals_one_piece(monkeypatch, rng, kind, params, snapshot):
    for name, seg in _maps(rng):
        whole = _chunked(monkeypatch, False)
        want = snapshot(ad.build(kind, seg, **params))
        calls = _chunked(monkeypatch, True)
        got = snapshot(ad.build(kind, seg, **params))
        assert len(calls) >= len(whole) + 2, (name, whole, calls)      # chunks ran
        for k in want:
            assert got[k].dtype == want[k].dtype and got[k].tobytes() == want[k].tobytes(), (name, k)


def test_allocation_with_equal_gains_matches_reference(rng):
    """The 'count' score gives every texel of one count the same gains: the bisection on the
    gain and the (texel, n) order among equal gains take the reference's steps."""
    counts = rng.integers(0, 12, 3000)
    w = AA.complexity(ad.Segments.from_arrays(np.r_[0, np.cumsum(counts)], np.zeros(counts.sum()),
                                              np.zeros(counts.sum()), optical_depth=np.ones(counts.sum())), "count")
    least = 2 * np.count_nonzero(counts)
    for nodes in (least, least + 1, least + 777, int(1.7 * least), 10 * least):
        np.testing.assert_array_equal(AA.allocate(counts, w, nodes, 16), ref.allocate(counts, w, nodes, 16))


@pytest.mark.parametrize("kind, params, arrays", [
    ("avsm", {"nodes": 8, "sort": True}, lambda r: (*r.depths, *r.values)),
    ("avsm_adaptive", {}, lambda r: (r.node_depth, r.node_value)),
])
def test_build_peak_within_4x_of_the_output(kind, params, arrays):
    """On the benchmark's memory map at its quick size (64^2 texels, ~0.4 M segments): peak
    = the larger of process RSS growth and Dr.Jit's allocator watermark growth, over
    nbytes_per_texel x texels (42x and 30x at 256^2 before the chunked builds); the chunks'
    kernels compiled outside the measurement."""
    ad.build(kind, counts_map(64, 100), **params)
    rep, m, out = build_peak(kind, arrays, **params)
    assert m.peak_bytes <= 4 * out, (m.rss_bytes, m.heap_bytes, out)

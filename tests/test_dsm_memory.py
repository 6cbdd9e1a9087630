"""DSM builds in chunks of texels (avsm_dr.representations.dsm, "Memory"): the nodes equal
those of a build in one piece bit for bit, chunks cover every texel once, the polyline
budget is summed over chunks, and the build's peak memory stays within 4x its output."""
import numpy as np
import pytest

import avsm_dr as ad
from avsm_dr import validation as V
from avsm_dr.representations import _dsm_polyline, dsm
from cases import random_segments
from helpers import build_peak

ATTRS = ("node_counts", "node_offsets", "node_left", "n_polyline_vertices")


def _one_piece(monkeypatch):
    monkeypatch.setattr(dsm, "MIN_CHUNK_SEGMENTS", 1 << 40)
    monkeypatch.setattr(dsm, "MAX_CHUNK_SEGMENTS", 1 << 40)


def _chunked(monkeypatch, n):
    monkeypatch.setattr(dsm, "MIN_CHUNK_SEGMENTS", n)
    monkeypatch.setattr(dsm, "MAX_CHUNK_SEGMENTS", n)


def _snapshot(rep):
    out = {k: np.asarray(getattr(rep, k)) for k in ATTRS}
    out["node_depth"] = np.asarray(rep.node_depth.numpy())
    out["node_value"] = np.asarray(rep.node_value.numpy())
    return out


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("placement", ["midslope", "curve"])
def test_chunked_build_equals_one_piece(monkeypatch, rng, dtype, placement):
    """Chunks of 37 segments (texels of up to 60 segments span several chunks' worth;
    empty texels fall on chunk edges): every attribute equal bit for bit."""
    data = random_segments(rng, texels=300, max_count=60, empty_fraction=0.3)
    seg = ad.Segments.from_arrays(data["offsets"], data["z0"], data["z1"], optical_depth=data["tau"], dtype=dtype)
    _one_piece(monkeypatch)
    ref = _snapshot(ad.build("dsm", seg, tolerance=0.005, placement=placement))
    _chunked(monkeypatch, 37)
    got = _snapshot(ad.build("dsm", seg, tolerance=0.005, placement=placement))
    for k in ref:
        assert got[k].dtype == ref[k].dtype and got[k].shape == ref[k].shape, k
        assert got[k].tobytes() == ref[k].tobytes(), k


def test_chunks_cover_every_texel_once():
    """chunk_end: about per_chunk segments, at least one texel (a texel larger than a
    chunk is kept whole), the last chunk ends at T."""
    offsets = np.array([0, 0, 5, 5, 40, 41, 41, 60])
    for per_chunk in (1, 4, 10, 100):
        t0, seen = 0, []
        while t0 < offsets.size - 1:
            t1 = dsm.chunk_end(offsets, t0, per_chunk)
            assert t1 > t0
            assert t1 == t0 + 1 or offsets[t1] - offsets[t0] <= per_chunk
            seen.extend(range(t0, t1))
            t0 = t1
        assert seen == list(range(offsets.size - 1))


def test_chunk_size_follows_the_output():
    """First chunk the minimum; then output estimate / TEMP_BYTES_PER_SEGMENT, clamped."""
    assert dsm.next_chunk_segments(0, 0, 10**7) == dsm.MIN_CHUNK_SEGMENTS
    per = dsm.TEMP_BYTES_PER_SEGMENT
    mid = (dsm.MIN_CHUNK_SEGMENTS + dsm.MAX_CHUNK_SEGMENTS) // 2
    assert dsm.next_chunk_segments(per * mid, 10**6, 10**6) == mid
    assert dsm.next_chunk_segments(1, 10**6, 10**6) == dsm.MIN_CHUNK_SEGMENTS
    assert dsm.next_chunk_segments(10**12, 10**3, 10**6) == dsm.MAX_CHUNK_SEGMENTS


def test_polyline_budget_is_summed_over_chunks(monkeypatch):
    """64 opaque texels at tolerance 1e-4 (~142 levels each), one texel per chunk, a budget
    for ~20 of them: the build stops at the chunk that crosses it and says how many
    texels it had reached; the same budget fits the first 10 texels alone."""
    T = 64
    seg = ad.Segments.from_arrays(np.arange(T + 1), np.zeros(T), np.ones(T), optical_depth=np.full(T, 30.0))
    _one_piece(monkeypatch)
    per_texel = int(ad.build("dsm", seg.select_texels(np.arange(1)), tolerance=1e-4).n_polyline_vertices[0])
    _chunked(monkeypatch, 1)
    monkeypatch.setattr(_dsm_polyline, "MEMORY_BUDGET_BYTES", 20 * (per_texel + 2) * _dsm_polyline.BYTES_PER_VERTEX)
    with pytest.raises(V.MemoryBudgetError, match=r"^tolerance: 0.0001 needs a polyline of up to [\d,]+ vertices over "
                                         r"the first 2\d texels"):
        ad.build("dsm", seg, tolerance=1e-4)
    rep = ad.build("dsm", seg.select_texels(np.arange(10)), tolerance=1e-4)
    assert rep.n_polyline_vertices.sum() * _dsm_polyline.BYTES_PER_VERTEX <= _dsm_polyline.MEMORY_BUDGET_BYTES


def test_build_peak_within_4x_of_the_output():
    """The issue-14 target on the benchmark's memory map at its quick size (64^2 texels,
    ~0.4 M segments; 76x in one piece): peak = the larger of process RSS growth and Dr.Jit's
    allocator watermark growth (:class:`Meter`), over nbytes_per_texel x texels."""
    rep, m, out = build_peak("dsm", lambda r: (r.node_depth, r.node_value), tolerance=0.01)
    assert m.peak_bytes <= 4 * out, (m.rss_bytes, m.heap_bytes, out)

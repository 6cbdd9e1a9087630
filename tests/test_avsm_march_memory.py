"""avsm_march builds in chunks of whole texels sized by DSM's helpers
(:func:`avsm_dr.representations.dsm.next_chunk_segments`), each of at least ``MIN_LANES``
(:mod:`avsm_dr.representations._loops`) non-empty texels: every stored array and the gradients
equal those of a build in one piece bit for bit, and the build's peak memory stays within 4x its
output on the benchmark's memory map."""
import drjit as dr
import numpy as np
import pytest

import avsm_dr as ad
from avsm_dr.representations import _loops, dsm
from cases import random_segments
from helpers import build_peak
from test_dsm import adversarial

PARAMS = ({}, {"nodes": 3}, {"nodes": 16, "abs_error": 0.0, "rel_error": 0.0, "interpolation": "linear"},
          {"precision": "float16"})


def _chunks(monkeypatch, n):
    """Chunks of about ``n`` segments and at least 17 lanes, one SIMD packet more than
    Dr.Jit runs on the calling thread (None: one piece)."""
    monkeypatch.setattr(_loops, "MIN_LANES", 17)
    n = 1 << 40 if n is None else n
    monkeypatch.setattr(dsm, "MIN_CHUNK_SEGMENTS", n)
    monkeypatch.setattr(dsm, "MAX_CHUNK_SEGMENTS", n)


def _snapshot(rep):
    out = {k: np.asarray(getattr(rep, k)) for k in ("node_counts", "node_offsets")}
    out.update({k: np.asarray(dr.detach(getattr(rep, k)).numpy()) for k in ("range_lo", "range_hi", "node_q",
                                                                            "node_value")})
    return out


def _data(name, rng):
    """random: texels of up to 60 segments, 30% empty (on chunk edges too); adversarial:
    8 copies of coincident, zero-length, opaque, steep, empty texels and one of 1500
    segments (values down to subnormals, where the area metrics tie)."""
    if name == "random":
        return random_segments(rng, texels=300, max_count=60, empty_fraction=0.3)
    parts = [adversarial(rng) for _ in range(8)]
    counts = np.concatenate([np.diff(p["offsets"]) for p in parts])
    return dict(offsets=np.r_[0, np.cumsum(counts)], **{k: np.concatenate([p[k] for p in parts])
                                                         for k in ("z0", "z1", "tau")})


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("name", ["random", "adversarial"])
def test_chunked_build_equals_one_piece(monkeypatch, rng, dtype, name):
    """Chunks of ~1, ~37 and ~500 segments (at least 17 lanes; texel ends straddle the
    nominal chunk ends; a texel larger than a chunk is kept whole): every array equal bit
    for bit."""
    d = _data(name, rng)
    seg = ad.Segments.from_arrays(d["offsets"], d["z0"], d["z1"], optical_depth=d["tau"], dtype=dtype)
    for params in PARAMS:
        _chunks(monkeypatch, None)
        ref = _snapshot(ad.build("avsm_march", seg, **params))
        for n in (1, 37, 500):
            _chunks(monkeypatch, n)
            got = _snapshot(ad.build("avsm_march", seg, **params))
            for k in ref:
                assert got[k].dtype == ref[k].dtype and got[k].shape == ref[k].shape, (params, n, k)
                assert got[k].tobytes() == ref[k].tobytes(), (params, n, k)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_chunked_gradients_equal_one_piece(monkeypatch, rng, dtype):
    """d(sum_i i v_i)/d tau of the node values: equal bit for bit in chunks of ~37 segments."""
    d = _data("random", rng)

    def grad():
        tau = ad.Segments.from_arrays([0, 1], [0.0], [1.0], optical_depth=[1.0], dtype=dtype).Float(d["tau"])
        dr.enable_grad(tau)
        seg = ad.Segments.from_arrays(d["offsets"], d["z0"], d["z1"], optical_depth=tau, dtype=dtype)
        v = ad.build("avsm_march", seg).node_value
        dr.backward(dr.sum(v * dr.arange(type(v), dr.width(v))))
        return np.asarray(dr.grad(tau).numpy())

    _chunks(monkeypatch, None)
    ref = grad()
    _chunks(monkeypatch, 37)
    got = grad()
    assert np.any(ref != 0) and got.dtype == ref.dtype and got.tobytes() == ref.tobytes()


def test_build_peak_within_4x_of_the_output():
    """On the benchmark's memory map at its quick size (64^2 texels, ~0.4 M segments): peak
    = the larger of process RSS growth and Dr.Jit's allocator watermark growth, over
    nbytes_per_texel x texels (about 340x in one piece at 256^2)."""
    rep, m, out = build_peak("avsm_march", lambda r: (r.node_q, r.node_value, r.range_lo, r.range_hi), nodes=8)
    assert m.peak_bytes <= 4 * out, (m.rss_bytes, m.heap_bytes, out)

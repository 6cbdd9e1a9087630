"""OSM builds without gradients in chunks of texels (OpacityShadowMap._build_chunked): the
slice optical depths a_k and the stored cumulative sums C_j equal, bit for bit, those of the
dense form it replaced (every texel's parts P and difference array R at full size, then
``dr.block_prefix_sum`` in float64 twice), whatever the chunk count, and the build's peak
memory stays within 4x its output (it was 7x on the benchmark's memory map)."""
from __future__ import annotations

import numpy as np
import pytest

import avsm_dr as ad
import drjit as dr
from avsm_dr import backend
from avsm_dr.representations import osm as OSM

from cases import random_segments, to_segments
from helpers import build_peak


def _dense(rep):
    """The build before the chunks: one lane per texel adds its segments' parts in CSR
    order into full-size P and R (the same :meth:`_add_parts` expressions), then
    a = P + float64 prefix sums of R, clamped at 0, and C = float64 prefix sums of a."""
    seg, n = rep.segments, rep.basis.n
    t = backend.types()
    Float, UInt32, F64 = seg.Float, t.UInt32, t.Float64
    T = seg.n_texels
    P, Rd = dr.zeros(Float, T * n), dr.zeros(Float, T * n)
    texel = t.UInt32(np.nonzero(seg.counts > 0)[0].astype(np.uint32))
    offsets = seg.offsets_dr()
    first, stop = dr.gather(UInt32, offsets, texel), dr.gather(UInt32, offsets, texel + 1)

    def body(i):
        rep._add_parts(P, Rd, dr.gather(Float, seg.z0, i), dr.gather(Float, seg.z1, i),
                       dr.gather(Float, seg.optical_depth, i), texel, texel * n, mode=dr.ReduceMode.NoConflicts)
        return (i + 1,)

    dr.while_loop((first,), lambda i: i < stop, body)
    a = P + Float(dr.block_prefix_sum(F64(Rd), n, exclusive=False))
    a = dr.select(a < 0, 0, a)
    cum = Float(dr.block_prefix_sum(F64(a), n, exclusive=False))
    return np.asarray(a.numpy()), np.asarray(cum.numpy())


def _bits(x):
    return np.asarray(x).view(np.uint8)


CASES = [
    ({"slices": 1}, "float32"),
    ({"slices": 7}, "float32"),
    ({"slices": 32}, "float32"),
    ({"slices": 300}, "float32"),
    ({"slices": 16, "depth_range": "texel"}, "float32"),
    ({"slices": 16, "near": -0.5, "far": 1.5}, "float32"),
    ({"slices": 9}, "float64"),
    ({"slices": 16, "depth_range": "texel"}, "float64"),
]


def _empty(case, lo, hi):
    """The case with texels lo .. hi - 1 emptied."""
    off = case["offsets"]
    counts = np.diff(off)
    counts[lo:hi] = 0
    idx = np.concatenate([np.arange(off[t], off[t] + counts[t]) for t in range(counts.size)])
    out = {k: case[k][idx] for k in ("z0", "z1", "tau")}
    out["offsets"] = np.concatenate([[0], np.cumsum(counts)])
    return out


@pytest.mark.parametrize("chunks", [1, 3, 4, 1000])
@pytest.mark.parametrize("params, dtype", CASES)
def test_chunked_build_equals_the_dense_form_bit_for_bit(params, dtype, chunks, monkeypatch):
    """Random texels (empty ones, zero-length and opaque segments among them; with 3 chunks
    the whole middle chunk empty): any chunk count (one, uneven, the default, more chunks
    than texels) gives the dense form's bits."""
    monkeypatch.setattr(OSM, "BUILD_CHUNKS", chunks)
    case = random_segments(np.random.default_rng(params["slices"]), texels=61, max_count=30, opaque_fraction=0.05)
    rep = ad.build("osm", to_segments(_empty(case, 21, 42), dtype), **params)
    a, cum = _dense(rep)
    np.testing.assert_array_equal(_bits(rep._coef.numpy()), _bits(a))
    np.testing.assert_array_equal(_bits(rep._cum.numpy()), _bits(cum))
    assert np.any(a > 0) and not np.any(a[21 * params["slices"]:42 * params["slices"]])


def test_build_peak_within_4x_of_the_output():
    """The benchmark's memory map at its quick size (64^2 texels, ~0.4 M segments, 32
    slices; 7.0x with every temporary at full size, 3.0x in two chunks): peak = the larger of
    process RSS growth and Dr.Jit's allocator watermark growth (:class:`Meter`), over
    nbytes_per_texel x texels; the memory check's estimate covers it."""
    rep, m, out = build_peak("osm", lambda r: (r._coef, r._cum), slices=32)
    assert m.peak_bytes <= 4 * out, (m.rss_bytes, m.heap_bytes, out)
    assert m.peak_bytes <= rep._build_bytes(32), (m.peak_bytes, rep._build_bytes(32))

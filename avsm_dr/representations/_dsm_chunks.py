"""Deep shadow maps: chunks of texels.  Phases A and B (:mod:`._dsm_polyline`,
:mod:`._dsm_compress`) run on groups of texels, so their temporaries scale with a chunk, not
the map; each chunk's nodes are then concatenated into the final arrays.  Texels are
independent, so the nodes do not depend on the chunking.
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import backend

#: Temporaries of phases A and B per segment of a chunk (bytes, host and device), and the
#: bounds of a chunk's segments (:func:`next_chunk_segments`).
TEMP_BYTES_PER_SEGMENT = 400
MIN_CHUNK_SEGMENTS = 1 << 13
MAX_CHUNK_SEGMENTS = 1 << 18


def chunk_end(offsets: np.ndarray, t0: int, per_chunk: int) -> int:
    """End ``t1`` of the chunk of texels that starts at ``t0`` and holds about ``per_chunk``
    segments (at least one texel: a texel's curve needs all of its segments)."""
    t1 = int(np.searchsorted(offsets, offsets[t0] + per_chunk, side="right")) - 1
    return min(max(t1, t0 + 1), offsets.size - 1)


def next_chunk_segments(output_bytes: float, segments_done: int, n_segments: int) -> int:
    """Segments of the next chunk: the output extrapolated from the chunks built
    (``output_bytes`` over ``segments_done`` of ``n_segments``) over
    ``TEMP_BYTES_PER_SEGMENT``, clamped to [MIN_CHUNK_SEGMENTS, MAX_CHUNK_SEGMENTS] (the
    first chunk: the minimum, below which kernel launches dominate)."""
    if segments_done <= 0:
        return MIN_CHUNK_SEGMENTS
    estimate = output_bytes * n_segments / segments_done
    return int(min(MAX_CHUNK_SEGMENTS, max(MIN_CHUNK_SEGMENTS, estimate // TEMP_BYTES_PER_SEGMENT)))


def host_range(x, s0: int, s1: int) -> np.ndarray:
    """Entries ``s0:s1`` of the Dr.Jit array ``x`` as float64 NumPy (the LLVM backend's
    ``numpy()`` is a view of its buffer; elsewhere only the range is gathered and copied)."""
    x = dr.detach(x)
    dr.eval(x)
    if dr.backend_v(x) == dr.JitBackend.LLVM:
        return np.asarray(x.numpy()[s0:s1], np.float64)
    U32 = backend.types().UInt32
    idx = dr.arange(U32, s1 - s0) + dr.opaque(U32, s0)
    return np.asarray(dr.gather(type(x), x, idx).numpy(), np.float64)


def concatenate(parts: list, k: int) -> np.ndarray:
    """Entry ``k`` of every chunk's tuple, concatenated into one 64-byte aligned array
    (:func:`avsm_dr._arrays.aligned`); each part is released once copied."""
    dtype = parts[0][k].dtype if parts else np.float64
    n = sum(p[k].size for p in parts)
    buf = np.empty(n + (64 + A.TAIL_PAD) // dtype.itemsize, dtype)
    first = (-buf.ctypes.data % 64) // dtype.itemsize
    out = buf[first:first + n]
    at = 0
    for i, p in enumerate(parts):
        out[at:at + p[k].size] = p[k]
        at += p[k].size
        parts[i] = p[:k] + (None,) + p[k + 1:]
    return out

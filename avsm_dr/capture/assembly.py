"""CSR assembly of captured content: pieces ``(texel, z0, z1, tau)`` -> :class:`Segments`.

Every content kind (grid, particles, hair, opaque blockers) yields a piece: per segment its
texel (a NumPy array, or :class:`TexelRuns` for the grid: one run per ray), depths and
optical depth (Dr.Jit or NumPy).  :func:`combine` orders each texel's segments on the device:
one grid piece is in texel and depth order already (offsets from its per-ray counts); merged
content is grouped by texel (``dr.scatter_inc`` slots, a prefix sum for the offsets) and every
texel sorted by ``(zq, concatenation index)``, ``zq`` z0 quantised to 32 bits over its range
(:func:`~avsm_dr.segments.key_order`), or by draw keys (the insertion orders: :func:`combine`).
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import backend
from ..segments import OPAQUE_OPTICAL_DEPTH, Segments, key_order, run_index


@dataclass
class TexelRuns:
    """Texels of segments stored as runs: ``counts[r]`` consecutive segments of texel
    ``texels[r]`` (``texels`` distinct and ascending, int64 NumPy; ``counts`` >= 0).
    ``np.asarray`` expands it to one texel per segment."""

    texels: np.ndarray
    counts: np.ndarray

    @property
    def size(self) -> int:
        """Number of segments."""
        return int(self.counts.sum())

    def __array__(self, dtype=None, copy=None):
        return np.repeat(self.texels.astype(np.int64), self.counts).astype(dtype or np.int64)

    def texel_counts(self, n_texels: int) -> np.ndarray:
        """(n_texels,) segments per texel."""
        c = np.zeros(n_texels, np.int64)
        c[self.texels] = self.counts
        return c

    def device(self):
        """Texel of every segment as a Dr.Jit UInt32 array, expanded on the device (the run of
        each segment by :func:`~avsm_dr.segments.run_index`)."""
        UInt32 = backend.types().UInt32
        nz = self.counts > 0
        tex, cnt = self.texels[nz], self.counts[nz]
        return dr.gather(UInt32, A.to_uint32(tex), run_index(A.to_uint32(np.cumsum(cnt[:-1])), int(cnt.sum())))


def combine(pieces, n_texels: int, Float, order: str = "depth", keys=None, seed: int | None = None) -> Segments:
    """CSR Segments from ``(texel, z0, z1, tau)`` pieces in insertion order ``order``
    (recorded as ``Segments.order``):

    * ``'depth'``: each texel's segments by ``(z0 quantised to 32 bits over the depth range,
      piece order)`` (module docstring);
    * ``'submission'``: by ``(keys, piece order)``, ``keys`` a list with one draw key per
      segment of each piece (uint32 NumPy or Dr.Jit UInt32, ``< 2^32``);
    * ``'reverse_depth'``, ``'random'`` (``seed``): the depth order reordered by
      :meth:`~avsm_dr.segments.Segments.in_order`."""
    dtype = A.dtype_of(Float)
    if not pieces:
        return Segments.from_arrays(np.zeros(n_texels + 1, np.int64), Float(), Float(),
                                    optical_depth=Float(), dtype=dtype, order=order)
    z0, z1, tau = (_concat([A.to_float(p[i], Float) for p in pieces], Float) for i in (1, 2, 3))
    key = None if order != "submission" else _concat([A.to_uint32(k) for k in keys], backend.types().UInt32)
    offsets, perm = texel_key_order([p[0] for p in pieces], key, n_texels, z0=z0)
    if perm is not None:
        z0, z1, tau = (dr.gather(Float, a, perm) for a in (z0, z1, tau))
    # every piece was validated at the boundary and is finite with z0 <= z1 and tau >= 0:
    # build the CSR directly (Segments.from_arrays would copy everything to the host again)
    tau = dr.minimum(tau, OPAQUE_OPTICAL_DEPTH)
    if order == "submission":
        return Segments(offsets, z0, z1, tau, dtype, order="submission")
    seg = Segments(offsets, z0, z1, tau, dtype, sorted_by_depth=True)
    return seg if order == "depth" else seg.in_order(order, seed)


def quantised_depth(z0):
    """``(z0 - min) * (2^32 - 1) / (max - min)`` truncated to an integer (Dr.Jit UInt64),
    computed in float64 on the device (finer than float32 depths)."""
    t = backend.types()
    z = t.Float64(dr.detach(z0))
    lo, hi = float(dr.min(z)[0]), float(dr.max(z)[0])
    scale = (2.0 ** 32 - 1) / (hi - lo) if hi > lo else 0.0
    return t.UInt64((z - dr.opaque(t.Float64, lo)) * dr.opaque(t.Float64, scale))


def texel_key_order(texels, key, n_texels: int, z0=None):
    """(offsets (T+1,) int64 NumPy, permutation Dr.Jit UInt32 (S,)) ordering the segments of
    the concatenated ``texels`` (NumPy arrays or :class:`TexelRuns`) by ``(texel, key,
    concatenation index)``: ``key`` a Dr.Jit UInt32 (S,) per concatenated segment (None:
    ``z0`` quantised, :func:`quantised_depth`); :func:`~avsm_dr.segments.key_order`.  The
    permutation is None when ``key`` is None and one piece is in that order already: a
    :class:`TexelRuns` (a grid: each ray front to back), or texels and, inside each, z0
    non-decreasing (a hair piece comes by texel, then strand)."""
    UInt32 = backend.types().UInt32
    one = texels[0] if len(texels) == 1 else None         # one piece in texel order: grouped already
    ready = False                                         # ... and in (texel, key) order too
    if isinstance(one, TexelRuns):
        counts, ready = one.texel_counts(n_texels), key is None
    elif one is not None and np.all(np.diff(np.asarray(one, np.int64)) >= 0):
        counts = np.bincount(np.asarray(one, np.int64), minlength=n_texels)
        ready = key is None and bool(np.all((np.diff(A.host(z0, "z0")) >= 0) | (np.diff(np.asarray(one)) > 0)))
    else:
        one = None
    if ready:
        return np.concatenate([[0], np.cumsum(counts)]), None
    tex = _concat([t.device() if isinstance(t, TexelRuns) else A.to_uint32(np.asarray(t, np.int64))
                   for t in texels], UInt32)
    n = dr.width(tex)
    if one is None:
        cnt = dr.zeros(UInt32, n_texels)
        slot = dr.scatter_inc(cnt, tex)                    # arbitrary order inside a texel
        dr.eval(cnt, slot)
        counts = np.asarray(cnt.numpy(), np.int64)
    offsets = np.zeros(n_texels + 1, np.int64)
    np.cumsum(counts, out=offsets[1:])
    off = A.to_uint32(offsets)
    group = None
    if one is None:                                 # group by texel (slots from the atomic counter)
        gid = dr.zeros(UInt32, n)
        dr.scatter(gid, dr.arange(UInt32, n), dr.gather(UInt32, off, tex) + slot)   # index at its slot
        group = (gid, dr.gather(UInt32, tex, gid))
    return offsets, key_order(counts, off, tex, quantised_depth(z0) if key is None else key, group)


def _concat(arrays, Type):
    """Dr.Jit arrays concatenated as one ``Type`` array (empty ones skipped), each scattered at
    an opaque offset (no offset in the kernel hash)."""
    arrays = [a for a in arrays if dr.width(a) > 0]
    if len(arrays) == 1:
        return arrays[0]
    out = dr.zeros(Type, sum(dr.width(a) for a in arrays))
    UInt32 = backend.types().UInt32
    start = 0
    for a in arrays:
        dr.scatter(out, a, dr.arange(UInt32, dr.width(a)) + dr.opaque(UInt32, start))
        start += dr.width(a)
    return out

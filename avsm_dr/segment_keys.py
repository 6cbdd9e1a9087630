"""Per-texel order keys of :meth:`Segments.in_order <avsm_dr.segments.Segments.in_order>` and
:meth:`Segments.sorted <avsm_dr.segments.Segments.sorted>`: the seeded 32-bit shuffle hash
(:func:`shuffle_key`) and ranks within index ranges on the device (:func:`rank_in_ranges`).
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from . import backend


def _mix32(x, c1, c2):
    """Chris Wellons' "lowbias32" integer hash (x ^= x >> 16; x *= c1; x ^= x >> 15; x *= c2;
    x ^= x >> 16) on uint32 NumPy or Dr.Jit UInt32 arrays (products modulo 2^32)."""
    x = x ^ (x >> 16)
    x = x * c1
    x = x ^ (x >> 15)
    x = x * c2
    return x ^ (x >> 16)


_MIX = (0x7FEB352D, 0x846CA68B)


def _seed_word(seed: int) -> int:
    """``lowbias32(seed)`` as a Python int (the seed's share of :func:`shuffle_key`)."""
    return int(_mix32(np.array([seed], np.uint32), *(np.uint32(c) for c in _MIX))[0])


def shuffle_key(seed: int, texel, rank):
    """Sort key of the ``"random"`` order (:meth:`Segments.in_order`): the 32-bit hash
    ``h(h(h(seed) + texel) + rank)`` (``h``: :func:`_mix32`, sums modulo 2^32) of the seed,
    the texel and the segment's rank in the texel's depth order.  ``texel``, ``rank``: uint32
    NumPy arrays (returns NumPy) or Dr.Jit UInt32 (returns UInt32; the seed enters as an
    opaque scalar, one kernel for every seed).  A texel's shuffle therefore depends on
    (seed, texel, its segment count) only, not on threads or on the order it came in."""
    if isinstance(texel, np.ndarray):
        c1, c2 = (np.uint32(c) for c in _MIX)
        s = np.uint32(_seed_word(seed))
        with np.errstate(over="ignore"):
            return _mix32(_mix32(texel.astype(np.uint32) + s, c1, c2) + rank.astype(np.uint32), c1, c2)
    UInt32 = type(texel)
    s = dr.opaque(UInt32, _seed_word(seed))
    return _mix32(_mix32(texel + s, *_MIX) + rank, *_MIX)


def rank_in_ranges(lo, hi, keys, ids=None):
    """Rank of every lane ``i`` among the lanes ``j`` of its range ``[lo_i, hi_i)`` (which
    contains ``i``): ``#{j : (keys[0]_j, keys[1]_j, ..., ids_j) < (keys[0]_i, ..., ids_i)}``,
    lexicographic, on the device (one lane per element, ``hi - lo`` gathers each).

    keys: Dr.Jit arrays (S,) compared in order; ids: distinct tie-breakers (S,) (default:
    the lane index, so equal keys keep their stored order, a stable sort).  Within each
    range the ranks are a permutation of ``0 .. hi - lo - 1``."""
    UInt32 = backend.types().UInt32
    i = dr.arange(UInt32, dr.width(lo))

    def cond(j, rank):
        return j < hi

    def body(j, rank):                  # j: lane compared with i; rank: lanes found before i
        before = j < i if ids is None else dr.gather(type(ids), ids, j) < ids
        for k in reversed(keys):
            kj = dr.gather(type(k), k, j)
            before = (kj < k) | ((kj == k) & before)
        return j + 1, rank + dr.select(before, 1, 0)

    return dr.while_loop((UInt32(lo), dr.zeros(UInt32, dr.width(lo))), cond, body, labels=("j", "rank"))[1]

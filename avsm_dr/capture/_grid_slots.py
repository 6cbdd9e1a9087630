"""Slot buffers of the grid captures' one-pass layout: every lane writes its segments
(z0, z1, tau) into its own run of slots (a bound of its segments), then
:func:`compact_slots` gathers the filled slots into CSR order.  Used by :mod:`.grid`'s
march and :mod:`.dda`'s exact traversal.  A slot is 4 floats (z0, z1, tau, unused): one
packet store per segment written, one packet load per segment read.
"""
from __future__ import annotations

import drjit as dr

from .. import backend


def new_slots(Float, n: int):
    """An uninitialised slot buffer for ``n`` segments."""
    return dr.empty(Float, 4 * n)


def _arr4(Float):
    t = backend.types()
    return t.Array4f if Float is t.Float else t.Array4f64


def write_slots(buf, values, idx, active) -> None:
    """Write (z0, z1, tau) ``values`` at slots ``idx`` of a :func:`new_slots` buffer."""
    dr.scatter(buf, _arr4(type(values[0]))(*values, 0), idx, active)


def read_slots(buf, idx, active=True) -> list:
    """(z0, z1, tau) at slots ``idx`` of a :func:`new_slots` buffer."""
    v = dr.gather(_arr4(type(buf)), buf, idx, active)
    return [v[0], v[1], v[2]]


def compact_slots(buf, slot, counts, n_segments: int):
    """The first ``counts[i]`` slots from ``slot[i]`` of every lane i of the slot buffer
    ``buf``, in lane order (CSR).  Output segment k of lane i reads slot
    ``k + slot[i] - off[i]`` (``off``: exclusive prefix sum of ``counts``); that shift is
    built without a per-segment lookup of the lane: a ``scatter_add`` at every lane's
    offset of the change of shift from the previous lane (``cap - count`` of that lane,
    ``cap`` = the slot gap), then an inclusive prefix sum (modulo 2^32)."""
    UInt32 = type(counts)
    Float = type(buf)
    if n_segments == 0:
        return Float(), Float(), Float()
    n = dr.width(counts)
    off = dr.prefix_sum(counts)
    i = dr.arange(UInt32, n)
    prev = dr.maximum(i, 1) - 1
    step = dr.select(i > 0, slot - dr.gather(UInt32, slot, prev) - dr.gather(UInt32, counts, prev), 0)
    shift = dr.zeros(UInt32, n_segments)
    # Direct (atomic) mode: Auto may pick Expand on the LLVM backend, which bakes the target's
    # size into the kernel (a new compile for every capture)
    dr.scatter_add(shift, step, off, off < dr.opaque(UInt32, n_segments), mode=dr.ReduceMode.Direct)
    src = dr.arange(UInt32, n_segments) + dr.cumsum(shift)
    out = read_slots(buf, src)
    dr.eval(out)
    dr.sync_thread()
    return out

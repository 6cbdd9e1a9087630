"""Slot buffers of the grid captures' one-pass layout: every lane writes its segments
(z0, z1, tau) into its own run of slots (a bound of its segments), then
:func:`compact_slots` gathers the filled slots into CSR order.  Used by :mod:`.grid`'s
march and :mod:`.dda`'s exact traversal.
"""
from __future__ import annotations

import drjit as dr

from .. import backend

#: Slot buffers hold 4 floats per slot (z0, z1, tau, unused): one packet store per segment in
#: the march, one packet load per segment in :func:`compact_slots` (3 gathers otherwise).
PACKET_SLOTS = True


def new_slots(Float, n: int) -> list:
    """Uninitialised slot buffers for ``n`` segments (z0, z1, tau), see :data:`PACKET_SLOTS`."""
    if PACKET_SLOTS:
        return [dr.empty(Float, 4 * n)]
    return [dr.empty(Float, n) for _ in range(3)]


def arr4(Float):
    t = backend.types()
    return t.Array4f if Float is t.Float else t.Array4f64


def write_slots(bufs, values, idx, active) -> None:
    """Write (z0, z1, tau) ``values`` at slots ``idx`` of :func:`new_slots` buffers."""
    if len(bufs) == 1:
        dr.scatter(bufs[0], arr4(type(values[0]))(*values, 0), idx, active)
    else:
        for b, v in zip(bufs, values):
            dr.scatter(b, v, idx, active)


def read_slots(bufs, idx, active=True) -> list:
    """(z0, z1, tau) at slots ``idx`` of :func:`new_slots` buffers."""
    Float = type(bufs[0])
    if len(bufs) == 1:
        v = dr.gather(arr4(Float), bufs[0], idx, active)
        return [v[0], v[1], v[2]]
    return [dr.gather(Float, b, idx, active) for b in bufs]


def compact_slots(bufs, slot, counts, n_segments: int):
    """The first ``counts[i]`` slots from ``slot[i]`` of every lane i of the slot buffers
    ``bufs``, in lane order (CSR).  Output segment k of lane i reads slot
    ``k + slot[i] - off[i]`` (``off``: exclusive prefix sum of ``counts``); that shift is
    built without a per-segment lookup of the lane: a ``scatter_add`` at every lane's
    offset of the change of shift from the previous lane (``cap - count`` of that lane,
    ``cap`` = the slot gap), then an inclusive prefix sum (modulo 2^32), so the kernel over
    the segments only reads the values (one packet load with :data:`PACKET_SLOTS`)."""
    UInt32 = type(counts)
    Float = type(bufs[0])
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
    out = read_slots(bufs, src)
    dr.eval(out)
    dr.sync_thread()
    return out

"""Deep shadow maps (Lokovic and Veach 2000, "Deep shadow maps", SIGGRAPH; Salvi et al.
2010, "Adaptive Volumetric Shadow Maps", secs. 2, 3.2 and 5 compare AVSM against them).

Each texel stores a variable number of nodes ``(z_i, V_i)`` (depth, transmittance)
that reproduce the texel's exact visibility function ``V(z)`` within a user tolerance
``epsilon`` everywhere::

    |DSM(z) - V(z)| <= epsilon   for every depth z        (Lokovic-Veach error bound)

Pipeline (one build, three phases):

1. **Exact curve as a polyline** (phase A).  ``V(z) = exp(-tau(z))`` with the optical
   depth ``tau`` piecewise linear between the texel's sorted unique segment ends
   ("breakpoints") and steps at zero-length segments (a receiver at a step depth is
   behind it, as in :mod:`.exact`).  ``tau`` at every breakpoint comes from events
   sorted inside each texel (NumPy row sorts, O(S log S); skipped when the segments
   are already sorted and disjoint) and a prefix sum (one Dr.Jit lane per texel; the
   slope is a compensated sum so that short dense segments do not wipe out small
   ones).  Between breakpoints ``V`` is exactly exponential; the polyline adds vertices
   where ``V`` crosses a fixed table of levels ``L_0 = 1 > L_1 > ... > L_N`` with ::

       L_{n+1} = L_n exp(-kappa_n),  kappa_n = sqrt(8 eps_p / L_n),  L_N <= eps_p,

   so that every polyline piece lies inside one band ``[L_{n+1}, L_n]`` and its chord
   error is at most ``max|V''| h^2 / 8 = L_n kappa^2 / 8 <= eps_p`` (below ``L_N`` both
   curves lie in ``[0, eps_p]``).  This replaces uniform subdivision: a monotone curve
   crosses each level once, so a texel's polyline has at most ``2 B + N`` vertices
   (B breakpoints, N ~ sqrt(1 / eps_p) levels) however opaque a segment is.  Inserted
   depths are rounded to the storage dtype first and their values are the exact curve
   at the rounded depth, so stored depths are exact and vertices sit on ``V``.  A
   crossing that rounds onto the previous vertex (a curve dropping within one ulp, e.g.
   an opaque segment of sub-ulp length at a large depth offset) moves to the next
   representable depth, and levels already passed there are skipped: dropping it would
   leave the chord to the next breakpoint far above ``V``.
   ``eps_p = epsilon / 4``.  Level crossings: one Dr.Jit lane per breakpoint (a
   counting pass, an exclusive sum, a writing pass).

2. **Greedy compression** (phase B, Lokovic-Veach's algorithm): from the current origin
   vertex keep the window ``[lo, hi]`` of slopes whose line from the origin passes
   within ``delta = epsilon / 2`` of every polyline vertex seen so far (band clipped to
   ``[0, 1]``, ``hi <= 0`` so the result is non-increasing); when the window empties,
   emit a node at the depth of the last vertex that fitted and restart from it.  A
   vertex at the origin's depth (a step) only asks the origin value to lie in its band,
   otherwise a vertical step node is emitted.  The last vertex becomes a node unless
   the slope 0 still fits (then the last node's value holds to the end).  Two node
   placements:

   * ``placement="midslope"`` (default, the paper's): the node lies on the line with the
     mid slope ``(lo + hi) / 2``, up to ``delta`` off the curve, and is the next origin.
   * ``placement="curve"``: nodes are a subset of the polyline vertices (values on the
     exact curve); a vertex is accepted while the chord to it stays within ``delta`` of
     the vertices in between.  Slightly more nodes; the node values are exact curve
     values, hence differentiable w.r.t. the segments with the node depths held fixed.

   Error: polyline <= eps_p, compression <= delta (the difference of two polylines
   whose kinks are all at polyline vertices is bounded by its values there), so
   ``|DSM - V| <= 3 epsilon / 4`` in exact arithmetic; the remaining ``epsilon / 4``
   absorbs the rounding of inserted depths (a rounded piece may straddle two bands).
   One Dr.Jit lane per texel runs a ``dr.while_loop`` over the texel's CSR polyline,
   scattering nodes into an output buffer of the polyline's size; nodes are then
   compacted to CSR.  Phases A and B run in float64; nodes are stored in the segments'
   dtype.

3. **Lookup** (phase C): per receiver, binary search of the texel's nodes for the last
   node with ``z_i <= z``, linear interpolation to the next one; ``V = 1`` in front of
   the first node, the last node's value behind the last one; empty texels ``V = 1``.

Storage: ``nbytes_per_texel`` = mean over texels of ``nodes x 2 x itemsize + 4``
(the (depth, value) pairs plus one 4-byte CSR offset).

Memory: phases A and B hold ~``TEMP_BYTES_PER_SEGMENT`` bytes per segment (float64 host
events, device prefix sums, polyline, node buffers), so they run on chunks of texels
sized from the output built so far (:func:`next_chunk_segments`); each chunk's nodes are
kept in the storage dtype.  The build's peak stays within a few times the output's size
(in one piece it was tens of times).  Texels are independent, so the nodes do not depend on
the chunking.
"""
from __future__ import annotations

import math

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import backend
from .. import validation as V
from .registry import register
from .base import Representation
from ._precision import PRECISIONS, Stored
from .schema import Param, Schema
from .exact import exact_values

PLACEMENTS = ("midslope", "curve")

#: share of epsilon given to the polyline (phase A) and to the compression band (phase B)
POLYLINE_SHARE = 0.25
BAND_SHARE = 0.5
#: smallest accepted tolerance (the level table has ~1/sqrt(2 eps_p) entries)
MIN_TOLERANCE = 1e-9
#: Memory the build may use for its phase-A polyline and phase-B buffers (bytes; 2 GiB),
#: summed over its chunks of texels (the nodes, a subset of the polyline, are kept).
#: Each chunk's polyline is bounded before it is allocated (``BYTES_PER_VERTEX`` per
#: vertex); a larger one raises ValueError saying which tolerance would fit.
MEMORY_BUDGET_BYTES = 2 * 2**30
#: Device and host bytes per polyline vertex over the build (phase A: depth, optical
#: depth, value, flag = 25; phase B: node depth, value, source = 20; host copies ~20).
BYTES_PER_VERTEX = 64


#: Builds run phases A and B on chunks of texels (:func:`next_chunk_segments`), so that their
#: temporaries, ~``TEMP_BYTES_PER_SEGMENT`` per segment of a chunk (host and device, measured
#: on random smoke-like maps), stay near the output's size: a chunk holds about as many
#: segments as ``estimated output bytes / TEMP_BYTES_PER_SEGMENT`` (the first chunk
#: ``MIN_CHUNK_SEGMENTS``, then extrapolated from the chunks built), clamped to
#: [MIN_CHUNK_SEGMENTS, MAX_CHUNK_SEGMENTS]: below the minimum the kernel launches of a
#: chunk would dominate.
TEMP_BYTES_PER_SEGMENT = 400
MIN_CHUNK_SEGMENTS = 1 << 13
MAX_CHUNK_SEGMENTS = 1 << 18


# ----------------------------------------------------------------------------
# Phase A: the exact curve as a polyline (NumPy event sort, Dr.Jit prefix sums and levels)
# ----------------------------------------------------------------------------
def transmittance_levels(eps_p: float) -> np.ndarray:
    """Optical-depth levels ``Lambda_n = -ln L_n`` (ascending, n >= 1) of the level table.

    ``L_{n+1} = L_n exp(-sqrt(8 eps_p / L_n))`` from ``L_0 = 1`` down to the first
    ``L_N <= eps_p``.  Empty when ``eps_p >= 1``.
    """
    out = []
    lam, level = 0.0, 1.0
    while level > eps_p:
        lam += math.sqrt(8.0 * eps_p / level)
        level = math.exp(-lam)
        out.append(lam)
    return np.asarray(out, dtype=np.float64)


def sort_within_texels(off: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Permutation sorting ``values`` inside each CSR range ``off[t]:off[t+1]``.

    Texels are bucketed by count (powers of two), each bucket padded with +inf to a
    (texels, width) block and sorted along rows: O(n log n) per texel with NumPy's
    row sorts, instead of a global ``lexsort`` on (texel, value).
    """
    counts = np.diff(off)
    order = np.arange(values.size)
    busy = np.flatnonzero(counts > 1)
    if busy.size == 0:
        return order
    bucket = np.ceil(np.log2(counts[busy])).astype(np.int64)
    for b in np.unique(bucket):
        tex = busy[bucket == b]
        c = counts[tex]
        width = int(c.max())
        cols = np.arange(width)
        idx = off[tex][:, None] + cols[None, :]
        valid = cols[None, :] < c[:, None]
        block = np.where(valid, values[np.minimum(idx, values.size - 1)], np.inf)
        rows = np.argsort(block, axis=1)
        order[idx[valid]] = np.take_along_axis(idx, rows, axis=1)[valid]
    return order


def breakpoints(offsets, z0, z1, tau):
    """Sorted unique segment ends per texel and what happens at each (float64 NumPy).

    Returns dict: ``off`` (T+1,) CSR over breakpoints, ``z`` depths, ``jump`` summed
    optical depth of zero-length segments there, ``rate_in`` / ``rate_out`` summed
    density (tau / length) of segments starting / ending there, ``active`` change of the
    number of open positive-length segments.
    """
    n_tex = offsets.size - 1
    counts = np.diff(offsets)
    s = tau.size
    length = z1 - z0
    pos = length > 0
    rate = np.where(pos, tau / np.where(pos, length, 1.0), 0.0)

    # events z0_0, z1_0, z0_1, z1_1, ...: texel t owns [2 off[t], 2 off[t+1])
    ev_z = np.empty(2 * s)
    ev_z[0::2] = z0
    ev_z[1::2] = z1
    ev_off = 2 * offsets
    first = np.zeros(2 * s, dtype=bool)               # first event of its texel
    first[ev_off[:-1][counts > 0]] = True
    in_order = bool(np.all((np.diff(ev_z) >= 0) | first[1:]))
    if in_order:    # sorted, non-overlapping segments (e.g. ray-marched voxels): no sort
        order = None
    else:
        order = sort_within_texels(ev_off, ev_z)
        ev_z = ev_z[order]
    new = first.copy()
    new[0] = True
    new[1:] |= ev_z[1:] != ev_z[:-1]
    bp_sorted = np.cumsum(new) - 1
    if order is None:
        bp_of_slot = bp_sorted
    else:
        bp_of_slot = np.empty(2 * s, dtype=np.int64)
        bp_of_slot[order] = bp_sorted
    nb = int(bp_sorted[-1]) + 1 if s else 0
    bp_z = ev_z[new]

    bp_start = bp_of_slot[0::2]           # breakpoint of each segment's z0
    bp_end = bp_of_slot[1::2]             # breakpoint of each segment's z1
    jump = np.bincount(bp_start, weights=np.where(pos, 0.0, tau), minlength=nb)
    rate_in = np.bincount(bp_start, weights=rate, minlength=nb)
    rate_out = np.bincount(bp_end, weights=rate, minlength=nb)
    active = (np.bincount(bp_start, weights=pos, minlength=nb)
              - np.bincount(bp_end, weights=pos, minlength=nb)).astype(np.int32)
    per_tex = np.add.reduceat(new, ev_off[:-1][counts > 0]) if s else np.zeros(0, np.int64)
    bp_count = np.zeros(n_tex, np.int64)
    bp_count[counts > 0] = per_tex
    off = np.concatenate([[0], np.cumsum(bp_count)]).astype(np.int64)
    return dict(off=off, z=bp_z, jump=jump, rate_in=rate_in, rate_out=rate_out, active=active)


def _lanes_by_length(off: np.ndarray) -> np.ndarray:
    """Non-empty CSR rows ordered by length: one lane each, so that SIMD packets run
    loops of similar length and empty texels cost nothing (DESIGN.md)."""
    counts = np.diff(off)
    lanes = np.flatnonzero(counts > 0)
    return lanes[np.argsort(counts[lanes], kind="stable")]


def prefix_optical_depth(bp):
    """``tau`` just before (``left``) and at (``right``) every breakpoint, and the slope
    ``d tau / dz`` on the interval after it.  Dr.Jit, one float64 lane per texel.

    tau_left[k] = tau_right[k-1] + slope[k-1] (z[k] - z[k-1]),  tau_right[k] = tau_left[k] + jump[k];
    the slope is a Neumaier-compensated running sum of rate_in - rate_out, reset to 0
    whenever no positive-length segment is open.  Returns Dr.Jit Float64 arrays.
    """
    t = backend.types()
    F64, U32, I32 = t.Float64, t.UInt32, t.Int32
    nb = bp["z"].size
    lanes = _lanes_by_length(bp["off"])
    start = U32(A.aligned(bp["off"][lanes].astype(np.uint32)))
    end = U32(A.aligned(bp["off"][lanes + 1].astype(np.uint32)))
    z, jump = F64(A.aligned(bp["z"])), F64(A.aligned(bp["jump"]))
    r_in, r_out = F64(A.aligned(bp["rate_in"])), F64(A.aligned(bp["rate_out"]))
    active = I32(bp["active"])
    tau_left, tau_right, slope_out = dr.zeros(F64, nb), dr.zeros(F64, nb), dr.zeros(F64, nb)

    def neumaier(s, c, x):
        total = s + x
        c = c + dr.select(dr.abs(s) >= dr.abs(x), (s - total) + x, (x - total) + s)
        return total, c

    def cond(k, tau, rate, comp, n_open, z_prev, slope):
        return k < end

    def body(k, tau, rate, comp, n_open, z_prev, slope):
        zk = dr.gather(F64, z, k)
        tl = dr.select(k == start, 0.0, tau + slope * (zk - z_prev))   # tau(z_k^-)
        tr = tl + dr.gather(F64, jump, k)                               # tau(z_k)
        dr.scatter(tau_left, tl, k)
        dr.scatter(tau_right, tr, k)
        rate, comp = neumaier(rate, comp, dr.gather(F64, r_in, k))
        rate, comp = neumaier(rate, comp, -dr.gather(F64, r_out, k))
        n_open = n_open + dr.gather(I32, active, k)
        closed = n_open <= 0
        rate = dr.select(closed, 0.0, rate)
        comp = dr.select(closed, 0.0, comp)
        slope = dr.maximum(rate + comp, 0.0)                           # d tau / dz after z_k
        dr.scatter(slope_out, slope, k)
        return k + 1, tr, rate, comp, n_open, zk, slope

    n = lanes.size
    state = (U32(start), dr.zeros(F64, n), dr.zeros(F64, n), dr.zeros(F64, n),
             dr.zeros(I32, n), dr.zeros(F64, n), dr.zeros(F64, n))
    dr.while_loop(state, cond, body, label="dsm_prefix_optical_depth")
    dr.eval(tau_left, tau_right, slope_out)
    return tau_left, tau_right, slope_out


def _count_below(table, x, m: int, strict: bool):
    """Per lane: number of entries of the sorted Float64 ``table`` (size m) that are
    ``< x`` (strict) or ``<= x``; unrolled binary search."""
    U32 = backend.types().UInt32
    lo = dr.zeros(U32, dr.width(x))
    hi = dr.full(U32, m, dr.width(x))
    for _ in range(max(1, math.ceil(math.log2(m + 1)))):
        live = lo < hi
        mid = (lo + hi) >> 1
        val = dr.gather(type(x), table, mid, live)
        below = (val < x) if strict else (val <= x)
        lo = dr.select(live & below, mid + 1, lo)
        hi = dr.select(live & ~below, mid, hi)
    return lo


def next_up(z, dtype: str):
    """The next depth after ``z`` (Float64 lanes holding ``dtype`` values) representable
    in the storage dtype (IEEE bit increment; +-0 -> the smallest subnormal)."""
    t = backend.types()
    F, U = (t.Float, t.UInt32) if dtype == "float32" else (t.Float64, t.UInt64)
    x = F(z)
    bits = dr.reinterpret_array(U, x)
    up = dr.select(x > 0, bits + 1, dr.select(x < 0, bits - 1, U(1)))
    return t.Float64(dr.reinterpret_array(F, up))


def check_polyline_size(n_breakpoints: int, n_crossings: int, n_tex: int, eps_p: float,
                        partial: bool = False) -> None:
    """ValueError (naming ``tolerance``) when the polyline's upper bound of
    ``2 B + crossings`` vertices exceeds :data:`MEMORY_BUDGET_BYTES` or the budget of every
    build, :func:`avsm_dr.validation.memory_budget`, whichever is less (B breakpoints and
    crossings of the first ``n_tex`` texels, all of them unless ``partial``).  The level
    part grows as ``1 / sqrt(tolerance)`` (e.g. 44,727 levels at 1e-9: ~2.9 MB per opaque
    texel, ~190 GB for a 256^2 map), so the message names the tolerance that would fit
    (those texels; the rest of a ``partial`` map needs more)."""
    bound = 2 * int(n_breakpoints) + int(n_crossings)
    need = bound * BYTES_PER_VERTEX
    budget = min(MEMORY_BUDGET_BYTES, V.memory_budget())   # and the budget of every build
    if need <= budget:
        return
    tol = eps_p / POLYLINE_SHARE
    room = budget // BYTES_PER_VERTEX - 2 * int(n_breakpoints)
    fit = "no tolerance fits: fewer texels or segments" if room <= 0 else \
        f"tolerance >= {tol * (n_crossings / room) ** 2:.2g} fits"
    raise ValueError(
        f"tolerance: {tol:g} needs a polyline of up to {bound:,} vertices over "
        f"{'the first ' if partial else ''}{n_tex} texels "
        f"({need / 2**30:.3g} GiB > the {budget / 2**30:.3g} GiB of "
        f"avsm_dr.representations.dsm.MEMORY_BUDGET_BYTES or avsm_dr.validation.memory_budget()); {fit} "
        "(vertices grow as 1/sqrt(tolerance))")


def exact_polyline(offsets, z0, z1, tau, eps_p: float, dtype: str = "float64", before=(0, 0, 0)):
    """Polyline within ``eps_p`` of the exact curve (phase A), all texels at once.

    offsets (T+1,) int; z0, z1, tau (S,) float64 host arrays (tau clamped as in Segments);
    ``before``: (breakpoints, level crossings, texels) of the chunks already built, counted
    in :func:`check_polyline_size`.  Returns dict: ``off`` (T+1,) int64 CSR over vertices,
    Dr.Jit arrays ``z``, ``tau``, ``v`` (Float64 depth, optical depth, transmittance) and
    ``left`` (Bool: the vertex is the value just before a step at its depth), and
    ``bound`` (breakpoints, level crossings) of these texels.  Per breakpoint k the vertices are
    (z_k, tau_left), (z_k, tau_right) if a zero-length segment steps there, then the
    level crossings inside (z_k, z_{k+1}) (one Dr.Jit lane per breakpoint, a counting
    pass and a writing pass).
    """
    t = backend.types()
    F64, F32, U32, Bool = t.Float64, t.Float, t.UInt32, t.Bool
    n_tex = offsets.size - 1
    if z0.size == 0:
        return dict(off=np.zeros(n_tex + 1, np.int64), z=F64(), tau=F64(), v=F64(), left=Bool(), bound=(0, 0))
    bp = breakpoints(offsets, z0, z1, tau)
    tl, tr, slope = prefix_optical_depth(bp)
    nb = bp["z"].size
    last = np.zeros(nb, dtype=bool)
    last[bp["off"][1:][np.diff(bp["off"]) > 0] - 1] = True          # last breakpoint of a texel
    has_next = ~Bool(A.aligned(last))
    nxt = dr.arange(U32, nb) + 1        # masked gathers: no size literal, one kernel for every chunk
    bz = F64(A.aligned(bp["z"]))
    z_next = dr.gather(F64, bz, nxt, has_next)
    tl_next = dr.gather(F64, tl, nxt, has_next)
    step = Bool(A.aligned(bp["jump"] > 0))

    # levels Lambda_i with tau_right[k] < Lambda_i < tau_left[k+1] are crossed in (z_k, z_{k+1})
    lam_np = transmittance_levels(eps_p)
    m = lam_np.size
    lam = F64(A.aligned(lam_np)) if m else F64(0.0)
    i0 = _count_below(lam, tr, m, strict=False) if m else dr.zeros(U32, nb)
    i1 = dr.select(has_next, _count_below(lam, tl_next, m, strict=True) if m else i0, i0)
    i1 = dr.maximum(i1, i0)
    n_cross = int((i1 - i0).numpy().astype(np.int64).sum())
    check_polyline_size(before[0] + nb, before[1] + n_cross, before[2] + n_tex, eps_p, partial=before[2] > 0)
    safe_slope = dr.select(slope > 0, slope, 1.0)

    def crossings(base, write: bool):
        """Loop over the candidate levels of each breakpoint.  A level not yet passed by
        the previous vertex (``Lambda_i > tau_prev``) gets a vertex at its crossing depth
        rounded to the storage dtype, or at the next representable depth after the
        previous vertex when it rounds onto it (a curve that drops within one ulp: the
        vertex then lies past several levels, which are skipped); kept when it lies
        before the next breakpoint.  Counts them, and with ``write`` scatters them from
        ``base``."""
        def cond(i, n, z_prev, tau_prev):
            return i < i1

        def body(i, n, z_prev, tau_prev):
            lam_i = dr.gather(F64, lam, i)
            zc = bz + (lam_i - tr) / safe_slope
            if dtype == "float32":
                zc = F64(F32(zc))
            zc = dr.maximum(zc, next_up(z_prev, dtype))
            tc = tr + slope * (zc - bz)
            keep = (lam_i > tau_prev) & (zc > z_prev) & (zc < z_next)
            if write:
                idx = base + n
                dr.scatter(out_z, zc, idx, keep)
                dr.scatter(out_tau, tc, idx, keep)
            return (i + 1, n + dr.select(keep, U32(1), U32(0)), dr.select(keep, zc, z_prev),
                    dr.select(keep, tc, tau_prev))

        _, n, _, _ = dr.while_loop((U32(i0), dr.zeros(U32, nb), F64(bz), F64(tr)), cond, body,
                                   label="dsm_level_crossings")
        return n

    out_z = out_tau = None
    n_lev = crossings(None, write=False)
    per_bp = 1 + dr.select(step, U32(1), U32(0)) + n_lev
    dr.eval(per_bp)
    counts = per_bp.numpy().astype(np.int64)
    base_np = np.concatenate([[0], np.cumsum(counts)])
    nv = int(base_np[-1])
    base = U32(A.aligned(base_np[:-1].astype(np.uint32)))
    out_z, out_tau = dr.zeros(F64, nv), dr.zeros(F64, nv)
    out_left = dr.zeros(Bool, nv)
    dr.scatter(out_z, bz, base)
    dr.scatter(out_tau, tl, base)
    dr.scatter(out_left, step, base)
    dr.scatter(out_z, bz, base + 1, step)
    dr.scatter(out_tau, tr, base + 1, step)
    crossings(base + 1 + dr.select(step, U32(1), U32(0)), write=True)
    v = dr.exp(-out_tau)
    dr.eval(out_z, out_tau, out_left, v)
    off = base_np[bp["off"]].astype(np.int64)
    return dict(off=off, z=out_z, tau=out_tau, v=v, left=out_left, bound=(nb, n_cross))


# ----------------------------------------------------------------------------
# Phase B: Lokovic-Veach greedy compression (Dr.Jit, one lane per texel)
# ----------------------------------------------------------------------------
def compress(poly, delta: float, placement: str = "midslope"):
    """Greedy slope-window compression of every texel's polyline within ``delta``.

    poly: output of :func:`exact_polyline`.  Returns (counts (T,) int64, z, v, src):
    float64 NumPy node depths/values and the polyline vertex each node sits on (``curve``
    placement; for ``midslope`` the vertex whose depth the node takes), in CSR by counts.
    """
    t = backend.types()
    F64, U32, Bool = t.Float64, t.UInt32, t.Bool
    off = poly["off"]
    n_tex = off.size - 1
    nv = int(off[-1])
    if nv == 0:
        e = np.zeros(0)
        return np.zeros(n_tex, np.int64), e, e, np.zeros(0, np.int64)
    lanes = _lanes_by_length(off)
    start = U32(A.aligned(off[lanes].astype(np.uint32)))
    end = U32(A.aligned(off[lanes + 1].astype(np.uint32)))
    pz, pv = poly["z"], poly["v"]
    out_z, out_v, out_src = dr.zeros(F64, nv), dr.zeros(F64, nv), dr.zeros(U32, nv)
    n = lanes.size
    inf = float("inf")

    # the first vertex is always the first node
    zo, vo = dr.gather(F64, pz, start), dr.gather(F64, pv, start)
    dr.scatter(out_z, zo, start)
    dr.scatter(out_v, vo, start)
    dr.scatter(out_src, start, start)

    def band(vk):
        """Admissible values at a vertex: [max(v - delta, 0), min(v + delta, 1)]."""
        return dr.maximum(vk - delta, 0.0), dr.minimum(vk + delta, 1.0)

    def emit(cnt, active, z_new, v_new, src):
        idx = start + cnt
        dr.scatter(out_z, z_new, idx, active)
        dr.scatter(out_v, v_new, idx, active)
        dr.scatter(out_src, src, idx, active)
        return cnt + dr.select(active, U32(1), U32(0))

    def cond(k, *_):
        return k < end

    if placement == "midslope":
        # state: k next vertex, (zo, vo) origin, [lo, hi] slope window, has_w window
        # holds a constraint, (zp, ip) last vertex that fitted, cnt nodes emitted
        def body(k, zo, vo, lo, hi, has_w, zp, ip, cnt):
            zk, vk = dr.gather(F64, pz, k), dr.gather(F64, pv, k)
            a, b = band(vk)
            dz = zk - zo
            vertical = dz <= 0
            sdz = dr.select(vertical, 1.0, dz)
            nlo = dr.maximum(lo, (a - vo) / sdz)
            nhi = dr.minimum(hi, (b - vo) / sdz)
            nlo = dr.select(has_w, nlo, dr.minimum(nlo, nhi))    # first constraint always fits
            accept = dr.select(vertical, (vo >= a) & (vo <= b), nlo <= nhi)
            step = vertical & ~accept        # step at the origin's depth: node (zo, vk)
            brk = ~vertical & ~accept        # window empty: node on the mid-slope line at zp
            s = 0.5 * (lo + hi)
            v_line = dr.maximum(vo + s * (zp - zo), 0.0)
            z_new = dr.select(step, zo, zp)
            v_new = dr.select(step, vk, v_line)
            emitted = step | brk
            cnt = emit(cnt, emitted, z_new, v_new, dr.select(step, k, ip))
            fit = accept & ~vertical
            lo = dr.select(fit, nlo, dr.select(emitted, -inf, lo))
            hi = dr.select(fit, nhi, dr.select(emitted, 0.0, hi))
            has_w = dr.select(fit, True, dr.select(emitted, False, has_w))
            zo = dr.select(emitted, z_new, zo)
            vo = dr.select(emitted, v_new, vo)
            zp = dr.select(accept, zk, dr.select(brk, zp, zo))
            ip = dr.select(accept | step, k, ip)
            k = dr.select(accept | step, k + 1, k)
            return k, zo, vo, lo, hi, has_w, zp, ip, cnt

        state = (start + 1, zo, vo, dr.full(F64, -inf, n), dr.zeros(F64, n),
                 dr.zeros(Bool, n), F64(zo), U32(start), dr.full(U32, 1, n))
        k, zo, vo, lo, hi, has_w, zp, ip, cnt = dr.while_loop(state, cond, body,
                                                              label="dsm_compress_midslope")
        v_last = dr.maximum(vo + 0.5 * (lo + hi) * (zp - zo), 0.0)
        flat_tail = (lo <= 0) & (hi >= 0)      # the origin's value holds to the end
        cnt = emit(cnt, has_w & ~flat_tail, zp, v_last, ip)
    elif placement == "curve":
        # state: k next vertex, (zo, vo) origin, [lo, hi] slopes of chords that keep the
        # vertices between origin and k within delta, (zp, vp, ip) last feasible vertex
        def body(k, zo, vo, io, lo, hi, zp, vp, ip, cnt):
            zk, vk = dr.gather(F64, pz, k), dr.gather(F64, pv, k)
            a, b = band(vk)
            dz = zk - zo
            vertical = dz <= 0
            sdz = dr.select(vertical, 1.0, dz)
            sk = (vk - vo) / sdz
            feasible = vertical | ((sk >= lo) & (sk <= hi))
            in_band = (vo >= a) & (vo <= b)
            nlo = dr.select(vertical, dr.select(in_band, lo, inf), dr.maximum(lo, (a - vo) / sdz))
            nhi = dr.select(vertical, hi, dr.minimum(hi, (b - vo) / sdz))
            brk = ~feasible
            cnt = emit(cnt, brk, zp, vp, ip)
            lo = dr.select(feasible, nlo, -inf)
            hi = dr.select(feasible, nhi, inf)
            zo = dr.select(brk, zp, zo)
            vo = dr.select(brk, vp, vo)
            io = dr.select(brk, ip, io)
            zp = dr.select(feasible, zk, zp)
            vp = dr.select(feasible, vk, vp)
            ip = dr.select(feasible, k, ip)
            k = dr.select(feasible, k + 1, k)
            return k, zo, vo, io, lo, hi, zp, vp, ip, cnt

        state = (start + 1, zo, vo, U32(start), dr.full(F64, -inf, n), dr.full(F64, inf, n),
                 F64(zo), F64(vo), U32(start), dr.full(U32, 1, n))
        k, zo, vo, io, lo, hi, zp, vp, ip, cnt = dr.while_loop(state, cond, body,
                                                              label="dsm_compress_curve")
        flat_tail = (lo <= 0) & (hi >= 0)      # the origin's value holds to the end
        cnt = emit(cnt, (ip != io) & ~flat_tail, zp, vp, ip)
    else:
        raise ValueError(f"placement: expected one of {PLACEMENTS}, got {placement!r}")

    dr.eval(out_z, out_v, out_src, cnt)
    counts = np.zeros(n_tex, np.int64)
    counts[lanes] = cnt.numpy()
    # compact: node j of texel i sits at off[i] + j in the output buffer
    node_off = np.concatenate([[0], np.cumsum(counts)])
    idx = np.repeat(off[:-1], counts) + (np.arange(node_off[-1]) - np.repeat(node_off[:-1], counts))
    return counts, out_z.numpy()[idx], out_v.numpy()[idx], out_src.numpy()[idx].astype(np.int64)


# ----------------------------------------------------------------------------
# Chunks: phases A and B run on groups of texels, so temporaries scale with a chunk
# ----------------------------------------------------------------------------
def chunk_end(offsets: np.ndarray, t0: int, per_chunk: int) -> int:
    """End ``t1`` of the chunk of texels that starts at ``t0`` and holds about ``per_chunk``
    segments (at least one texel: a texel's curve needs all of its segments)."""
    t1 = int(np.searchsorted(offsets, offsets[t0] + per_chunk, side="right")) - 1
    return min(max(t1, t0 + 1), offsets.size - 1)


def next_chunk_segments(output_bytes: float, segments_done: int, n_segments: int) -> int:
    """Segments of the next chunk: the output extrapolated from the chunks built
    (``output_bytes`` over ``segments_done`` of ``n_segments``) over
    ``TEMP_BYTES_PER_SEGMENT``, clamped to [MIN_CHUNK_SEGMENTS, MAX_CHUNK_SEGMENTS]."""
    if segments_done <= 0:
        return MIN_CHUNK_SEGMENTS
    estimate = output_bytes * n_segments / segments_done
    return int(min(MAX_CHUNK_SEGMENTS, max(MIN_CHUNK_SEGMENTS, estimate // TEMP_BYTES_PER_SEGMENT)))


def _host_range(x, s0: int, s1: int) -> np.ndarray:
    """Entries ``s0:s1`` of the Dr.Jit array ``x`` as float64 NumPy (the LLVM backend's
    ``numpy()`` is a view of its buffer; elsewhere only the range is gathered and copied)."""
    x = dr.detach(x)
    dr.eval(x)
    if dr.backend_v(x) == dr.JitBackend.LLVM:
        return np.asarray(x.numpy()[s0:s1], np.float64)
    U32 = backend.types().UInt32
    idx = dr.arange(U32, s1 - s0) + dr.opaque(U32, s0)
    return np.asarray(dr.gather(type(x), x, idx).numpy(), np.float64)


def _concatenate(parts: list, k: int) -> np.ndarray:
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


# ----------------------------------------------------------------------------
# The representation
# ----------------------------------------------------------------------------
@register("dsm")
class DeepShadowMap(Representation):
    """Deep shadow map with error bound ``tolerance`` (see the module docstring).

    Parameters (of ``ad.build("dsm", segments, ...)``): ``tolerance``, epsilon, the bound on
    ``|DSM(z) - V(z)|``, in [1e-9, inf) (default 0.01, the value of Salvi et al. 2010,
    "Adaptive Volumetric Shadow Maps", table 1); ``placement``, 'midslope' (Lokovic-Veach,
    not differentiable) or 'curve' (nodes on the exact curve; gradients w.r.t. optical depth
    with the node depths held fixed).

    Attributes after the build: ``node_counts`` (T,) int64 NumPy; ``node_depth``,
    ``node_value`` Dr.Jit arrays in CSR order; ``node_offsets`` (T+1,) int64 NumPy;
    ``node_left`` (bool NumPy) the node's polyline vertex is the value just before a step at
    its depth; ``n_polyline_vertices`` (T,) size of the phase-A polyline.

    Limit: the build holds the phase-A polyline, up to ``2 B + N`` vertices per texel
    (B breakpoints, N ~ sqrt(2 / tolerance) levels for a texel that goes opaque: 15 at
    0.01, 1418 at 1e-6, 44,727 at 1e-9), ``BYTES_PER_VERTEX`` bytes each, one chunk of
    texels at a time; a build whose bound summed over its chunks exceeds
    ``MEMORY_BUDGET_BYTES`` (2 GiB) raises ValueError naming the tolerance that fits,
    before allocating the chunk that crosses it.
    """

    schema = Schema(
        params=(
            Param("tolerance", "float", 0.01, "epsilon, the bound on |DSM(z) - V(z)| (below 1e-9 the bound "
                  "is lost in float rounding and the level table grows as 1/sqrt(tolerance))",
                  min=MIN_TOLERANCE),
            Param("placement", "choice", "midslope", "'midslope' (Lokovic-Veach, not differentiable) or "
                  "'curve' (nodes on the exact curve, differentiable)", choices=PLACEMENTS),
        ),
        size="tolerance", sweep=(0.1, 0.05, 0.02, 0.01, 0.005, 0.002), quick_sweep=(0.05, 0.01),
        examples=({"tolerance": 0.01}, {"tolerance": 0.01, "placement": "curve"}),
        headline={"tolerance": 0.01},
        summary="error-bounded polyline (variable node count)",
        paper="Lokovic & Veach 2000",
    )

    def _resolve(self):
        self.tolerance = self.params["tolerance"]
        self.placement = self.params["placement"]

    @property
    def differentiable(self) -> bool:
        """Only ``placement='curve'`` (node values on the exact curve) has gradients."""
        return self.placement == "curve"

    # ------------------------------------------------------------- build
    def _build(self):
        """Phases A and B chunk by chunk of texels (:func:`next_chunk_segments`); each
        chunk's nodes are kept in the storage dtype and copied once into the final arrays."""
        seg = self.segments
        t = backend.types()
        store = np.float32 if seg.dtype == "float32" else np.float64
        offsets = seg.offsets
        n_tex = seg.n_texels
        counts = np.zeros(n_tex, np.int64)
        self.n_polyline_vertices = np.zeros(n_tex, np.int64)
        parts, t0, node_bytes, bound = [], 0, 0, (0, 0)
        while t0 < n_tex:
            per_chunk = next_chunk_segments(node_bytes + 4 * t0, int(offsets[t0]), seg.n_segments)
            t1 = chunk_end(offsets, t0, per_chunk)
            s0, s1 = int(offsets[t0]), int(offsets[t1])
            off = offsets[t0:t1 + 1] - s0
            poly = exact_polyline(off, *(_host_range(x, s0, s1) for x in (seg.z0, seg.z1, seg.optical_depth)),
                                  POLYLINE_SHARE * self.tolerance, seg.dtype, before=(*bound, t0))
            bound = (bound[0] + poly["bound"][0], bound[1] + poly["bound"][1])
            del poly["tau"]             # only v is compressed
            self.n_polyline_vertices[t0:t1] = np.diff(poly["off"])
            c, nz, nv, src = compress(poly, BAND_SHARE * self.tolerance, self.placement)
            counts[t0:t1] = c
            left = poly["left"].numpy()[src] if src.size else np.zeros(0, bool)
            del poly
            parts.append((nz.astype(store), nv.astype(store), left))
            node_bytes += 2 * nz.size * seg.itemsize
            del nz, nv, src
            t0 = t1
        self.node_counts = counts
        self.node_offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        nz, nv, self.node_left = (_concatenate(parts, k) for k in range(3))
        Float = seg.Float
        self.node_depth = Float(nz)
        value = Float(nv)
        if self.placement == "curve" and counts.sum() and self._needs_grad():
            value = self._attach_gradients(value, nz, self.node_left, counts)
        self.node_value = value
        self._offsets_dr = t.UInt32(A.aligned(self.node_offsets.astype(np.uint32)))
        self._max_nodes = int(counts.max()) if counts.size else 0

    def _needs_grad(self) -> bool:
        return self.segments.requires_grad

    def _attach_gradients(self, value, nz, left, counts):
        """value + (V(z) - detach(V(z))): the primal stays the float64 one, the gradient is
        that of the exact curve at each node's fixed depth (left limit before a step;
        :func:`.exact.exact_values`, a sum loop that reverse mode recomputes)."""
        tex = np.repeat(np.arange(counts.size), counts)
        v = exact_values(self.segments, tex, nz, left)
        return value + (v - dr.detach(v))

    # ------------------------------------------------------------ storage
    precisions = PRECISIONS

    def _stored(self):
        return (Stored("node_depth", "depth", "csr"), Stored("node_value", "transmittance", "csr"))

    variable_size = True

    def texel_payload_bytes(self):
        """Sparse layout: a texel's (depth, value) pairs."""
        return self._csr_payload(self.node_counts, 2 * self.segments.itemsize)

    @property
    def nbytes_per_texel(self) -> float:
        if self.precision is not None:      # codes + per-texel ranges (:mod:`._precision`) + offset
            return self._stored_nbytes + 4
        mean = float(self.node_counts.mean()) if self.node_counts.size else 0.0
        return 2 * self.segments.itemsize * mean + 4

    def nodes_numpy(self, texel: int) -> tuple[np.ndarray, np.ndarray]:
        """(depths, values) of one texel's nodes as float64 NumPy arrays."""
        s = slice(int(self.node_offsets[texel]), int(self.node_offsets[texel + 1]))
        z = np.asarray(dr.detach(self.node_depth).numpy(), np.float64)
        v = np.asarray(dr.detach(self.node_value).numpy(), np.float64)
        return z[s], v[s]

    # -------------------------------------------------------------- lookup
    def _eval_texels(self, texel, depth):
        Float = self.Float
        UInt32 = backend.types().UInt32
        if self._max_nodes == 0:
            return dr.full(Float, 1.0, dr.width(depth))
        start = dr.gather(UInt32, self._offsets_dr, texel)
        end = dr.gather(UInt32, self._offsets_dr, texel + 1)
        zs, vs = self.node_depth, self.node_value
        # binary search: j = first node in [start, end) with z_j > depth
        lo, hi = UInt32(start), UInt32(end)
        for _ in range(max(1, math.ceil(math.log2(self._max_nodes + 1)))):
            live = lo < hi
            mid = (lo + hi) >> 1
            below = dr.gather(Float, zs, mid, live) <= depth
            lo = dr.select(live & below, mid + 1, lo)
            hi = dr.select(live & ~below, mid, hi)
        j = lo
        inside = (j > start) & (j < end)
        after = (j > start) & (j == end)
        ja = dr.select(j > start, j - 1, start)
        jb = dr.select(inside, j, ja)
        za = dr.gather(Float, zs, ja, j > start)
        zb = dr.gather(Float, zs, jb, j > start)
        va = dr.gather(Float, vs, ja, j > start)
        vb = dr.gather(Float, vs, jb, j > start)
        dz = zb - za
        safe = dr.select(dz > 0, dz, 1.0)
        w = dr.clip((depth - za) / safe, 0.0, 1.0)
        interp = va + w * (vb - va)
        out = dr.select(inside, interp, dr.select(after, va, 1.0))
        out = dr.clip(out, 0.0, 1.0)
        if self.placement == "midslope" and self._needs_grad():
            seg = self.segments     # a gradient request raises a clear ValueError, not Dr.Jit's
            out = dr.custom(_MidslopeNoGradient, out, seg.optical_depth, seg.z0, seg.z1)
        return out


class _MidslopeNoGradient(dr.CustomOp):
    """Identity on T whose derivative (either mode) raises: the mid-slope nodes sit off the
    curve, so DSM with ``placement='midslope'`` has no gradient w.r.t. the segments."""

    MESSAGE = ("placement: 'midslope' DSM nodes lie off the exact curve and are not differentiable; "
               "build with placement='curve' for gradients (node values on the curve, depths fixed)")

    def eval(self, T, *anchors):
        return dr.detach(T)

    def forward(self):
        raise ValueError(self.MESSAGE)

    def backward(self):
        raise ValueError(self.MESSAGE)

    def name(self):
        return "dsm_midslope_no_gradient"

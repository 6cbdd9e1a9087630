"""Deep shadow maps, phase A: the exact visibility curve of every texel as a polyline within
``eps_p`` (Lokovic and Veach 2000, "Deep shadow maps"; the level table and its error bound:
:mod:`.dsm`).  Vertices: per breakpoint ``(z_k, tau_left)``, ``(z_k, tau_right)`` after a
step, then the level crossings; the polyline's size is bounded before it is allocated
(:func:`check_polyline_size`).
"""
from __future__ import annotations

import math

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import backend
from .. import validation as V
from ._loops import count_sorted

#: share of epsilon given to the polyline (phase A; the compression band's is
#: :data:`~.dsm.BAND_SHARE`)
POLYLINE_SHARE = 0.25
#: Memory the build may use for its phase-A polyline and phase-B buffers (bytes; 2 GiB),
#: summed over its chunks of texels (:func:`check_polyline_size`).
MEMORY_BUDGET_BYTES = 2 * 2**30
#: Device and host bytes per polyline vertex over the build (phase A: depth, optical
#: depth, value, flag = 25; phase B: node depth, value, source = 20; host copies ~20).
BYTES_PER_VERTEX = 64


def transmittance_levels(eps_p: float) -> np.ndarray:
    """Optical-depth levels ``Lambda_n = -ln L_n`` (ascending, n >= 1) of the level table
    ``L_{n+1} = L_n exp(-sqrt(8 eps_p / L_n))`` from ``L_0 = 1`` down to the first
    ``L_N <= eps_p``.  Empty when ``eps_p >= 1``."""
    out = []
    lam, level = 0.0, 1.0
    while level > eps_p:
        lam += math.sqrt(8.0 * eps_p / level)
        level = math.exp(-lam)
        out.append(lam)
    return np.asarray(out, dtype=np.float64)


def sort_within_texels(off: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Permutation sorting ``values`` inside each CSR range ``off[t]:off[t+1]``: texels
    bucketed by count (powers of two), each bucket padded with +inf and sorted along rows."""
    counts = np.diff(off)
    order = np.arange(values.size)
    busy = np.flatnonzero(counts > 1)
    if busy.size == 0:
        return order
    bucket = np.ceil(np.log2(counts[busy])).astype(np.int64)
    for b in np.unique(bucket):
        tex = busy[bucket == b]
        c = counts[tex]
        cols = np.arange(int(c.max()))
        idx = off[tex][:, None] + cols[None, :]
        valid = cols[None, :] < c[:, None]
        block = np.where(valid, values[np.minimum(idx, values.size - 1)], np.inf)
        rows = np.argsort(block, axis=1)
        order[idx[valid]] = np.take_along_axis(idx, rows, axis=1)[valid]
    return order


def breakpoints(offsets, z0, z1, tau):
    """Sorted unique segment ends per texel and what happens at each (float64 NumPy): dict
    of ``off`` (T+1,) CSR over breakpoints, ``z`` depths, ``jump`` summed optical depth of
    zero-length segments there, ``rate_in`` / ``rate_out`` summed density (tau / length) of
    segments starting / ending there, ``active`` change of the open positive-length segments."""
    n_tex = offsets.size - 1
    counts = np.diff(offsets)
    s = tau.size
    length = z1 - z0
    pos = length > 0
    rate = np.where(pos, tau / np.where(pos, length, 1.0), 0.0)

    # events z0_0, z1_0, z0_1, z1_1, ...: texel t owns [2 off[t], 2 off[t+1])
    ev_z = np.stack([z0, z1], axis=1, dtype=np.float64).ravel()
    ev_off = 2 * offsets
    first = np.zeros(2 * s, dtype=bool)               # first event of its texel
    first[ev_off[:-1][counts > 0]] = True
    order = None                          # sorted, non-overlapping segments (e.g. ray-marched voxels)
    if not np.all((np.diff(ev_z) >= 0) | first[1:]):
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
    bp_count = np.zeros(n_tex, np.int64)
    bp_count[counts > 0] = np.add.reduceat(new, ev_off[:-1][counts > 0]) if s else np.zeros(0, np.int64)
    off = np.concatenate([[0], np.cumsum(bp_count)]).astype(np.int64)
    return dict(off=off, z=bp_z, jump=jump, rate_in=rate_in, rate_out=rate_out, active=active)


def lanes_by_length(off: np.ndarray) -> np.ndarray:
    """Non-empty CSR rows ordered by length: one lane each, so that SIMD packets run
    loops of similar length and empty texels cost nothing (DESIGN.md)."""
    counts = np.diff(off)
    lanes = np.flatnonzero(counts > 0)
    return lanes[A.order_by_count(counts[lanes])]


def prefix_optical_depth(bp):
    """``tau`` just before (``left``) and at (``right``) every breakpoint, and the slope
    ``d tau / dz`` after it (Dr.Jit Float64, one lane per texel):
    tau_left[k] = tau_right[k-1] + slope[k-1] (z[k] - z[k-1]),  tau_right[k] = tau_left[k] + jump[k];
    the slope is a Neumaier-compensated running sum of rate_in - rate_out, reset to 0
    whenever no positive-length segment is open."""
    t = backend.types()
    F64, U32, I32 = t.Float64, t.UInt32, t.Int32
    nb = bp["z"].size
    lanes = lanes_by_length(bp["off"])
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
    dr.while_loop(state, lambda k, *_: k < end, body, label="dsm_prefix_optical_depth")
    dr.eval(tau_left, tau_right, slope_out)
    return tau_left, tau_right, slope_out


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
    """ValueError (naming ``tolerance`` and the one that would fit) when the polyline's
    bound of ``2 B + crossings`` vertices (B breakpoints; the first ``n_tex`` texels, all of
    them unless ``partial``) exceeds :data:`MEMORY_BUDGET_BYTES` or
    :func:`avsm_dr.validation.memory_budget`, whichever is less."""
    bound = 2 * int(n_breakpoints) + int(n_crossings)
    need = bound * BYTES_PER_VERTEX
    budget = min(MEMORY_BUDGET_BYTES, V.memory_budget())   # and the budget of every build
    if need <= budget:
        return
    tol = eps_p / POLYLINE_SHARE
    room = budget // BYTES_PER_VERTEX - 2 * int(n_breakpoints)
    fit = "no tolerance fits: fewer texels or segments" if room <= 0 else \
        f"tolerance >= {tol * (n_crossings / room) ** 2:.2g} fits"
    raise V.MemoryBudgetError(
        f"tolerance: {tol:g} needs a polyline of up to {bound:,} vertices over "
        f"{'the first ' if partial else ''}{n_tex} texels "
        f"({need / 2**30:.3g} GiB > the {budget / 2**30:.3g} GiB of "
        f"avsm_dr.representations._dsm_polyline.MEMORY_BUDGET_BYTES or avsm_dr.validation.memory_budget()); {fit} "
        "(vertices grow as 1/sqrt(tolerance))")


def exact_polyline(offsets, z0, z1, tau, eps_p: float, dtype: str = "float64", before=(0, 0, 0)):
    """Polyline within ``eps_p`` of the exact curve (phase A), all texels at once.

    offsets (T+1,) int; z0, z1, tau (S,) float64 host arrays; ``before``: (breakpoints, level
    crossings, texels) of the chunks already built (:func:`check_polyline_size`).  Returns
    dict: ``off`` (T+1,) int64 CSR over vertices, Dr.Jit Float64 ``z``, ``tau``, ``v``, Bool
    ``left`` (the value just before a step at its depth), ``bound`` (breakpoints, crossings).
    Per breakpoint k: (z_k, tau_left), (z_k, tau_right) at a step, then the level crossings
    inside (z_k, z_{k+1}) (one lane per breakpoint, a counting and a writing pass).
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
    def below(x, strict):                 # levels below x (count_sorted over the table)
        return count_sorted(lambda i, a: dr.gather(F64, lam, i, a), 0, dr.full(U32, m, nb), x, m, strict)

    i0 = below(tr, False) if m else dr.zeros(U32, nb)
    i1 = dr.select(has_next, below(tl_next, True) if m else i0, i0)
    i1 = dr.maximum(i1, i0)
    n_cross = int((i1 - i0).numpy().astype(np.int64).sum())
    check_polyline_size(before[0] + nb, before[1] + n_cross, before[2] + n_tex, eps_p, partial=before[2] > 0)
    safe_slope = dr.select(slope > 0, slope, 1.0)

    def crossings(base, write: bool):
        """Per breakpoint, a vertex for each level not yet passed (``Lambda_i > tau_prev``) at
        its crossing depth rounded to the storage dtype (at least the next representable
        depth after the previous vertex), kept before the next breakpoint.  Counts them;
        ``write``: scatters them from ``base``."""
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

        _, n, _, _ = dr.while_loop((U32(i0), dr.zeros(U32, nb), F64(bz), F64(tr)), lambda i, *_: i < i1, body,
                                   label="dsm_level_crossings")
        return n

    out_z = out_tau = None
    per_bp = 1 + dr.select(step, U32(1), U32(0)) + crossings(None, write=False)
    dr.eval(per_bp)
    base_np = np.concatenate([[0], np.cumsum(per_bp.numpy().astype(np.int64))])      # first vertex of each
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
    return dict(off=base_np[bp["off"]].astype(np.int64), z=out_z, tau=out_tau, v=v, left=out_left, bound=(nb, n_cross))



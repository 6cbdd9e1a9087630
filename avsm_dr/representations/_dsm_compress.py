"""Deep shadow maps, phase B: Lokovic-Veach greedy compression of the phase-A polyline
(Lokovic and Veach 2000, "Deep shadow maps"; the pipeline is described in :mod:`.dsm`).

From the current origin keep the window ``[lo, hi]`` of slopes whose line passes within
``delta = BAND_SHARE * epsilon`` of every vertex seen so far (band clipped to ``[0, 1]``,
``hi <= 0``); when it empties, emit a node and restart from it.  ``placement='midslope'``
(the paper's) puts the node on the mid-slope line; ``placement='curve'`` keeps nodes on
polyline vertices (exact curve values).  One Dr.Jit lane per texel.
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import backend
from ._dsm_polyline import lanes_by_length

PLACEMENTS = ("midslope", "curve")
#: share of epsilon given to the compression band (phase B)
BAND_SHARE = 0.5


def compress(poly, delta: float, placement: str = "midslope"):
    """Greedy slope-window compression of every texel's polyline (:func:`~._dsm_polyline.exact_polyline`)
    within ``delta``.  Returns (counts (T,) int64, z, v, src): float64 NumPy node depths /
    values and the vertex whose depth each node takes, in CSR by counts."""
    t = backend.types()
    F64, U32, Bool = t.Float64, t.UInt32, t.Bool
    off = poly["off"]
    n_tex = off.size - 1
    nv = int(off[-1])
    if nv == 0:
        e = np.zeros(0)
        return np.zeros(n_tex, np.int64), e, e, np.zeros(0, np.int64)
    lanes = lanes_by_length(off)
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

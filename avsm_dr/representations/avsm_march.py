"""Engine-style AVSM: nodes placed while marching the light ray, only where the
transmittance leaves the exponential extrapolation of the last node; a variable node
count per texel up to a cap, compacted; node depths in half precision relative to the
texel's depth range.

March (one Dr.Jit lane per texel, float64) over the exact curve's points in depth order
(:mod:`._curve`), each with ``T`` and the local extinction ``s`` (d tau / dz behind it).  The
first point is a node; the last node ``(d_n, T_n, s_n)`` predicts ``P(x) = T_n exp(-s_n (x -
d_n))``.  At a point with ``|T_k - P(x_k)| > max(abs_error, rel_error T_k)`` the previous
point becomes a node, and ``x_k`` too if it still departs from the new prediction (a step:
two nodes at one depth).  The last point is always a node.  A node added to a full texel
(``nodes`` = cap) pushes out the interior node of smallest AVSM area metric (Salvi et al.
2010, sec. 3.2; ties: the deepest; first and last never).

Storage (CSR): a 4-byte offset and the depth range ``[lo, hi]`` (2 floats of the segments'
dtype) per texel, per node a float16 depth ``q = (d - lo) / (hi - lo)`` in [0, 1] (error at
most (hi - lo) 2^-12; dequantised as ``lo + q (hi - lo)``, monotone) and its T (segments'
dtype); ``precision=p``: q and T in ``p``, the range in float32.  Lookup:
:func:`.avsm.csr_lookup` (default 'exp').  Node values are the exact curve's (float64 march),
with its gradients at the fixed node depths.
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from .. import backend
from . import _curve
from ._avsm_insertion import remove_refit
from .avsm import INTERPOLATIONS, csr_lookup
from .base import Representation
from ._loops import chunk_stop
from .dsm import concatenate, host_range, next_chunk_segments
from ._dsm_polyline import lanes_by_length
from ._precision import PRECISIONS, Stored
from .registry import register
from .schema import Param, Schema


def march(pts: dict, cap: int, abs_error: float, rel_error: float):
    """Run the march over every texel's curve points (one Dr.Jit Float64 lane per
    non-empty texel).  Returns (counts (T,) int64, src (sum counts,) int64): the point
    index of every node, in depth order, CSR by counts."""
    t = backend.types()
    F64, U32, Bool = t.Float64, t.UInt32, t.Bool
    off = pts["off"]
    n_tex = off.size - 1
    lanes_np = lanes_by_length(off)
    if lanes_np.size == 0:
        return np.zeros(n_tex, np.int64), np.zeros(0, np.int64)
    L = lanes_np.size
    start = U32(off[lanes_np].astype(np.uint32))
    end = U32(off[lanes_np + 1].astype(np.uint32))
    px, pv, ps = F64(pts["z"]), F64(pts["v"]), F64(pts["slope"])

    def append(cnt, d, v, src, active, x, tv, k):
        """Node (x, tv, point k) after the last one where ``active``; a full list drops
        its smallest-area interior node."""
        full = cnt == cap
        old = (d, v, src)
        ext = [[dr.select(U32(j) == cnt, new, o[j]) for j in range(cap)] + [new] for o, new in zip(old, (x, tv, k))]
        out = [[dr.select(active, dr.select(full, r[j], e[j]), o[j]) for j in range(cap)]
               for o, e, r in zip(old, ext, remove_refit(*ext[:2], None, "area", ext[2:]))]
        return dr.select(active & ~full, cnt + 1, cnt), *out

    # state: k next point; cnt nodes held; (dn, tn, sn) last node and its extinction;
    # (xp, tp, sp, kp) previous point; p_node: the previous point is a node;
    # node depths d_0.., values v_0.., source points src_0..
    def body(k, cnt, dn, tn, sn, xp, tp, sp, kp, p_node, *lists):
        d, v, src = list(lists[:cap]), list(lists[cap:2 * cap]), list(lists[2 * cap:])
        xk, tk, sk = dr.gather(F64, px, k), dr.gather(F64, pv, k), dr.gather(F64, ps, k)
        tol = dr.maximum(abs_error, rel_error * tk)
        depart = dr.abs(tk - tn * dr.exp(-sn * (xk - dn))) > tol
        add_prev = depart & ~p_node
        cnt, d, v, src = append(cnt, d, v, src, add_prev, xp, tp, kp)
        dn, tn, sn = (dr.select(add_prev, p, n) for p, n in zip((xp, tp, sp), (dn, tn, sn)))
        add_cur = depart & (dr.abs(tk - tn * dr.exp(-sn * (xk - dn))) > tol)
        cnt, d, v, src = append(cnt, d, v, src, add_cur, xk, tk, k)
        dn, tn, sn = (dr.select(add_cur, p, n) for p, n in zip((xk, tk, sk), (dn, tn, sn)))
        return (k + 1, cnt, dn, tn, sn, xk, tk, sk, k, add_cur, *d, *v, *src)

    x0, t0, s0 = dr.gather(F64, px, start), dr.gather(F64, pv, start), dr.gather(F64, ps, start)
    state = (start + 1, dr.full(U32, 1, L), x0, t0, s0, F64(x0), F64(t0), F64(s0), U32(start),
             dr.full(Bool, True, L), *[F64(x0) for _ in range(cap)], *[F64(t0) for _ in range(cap)],
             *[U32(start) for _ in range(cap)])
    k, cnt, dn, tn, sn, xp, tp, sp, kp, p_node, *lists = dr.while_loop(state, lambda k, *_: k < end, body,
                                                                         label="avsm_march")
    d, v, src = lists[:cap], lists[cap:2 * cap], lists[2 * cap:]
    # the last point is always a node
    cnt, d, v, src = append(cnt, d, v, src, ~p_node, xp, tp, kp)
    dr.eval(cnt, src)
    cnt_np = np.asarray(cnt.numpy(), np.int64)
    src_np = np.stack([np.asarray(s.numpy(), np.int64) for s in src], axis=1)     # (L, cap)
    counts = np.zeros(n_tex, np.int64)
    counts[lanes_np] = cnt_np
    by_texel = np.argsort(lanes_np)                       # rows in texel order, nodes in row order: CSR
    keep = np.arange(cap)[None, :] < cnt_np[by_texel, None]
    return counts, src_np[by_texel][keep]


@register("avsm_march")
class AVSMMarch(Representation):
    """Engine-style AVSM (module docstring).  Attributes: ``node_counts``, ``node_offsets``
    as DSM's; ``range_lo``/``range_hi`` (Dr.Jit, per texel); ``node_q`` (Dr.Jit Float16,
    relative depths), ``node_value`` (T)."""

    schema = Schema(
        params=(
            Param("nodes", "int", 8, "cap on the nodes per texel", min=2, max=64),
            Param("abs_error", "float", 0.002, "absolute departure from the extrapolation that adds a node",
                  min=0.0),
            Param("rel_error", "float", 0.01, "relative departure (x T) that adds a node", min=0.0),
            Param("interpolation", "choice", "exp", "between nodes: 'exp' (uniform density) or 'linear'",
                  choices=INTERPOLATIONS),
        ),
        size="nodes", sweep=(2, 4, 6, 8, 12, 16, 24, 32), quick_sweep=(2, 4, 8, 16),
        examples=({"nodes": 4}, {"nodes": 8, "abs_error": 0.0, "rel_error": 0.0, "interpolation": "linear"}),
        headline={"nodes": 8},
        summary="AVSM placed while ray marching (error-driven, variable count <= cap, fp16 relative depths)",
        paper="Salvi et al. 2010 (engine-style variant)")

    def _resolve(self):
        self.cap = self.params["nodes"]
        self._check_node_memory()

    def _build(self):
        seg, P, t = self.segments, self.params, backend.types()
        offsets, n_tex, Float = seg.offsets, seg.n_texels, seg.Float
        counts, parts, t0, out_bytes = np.zeros(n_tex, np.int64), [], 0, 0
        while t0 < n_tex:           # chunks of whole texels (as DSM's): the nodes do not depend on them
            t1 = chunk_stop(offsets, t0, next_chunk_segments(out_bytes, int(offsets[t0]), seg.n_segments))
            s0, s1 = int(offsets[t0]), int(offsets[t1])
            pts = _curve.host_curve_points(offsets[t0:t1 + 1] - s0,
                                           *(host_range(x, s0, s1) for x in (seg.z0, seg.z1, seg.optical_depth)))
            counts[t0:t1], src = march(pts, self.cap, P["abs_error"], P["rel_error"])
            parts.append(self._chunk_nodes(pts, counts[t0:t1], src))
            out_bytes += sum(a.nbytes for a in parts[-1][:4]) + 4 * (t1 - t0)
            t0 = t1
        self._set_nodes(counts)
        lo, hi, q, value, z, left = (concatenate(parts, k) for k in range(6))
        self.range_lo, self.range_hi = Float(lo), Float(hi)
        self.node_q = t.Float16(q) if self.precision is None else Float(q)
        self.node_value = Float(value)
        if seg.requires_grad:
            self.node_value = _curve.attach_exact_gradients(seg, self.node_value, np.repeat(np.arange(n_tex), counts),
                                                            z, left)

    def _chunk_nodes(self, pts, counts, src):
        """(range_lo, range_hi, q, value) of a chunk's texels and nodes in the stored dtypes
        (q: float16 on store, else quantised after the build, :meth:`_stored`), and the
        nodes' float64 depths and left flags where the segments carry gradients."""
        dt = np.float32 if self.segments.dtype == "float32" else np.float64
        off, z = pts["off"], pts["z"]
        nz = np.diff(off) > 0
        lo, hi = np.zeros(counts.size), np.ones(counts.size)
        lo[nz], hi[nz] = z[off[:-1][nz]], z[off[1:][nz] - 1]
        tex = np.repeat(np.arange(counts.size), counts)
        span = (hi - lo)[tex]
        q = np.clip(np.where(span > 0, (z[src] - lo[tex]) / np.where(span > 0, span, 1.0), 0.0), 0.0, 1.0)
        grad = self.segments.requires_grad
        return (lo.astype(dt), hi.astype(dt), q.astype(np.float16 if self.precision is None else dt),
                pts["v"][src].astype(dt), z[src] if grad else np.zeros(0),
                pts["left"][src] if grad else np.zeros(0, bool))

    precisions = PRECISIONS

    def _stored(self):
        return (Stored("node_q", "unit", "csr"), Stored("node_value", "transmittance", "csr"),
                Stored("range_lo", "range", "texel"), Stored("range_hi", "range", "texel"))

    variable_size = True

    def texel_payload_bytes(self):
        """Sparse layout: a texel's depth range and its (2-byte depth, value) nodes."""
        item = self.segments.itemsize
        return self._csr_payload(self.node_counts, 2 + item, 2 * item)

    def _native_bytes(self) -> float:
        mean = float(self.node_counts.mean()) if self.node_counts.size else 0.0
        item = self.segments.itemsize
        return 4 + 2 * item + mean * (2 + item)

    def node_depths(self) -> np.ndarray:
        """Dequantised depths of every node (float64 NumPy, CSR order)."""
        tex = np.repeat(np.arange(self.n_texels), self.node_counts)
        lo = np.asarray(self.range_lo.numpy(), np.float64)[tex]
        hi = np.asarray(self.range_hi.numpy(), np.float64)[tex]
        return lo + np.asarray(self.node_q.numpy(), np.float64) * (hi - lo)

    def _eval_texels(self, texel, depth):
        Float = self.Float
        lo = dr.gather(Float, self.range_lo, texel)
        span = dr.gather(Float, self.range_hi, texel) - lo

        def z(i, active=True):                  # dequantised node depth
            return lo + Float(dr.gather(type(self.node_q), self.node_q, i, active)) * span

        return csr_lookup(self._offsets_dr, self._max_nodes, z, self.node_value, texel, depth,
                          self.params["interpolation"])

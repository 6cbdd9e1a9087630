"""Deep shadow maps (Lokovic and Veach 2000, "Deep shadow maps", SIGGRAPH; Salvi et al.
2010, "Adaptive Volumetric Shadow Maps", secs. 2, 3.2 and 5 compare AVSM against them).

Each texel stores a variable number of nodes ``(z_i, V_i)`` (depth, transmittance) within
a tolerance ``epsilon`` of its exact visibility ``V(z)``: ``|DSM(z) - V(z)| <= epsilon`` for
every depth z (Lokovic-Veach error bound).

1. **Exact curve as a polyline** (phase A, :mod:`._dsm_polyline`).  ``V(z) = exp(-tau(z))``
   with ``tau`` piecewise linear between the texel's sorted unique segment ends
   ("breakpoints"), steps at zero-length segments (a receiver at a step depth is behind it,
   as in :mod:`.exact`).  The polyline adds vertices where ``V`` crosses the levels ::

       L_{n+1} = L_n exp(-kappa_n),  kappa_n = sqrt(8 eps_p / L_n),  L_N <= eps_p,

   so each piece lies in one band ``[L_{n+1}, L_n]`` with chord error
   ``max|V''| h^2 / 8 = L_n kappa^2 / 8 <= eps_p``; at most ``2 B + N`` vertices per texel
   (B breakpoints, N ~ sqrt(1 / eps_p) levels).  Inserted depths are rounded to the storage
   dtype (a crossing rounding onto the previous vertex moves to the next representable
   depth) and take the exact curve's value there.  ``eps_p = epsilon / 4``.

2. **Greedy compression** (phase B, :func:`compress`, Lokovic-Veach's algorithm): from
   the current origin keep the window ``[lo, hi]`` of slopes whose line passes within
   ``delta = epsilon / 2`` of every vertex seen so far (band clipped to ``[0, 1]``,
   ``hi <= 0``: non-increasing); when it empties, emit a node at the last vertex that
   fitted and restart from it.  ``placement="midslope"`` (default, the paper's): the node
   lies on the mid-slope line ``(lo + hi) / 2``; ``placement="curve"``: nodes are polyline
   vertices (exact curve values, differentiable with the node depths held fixed).
   Error: ``|DSM - V| <= eps_p + delta = 3 epsilon / 4`` in exact arithmetic; the remaining
   ``epsilon / 4`` absorbs the rounding of inserted depths.  Phases A and B run in float64 on
   chunks of texels (:func:`next_chunk_segments`; the nodes do not depend on the chunking).

3. **Lookup** (phase C): :func:`.avsm.csr_lookup`, linear between nodes.  Storage: per
   texel its (depth, value) nodes in the segments' dtype and a 4-byte CSR offset.
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import backend
from . import _curve
from .registry import register
from .avsm import csr_lookup
from .base import Representation
from ._precision import PRECISIONS, Stored
from .schema import Param, Schema
from ._dsm_polyline import POLYLINE_SHARE, exact_polyline, lanes_by_length

#: smallest accepted tolerance (the level table has ~1/sqrt(2 eps_p) entries)
MIN_TOLERANCE = 1e-9
PLACEMENTS = ("midslope", "curve")
#: share of epsilon given to the compression band (phase B)
BAND_SHARE = 0.5


def compress(poly, delta: float, placement: str = "midslope"):
    """Phase B on every texel's polyline within ``delta``: (counts (T,) int64, z, v, src), the
    float64 NumPy nodes and the vertex whose depth each takes, CSR by counts."""
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

    def vertex(k, zo):
        """Vertex k, its band of admissible values [max(v - delta, 0), min(v + delta, 1)], whether
        it lies at the origin's depth zo and its (safe) depth step from it."""
        zk, vk = dr.gather(F64, pz, k), dr.gather(F64, pv, k)
        dz = zk - zo
        vertical = dz <= 0
        return zk, vk, dr.maximum(vk - delta, 0.0), dr.minimum(vk + delta, 1.0), vertical, dr.select(vertical, 1.0, dz)

    def emit(cnt, active, z_new, v_new, src):
        idx = start + cnt
        for buf, x in ((out_z, z_new), (out_v, v_new), (out_src, src)):
            dr.scatter(buf, x, idx, active)
        return cnt + dr.select(active, U32(1), U32(0))

    zo, vo = dr.gather(F64, pz, start), dr.gather(F64, pv, start)
    emit(0, True, zo, vo, start)                # the first vertex is always the first node

    def cond(k, *_):
        return k < end

    if placement == "midslope":
        # state: k next vertex, (zo, vo) origin, [lo, hi] slope window, has_w window
        # holds a constraint, (zp, ip) last vertex that fitted, cnt nodes emitted
        def body(k, zo, vo, lo, hi, has_w, zp, ip, cnt):
            zk, vk, a, b, vertical, sdz = vertex(k, zo)
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
        k, zo, vo, lo, hi, has_w, zp, ip, cnt = dr.while_loop(state, cond, body, label="dsm_compress_midslope")
        tail, v_tail = has_w, dr.maximum(vo + 0.5 * (lo + hi) * (zp - zo), 0.0)
    elif placement == "curve":
        # state: k next vertex, (zo, vo) origin, [lo, hi] slopes of chords that keep the
        # vertices between origin and k within delta, (zp, vp, ip) last feasible vertex
        def body(k, zo, vo, io, lo, hi, zp, vp, ip, cnt):
            zk, vk, a, b, vertical, sdz = vertex(k, zo)
            sk = (vk - vo) / sdz
            feasible = vertical | ((sk >= lo) & (sk <= hi))
            nlo = dr.select(vertical, dr.select((vo >= a) & (vo <= b), lo, inf), dr.maximum(lo, (a - vo) / sdz))
            nhi = dr.select(vertical, hi, dr.minimum(hi, (b - vo) / sdz))
            brk = ~feasible
            cnt = emit(cnt, brk, zp, vp, ip)
            lo = dr.select(feasible, nlo, -inf)
            hi = dr.select(feasible, nhi, inf)
            zo, vo, io = (dr.select(brk, p, o) for p, o in zip((zp, vp, ip), (zo, vo, io)))
            zp, vp, ip = (dr.select(feasible, x, p) for x, p in zip((zk, vk, k), (zp, vp, ip)))
            k = dr.select(feasible, k + 1, k)
            return k, zo, vo, io, lo, hi, zp, vp, ip, cnt

        state = (start + 1, zo, vo, U32(start), dr.full(F64, -inf, n), dr.full(F64, inf, n),
                 F64(zo), F64(vo), U32(start), dr.full(U32, 1, n))
        k, zo, vo, io, lo, hi, zp, vp, ip, cnt = dr.while_loop(state, cond, body, label="dsm_compress_curve")
        tail, v_tail = ip != io, vp
    else:
        raise ValueError(f"placement: expected one of {PLACEMENTS}, got {placement!r}")
    flat_tail = (lo <= 0) & (hi >= 0)          # the origin's value holds to the end
    cnt = emit(cnt, tail & ~flat_tail, zp, v_tail, ip)

    dr.eval(out_z, out_v, out_src, cnt)
    counts = np.zeros(n_tex, np.int64)
    counts[lanes] = cnt.numpy()
    # compact: node j of texel i sits at off[i] + j in the output buffer
    node_off = np.concatenate([[0], np.cumsum(counts)])
    idx = np.repeat(off[:-1], counts) + (np.arange(node_off[-1]) - np.repeat(node_off[:-1], counts))
    return counts, out_z.numpy()[idx], out_v.numpy()[idx], out_src.numpy()[idx].astype(np.int64)

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


@register("dsm")
class DeepShadowMap(Representation):
    """Deep shadow map with error bound ``tolerance`` (module docstring; default 0.01, the
    value of Salvi et al. 2010, table 1).

    Attributes: ``node_counts`` (T,) and ``node_offsets`` (T+1,) int64 NumPy; ``node_depth``,
    ``node_value`` Dr.Jit arrays in CSR order; ``node_left`` (bool NumPy: the node's vertex
    is the value just before a step at its depth); ``n_polyline_vertices`` (T,).  ValueError
    naming the tolerance that fits, before allocating, when the polyline summed over the
    chunks would exceed its budget (:func:`._dsm_polyline.check_polyline_size`)."""

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
        paper="Lokovic & Veach 2000")

    def _resolve(self):
        self.tolerance = self.params["tolerance"]
        self.placement = self.params["placement"]
        self.differentiable = self.placement == "curve"        # node values on the exact curve

    def _build(self):
        seg = self.segments
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
            poly = exact_polyline(off, *(host_range(x, s0, s1) for x in (seg.z0, seg.z1, seg.optical_depth)),
                                  POLYLINE_SHARE * self.tolerance, seg.dtype, before=(*bound, t0))
            bound = (bound[0] + poly["bound"][0], bound[1] + poly["bound"][1])
            del poly["tau"]             # only v is compressed
            self.n_polyline_vertices[t0:t1] = np.diff(poly["off"])
            c, nz, nv, src = compress(poly, BAND_SHARE * self.tolerance, self.placement)
            counts[t0:t1] = c
            left = poly["left"].numpy()[src] if src.size else np.zeros(0, bool)
            del poly
            parts.append((nz.astype(seg.dtype), nv.astype(seg.dtype), left))
            node_bytes += 2 * nz.size * seg.itemsize
            del nz, nv, src
            t0 = t1
        self._set_nodes(counts)
        nz, nv, self.node_left = (concatenate(parts, k) for k in range(3))
        self.node_depth, self.node_value = seg.Float(nz), seg.Float(nv)
        if self.placement == "curve":         # the exact curve's gradients at fixed node depths
            self.node_value = _curve.attach_exact_gradients(seg, self.node_value, np.repeat(np.arange(n_tex), counts),
                                                            nz, self.node_left)

    precisions = PRECISIONS

    def _stored(self):
        return (Stored("node_depth", "depth", "csr"), Stored("node_value", "transmittance", "csr"))

    variable_size = True                    # sparse payload: the (depth, value) pairs

    def _native_bytes(self) -> float:
        mean = float(self.node_counts.mean()) if self.node_counts.size else 0.0
        return 2 * self.segments.itemsize * mean + 4

    def nodes_numpy(self, texel: int) -> tuple[np.ndarray, np.ndarray]:
        """(depths, values) of one texel's nodes as float64 NumPy arrays."""
        s = slice(int(self.node_offsets[texel]), int(self.node_offsets[texel + 1]))
        return tuple(np.asarray(dr.detach(x).numpy(), np.float64)[s] for x in (self.node_depth, self.node_value))

    def _eval_texels(self, texel, depth):
        zs = self.node_depth
        out = dr.clip(csr_lookup(self._offsets_dr, self._max_nodes, lambda i, a: dr.gather(self.Float, zs, i, a),
                                 self.node_value, texel, depth, "linear"), 0.0, 1.0)
        if self.placement == "midslope" and self.segments.requires_grad and self._max_nodes:
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

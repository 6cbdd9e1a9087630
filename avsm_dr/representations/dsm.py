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
kept in the storage dtype.  The build's peak stays within a few times the output's size.
Texels are independent, so the nodes do not depend on the chunking.

Code: phase A (and the polyline's memory bound) in :mod:`._dsm_polyline`, phase B in
:mod:`._dsm_compress`, the chunks in :mod:`._dsm_chunks`, the representation (build loop,
storage, phase C) here; the public names of those modules are re-exported here.
"""
from __future__ import annotations

import math

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import backend
from .registry import register
from .base import Representation
from ._precision import PRECISIONS, Stored
from .schema import Param, Schema
from .exact import exact_values
# phase A, phase B and the chunks of the build live in private modules; their public names
# are re-exported here, their old home
from ._dsm_polyline import (  # noqa: F401
    BYTES_PER_VERTEX, MEMORY_BUDGET_BYTES, POLYLINE_SHARE, breakpoints, check_polyline_size, exact_polyline,
    next_up, prefix_optical_depth, sort_within_texels, transmittance_levels)
from ._dsm_compress import BAND_SHARE, PLACEMENTS, compress  # noqa: F401
from ._dsm_chunks import (  # noqa: F401
    MAX_CHUNK_SEGMENTS, MIN_CHUNK_SEGMENTS, TEMP_BYTES_PER_SEGMENT, chunk_end, concatenate, host_range,
    next_chunk_segments)

#: smallest accepted tolerance (the level table has ~1/sqrt(2 eps_p) entries)
MIN_TOLERANCE = 1e-9


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
    ``_dsm_polyline.MEMORY_BUDGET_BYTES`` (2 GiB) raises ValueError naming the tolerance that fits,
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
            poly = exact_polyline(off, *(host_range(x, s0, s1) for x in (seg.z0, seg.z1, seg.optical_depth)),
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
        nz, nv, self.node_left = (concatenate(parts, k) for k in range(3))
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

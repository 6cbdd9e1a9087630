"""Opacity shadow maps (Kim and Neumann 2001) as the piecewise-constant basis of
Jansen and Bavoil 2010, "Fourier Opacity Mapping", sec. 5.1.

``n`` uniform slices over ``[near, far]``, in the simplified form of sec. 5.1::

    f_k(u) = H(u - k/n) - H(u - (k+1)/n)          (slice indicator, the last slice closed)
    g_k(u) = n [(u - k/n) H(u - k/n) - (u - (k+1)/n) H(u - (k+1)/n)] = clamp(n u - k, 0, 1)

so ``a_k`` is the optical depth inside slice ``k`` (a segment adds ``tau`` times the
fraction of its length inside the slice; a zero-length one adds ``tau`` to the slice
holding it) and the optical depth ``D(u) = sum_k a_k g_k(u)`` is piecewise linear,
exact at the slice boundaries ``u = j / n``.

Stored form (texel-major, flat ``[texel * n + j - 1]``): the cumulative optical depths
``C_j = D(j / n) = sum_{k<j} a_k``, ``j = 1..n`` (float64 running sums; ``C_0 = 0``
implicit), so a lookup is ``D(u) = min(C_j + (C_{j+1} - C_j)(n u - j), C_{j+1})`` with
``j = min(floor(n u), n - 1)``; the ``min`` keeps ``D`` non-decreasing under rounding, so
``T`` is monotone (to one ulp of Dr.Jit's float32 ``exp``).  Projection: four scatters per
segment whatever ``n`` (``_project``); depth range and clipping as :mod:`.basis`.
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import backend
from .registry import register
from ._precision import Stored
from .basis import MAX_COEFFICIENTS, BasisRepresentation
from .basis_functions import Basis, clip_segment, register_basis
from .schema import DEPTH_RANGE, FAR, NEAR, Param, Schema


@register_basis("piecewise_constant")
class PiecewiseConstantBasis(Basis):
    """``n`` slice indicators on [0, 1] (Jansen and Bavoil 2010, sec. 5.1, simplified scaling)."""

    monotone = True
    arg = "slices"

    def _slice(self, u):
        """Index of the slice holding u (the last slice includes u = 1), as Float."""
        return dr.minimum(dr.floor(self.n * u), self.n - 1)

    def f(self, u):
        j = self._slice(u)
        return [dr.select(j == k, 1, 0 * u) for k in range(self.n)]

    def g(self, u):
        return [dr.clip(self.n * u - k, 0, 1) for k in range(self.n)]

    indexed = True

    def f_at(self, j, u):
        return dr.select(self._slice(u) == type(u)(j), 1.0, 0.0)

    def g_at(self, j, u):
        return dr.clip(self.n * u - type(u)(j), 0, 1)

    def average_at(self, j, u0, u1):
        k = type(u0)(j)
        du = u1 - u0
        overlap = dr.maximum(dr.minimum(u1, (k + 1) / self.n) - dr.maximum(u0, k / self.n), 0)
        return dr.select(du > 0, overlap / dr.select(du > 0, du, 1), self.f_at(j, u0))

    def average(self, u0, u1):
        """Fraction of [u0, u1] inside each slice (overlap / length, no cancellation);
        the slice indicator for a zero-length segment."""
        du = u1 - u0
        safe = dr.select(du > 0, du, 1)
        point = self.f(u0)
        return [dr.select(du > 0, dr.maximum(dr.minimum(u1, (k + 1) / self.n) - dr.maximum(u0, k / self.n), 0) / safe,
                          point[k]) for k in range(self.n)]


#: Texel chunks of the build without gradients (:meth:`OpacityShadowMap._build_chunked`):
#: one chunk's parts P and R at a time, 2 / BUILD_CHUNKS of the output's size.
BUILD_CHUNKS = 2


@register("osm")
class OpacityShadowMap(BasisRepresentation):
    """Opacity shadow map: n ``slices``; ``coefficients``: a_k, the optical depth per slice;
    ``_cum``: the stored C_1..C_n, flat (``precision``: coded as ``optical_depth``)."""

    schema = Schema(
        params=(
            Param("slices", "int", 16, "n uniform slices over [near, far]", min=1, max=MAX_COEFFICIENTS),
            NEAR, FAR, DEPTH_RANGE,
        ),
        size="slices", sweep=(4, 8, 16, 32, 64), quick_sweep=(4, 16, 32),
        examples=({"slices": 16},),
        headline={"slices": 32},
        summary="n uniform opacity slices",
        paper="Kim & Neumann 2001")

    def _make_basis(self):
        return PiecewiseConstantBasis(self.params["slices"])

    def _build_bytes(self, K: int) -> float:
        """Without gradients (:meth:`_build_chunked`): a_k, C_j and one chunk's parts; with
        them (:meth:`_project`): P, R, their float64 prefix sums, the store and ~12 words per
        segment."""
        seg = self.segments
        T, it = seg.n_texels, seg.itemsize
        if not seg.requires_grad:
            return (2.0 + 2.0 / BUILD_CHUNKS) * it * T * K + 4.0 * T
        return (8.0 * it + 32.0) * T * K + 12.0 * it * seg.n_segments

    def _build(self):
        if self.segments.n_segments and not self.segments.requires_grad:
            self._coef, self._cum = self._build_chunked()
            return
        super()._build()
        # ---- stored form: C_{j+1} = sum_{k<=j} a_k, flat texel-major [texel * n + j]
        F64 = backend.types().Float64        # summed in float64 whatever the storage
        self._cum = self.Float(dr.block_prefix_sum(F64(self._coef), self.basis.n, exclusive=False))
        dr.eval(self._cum)

    def _build_chunked(self):
        """(a_k, C_j), flat texel-major, without gradients, in :data:`BUILD_CHUNKS` chunks of
        texels: one lane per non-empty texel adds its segments' parts in CSR order into its
        rows of P and R (:meth:`_add_parts`, no atomics), then walks its slices with float64
        running sums: the operations, in order, of :meth:`_project` (the same bits)."""
        seg, n = self.segments, self.basis.n
        t = backend.types()
        Float, UInt32, F64 = seg.Float, t.UInt32, t.Float64
        T = seg.n_texels
        self._check_index_range(T, n)
        a_all, c_all = dr.zeros(Float, T * n), dr.zeros(Float, T * n)
        lanes = np.nonzero(seg.counts > 0)[0]
        offsets = seg.offsets_dr()
        z0, z1, tau = seg.z0, seg.z1, seg.optical_depth
        rows = -(-T // BUILD_CHUNKS)
        for r0 in range(0, T, rows):         # rows r0 .. r0 + m - 1, their non-empty texels
            sel = lanes[np.searchsorted(lanes, r0):np.searchsorted(lanes, min(T, r0 + rows))]
            if not sel.size:
                continue
            texel, m = A.to_uint32(sel), min(T, r0 + rows) - r0
            first, stop = dr.gather(UInt32, offsets, texel), dr.gather(UInt32, offsets, texel + 1)
            row = (texel - dr.opaque(UInt32, r0)) * n          # the texel's first slot in the chunk
            P, Rd = dr.zeros(Float, m * n), dr.zeros(Float, m * n)

            def body(i):
                self._add_parts(P, Rd, dr.gather(Float, z0, i), dr.gather(Float, z1, i), dr.gather(Float, tau, i),
                                texel, row, mode=dr.ReduceMode.NoConflicts)
                return (i + 1,)

            dr.while_loop((first,), lambda i: i < stop, body, label="osm_project")
            dr.eval(P, Rd)
            out = texel * n

            def sums(j, r, c):
                r = r + F64(dr.gather(Float, Rd, row + j))
                a = dr.gather(Float, P, row + j) + Float(r)
                # clamp a negative rounding residual of R's +r / -r pairs (as in _project)
                a = dr.select(a < 0, 0, a)
                c = c + F64(a)
                dr.scatter(a_all, a, out + j)
                dr.scatter(c_all, Float(c), out + j)
                return j + 1, r, c

            w = dr.width(texel)
            dr.while_loop((dr.zeros(UInt32, w), dr.zeros(F64, w), dr.zeros(F64, w)), lambda j, r, c: j < n, sums,
                          label="osm_sums")
            dr.eval(a_all, c_all)
        return a_all, c_all

    def _add_parts(self, P, Rd, z0, z1, tau, texel, row, mode=dr.ReduceMode.Auto):
        """Add segments' parts into P (end slices) and Rd (difference array of full-slice
        rates) at ``row + j`` (row: the texel's first slot); see :meth:`_project`."""
        n, UInt32 = self.basis.n, backend.types().UInt32
        near, span = self._range(texel if self._per_texel else None)
        c0, c1, tau_in, tau_front = clip_segment(z0, z1, tau, near, span)
        t0, t1 = n * c0, n * c1                 # segment in slice units
        j0 = dr.minimum(dr.floor(t0), n - 1)    # first slice (the last one is closed)
        j1 = dr.minimum(dr.floor(t1), n - 1)    # last slice
        same = j0 == j1
        dt = t1 - t0
        rate = tau_in / dr.select(dt > 0, dt, 1)
        i0, i1 = row + UInt32(j0), row + UInt32(j1)
        add = dr.ReduceOp.Add
        dr.scatter_reduce(add, P, dr.select(same, tau_in, rate * (j0 + 1 - t0)), i0, mode=mode)
        dr.scatter_reduce(add, P, rate * (t1 - j1), i1, active=~same, mode=mode)
        full = j1 > j0 + 1
        dr.scatter_reduce(add, Rd, rate, i0 + 1, active=full, mode=mode)
        dr.scatter_reduce(add, Rd, -rate, i1, active=full, mode=mode)
        dr.scatter_reduce(add, P, tau_front, row, active=tau_front > 0, mode=mode)

    def _project(self):
        """a_k with four scatters per segment whatever n (instead of n): in slice units
        t = n u a segment [t0, t1] covers slices j0 = slice(t0) .. j1 = slice(t1) with
        rate r = tau_in / (t1 - t0) per slice; the end slices get r (j0 + 1 - t0) and
        r (t1 - j1) (all of tau_in when j0 = j1), the full slices j0 < j < j1 get r through
        a difference array R (R[j0 + 1] += r, R[j1] -= r, only when j1 > j0 + 1 so that
        r <= tau and the running sum's rounding stays below eps sum tau)."""
        seg, n = self.segments, self.basis.n
        Float, T = seg.Float, seg.n_texels
        self._check_index_range(T, n)
        # texel-major [texel * n + j]: a texel's scatters stay in one cache line or two
        P = dr.zeros(Float, n * T)                  # end-slice parts
        Rd = dr.zeros(Float, n * T)                 # difference array of full-slice rates
        if seg.n_segments:      # with gradients (reverse mode: no symbolic loop); otherwise _build_chunked
            texel = seg.texel_of_segment()
            self._add_parts(P, Rd, seg.z0, seg.z1, seg.optical_depth, texel, texel * n)
        # a_j = P_j + sum_{i <= j} R_i: a prefix sum inside each texel's block of n, in float64
        a = P + Float(dr.block_prefix_sum(backend.types().Float64(Rd), n, exclusive=False))
        # clamp a negative rounding residual of R's +r / -r pairs (D must not decrease)
        a = dr.select(a < 0, 0, a)
        dr.eval(a)
        return a

    #: Reconstruction reads, and ``precision`` quantises, the cumulative sums (non-negative,
    #: non-decreasing: the codes stay so, T stays monotone); ``coefficients`` stay exact.
    _stored_attr = "_cum"

    def _stored(self):
        """The cumulative sums as optical depths (:mod:`._precision`), the range as the basis'."""
        return (Stored("_cum", "optical_depth", "flat"),) + super()._stored()[1:]

    def _reconstruct_from(self, store, row, u):
        UInt32, Float = backend.types().UInt32, self.Float
        n = self.basis.n
        t = n * u                                        # position in slice units, [0, n]
        j = dr.minimum(dr.floor(t), n - 1)               # slice holding the receiver
        i = row * n + UInt32(j)
        c0 = dr.gather(Float, store, i - 1, j > 0)       # C_j (C_0 = 0)
        c1 = dr.gather(Float, store, i)                  # C_{j+1}
        return dr.minimum(c0 + (c1 - c0) * (t - j), c1)

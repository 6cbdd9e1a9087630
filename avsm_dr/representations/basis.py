"""Linear transmittance representations: projection of the absorption onto a basis
(Jansen and Bavoil 2010, "Fourier Opacity Mapping", I3D, sec. 5).

Depth is normalised per range ``u = (z - near) / (far - near)`` in [0, 1].  The
absorption ``sigma(u)`` of a texel is projected onto projection functions ``f_k``
and rebuilt from reconstruction integrals ``g_k``::

    a_k  = int_0^1 sigma(u) f_k(u) du                       (coefficient map, sec. 5)
    D(u) = sum_k a_k g_k(u),   T(u) = clamp(exp(-D(u)), 0, 1)

For an orthonormal basis ``g_k = F_k = int_0^u f_k``; scaled pairs (the paper's Fourier
``a'_k``, the piecewise-constant form of sec. 5.1) override ``g``.  A segment ``[u0, u1]``
with optical depth ``tau`` (uniform density) adds ``tau * (F_k(u1) - F_k(u0)) / (u1 - u0)``
(:meth:`~.basis_functions.Basis.average`), a zero-length one the delta limit
``tau * f_k(u0)`` (sec. 5: ``delta a_{i,k} = -ln(1 - alpha_i) f_k(d_i)``).  The bases live
in :mod:`.basis_functions`.

Depth range (``depth_range=``): ``"global"``, one ``[near, far]`` for all texels (default
``Segments.bounds()``; an explicit range must contain every segment,
:func:`~.base.depth_range`), or ``"texel"``, tight per-texel bounds stored per texel (2
floats; ``near=``/``far=`` must not be given; constants of the build: gradients w.r.t.
``z0``/``z1`` hold them fixed).  A range shorter than ``MIN_SPAN_REL max(|near|, |far|) +
MIN_SPAN_ABS`` is widened to that length.  Normalised depths clip to [0, 1] (a part in front
of ``u = 0`` counted as a delta there, one behind ``u = 1`` dropped); receiver depths clamp
to the range.  ``precision=``: coefficients per texel as ``a_k / s``, ``s = max_k |a_k|``
(:mod:`._precision`).

Kernel: coefficients stored flat, texel-major ``[texel * K + k]`` (:meth:`BasisRepresentation._project`).
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import backend
from ..filtering import filtered_eval
from .registry import register
from .base import Representation, depth_range
from ._loops import texel_lanes, texel_sums
from ._precision import PRECISIONS, Stored
from .basis_functions import BASES, LIST_CHUNK, LIST_UNROLL, Basis, clip_segment, make_basis
from .basis_functions import CosineBasis, LegendreBasis  # noqa: F401  (re-exported: their old home)
from .schema import DEPTH_RANGE, FAR, NEAR, Param, Schema

#: Shortest depth range per storage dtype: ``MIN_SPAN_REL[dtype] max(|near|, |far|) +
#: MIN_SPAN_ABS[dtype]`` (the dtype's smallest normal number: near = far = 0 does not divide by 0).
MIN_SPAN_REL = {"float32": 1e-6, "float64": 1e-14}
MIN_SPAN_ABS = {"float32": float(np.finfo(np.float32).tiny), "float64": float(np.finfo(np.float64).tiny)}
#: (item, coefficient) lanes per kernel on the indexed path.
LANES_PER_BATCH = 1 << 22
#: Most coefficients per texel, the bound of every size parameter (n, harmonics, slices):
#: 2^16 (256 KiB per texel in float32); the memory budget bounds texels x coefficients.
MAX_COEFFICIENTS = 1 << 16
#: Most coefficients of a basis in list form (~K / LIST_CHUNK kernels per build and lookup).
MAX_LIST_COEFFICIENTS = 1 << 12


@register("basis")
class BasisRepresentation(Representation):
    """Coefficient map of any :class:`Basis` (module docstring).  Attributes: ``coefficients``
    (K Dr.Jit arrays of length T); ``near``, ``far``: floats (global) or Dr.Jit arrays (texel).
    """

    # Best practice for every basis kind (inherited): per-texel range, opaque blockers apart.
    PRESET = {"depth_range": "texel"}
    PRESET_CAPTURE = {"opaque": "separate"}
    schema = Schema(
        params=(
            Param("basis", "object", "legendre", f"a Basis instance or a registered name {sorted(BASES)}"),
            Param("n", "int", None, "size of a named basis (functions; default 8)", min=1, max=MAX_COEFFICIENTS,
                  nullable=True),
            NEAR, FAR, DEPTH_RANGE,
        ),
        size="n", sweep=(2, 4, 6, 8, 12, 16), quick_sweep=(4, 8),
        examples=({"basis": "legendre", "n": 6}, {"basis": "cosine", "n": 6}),
        headline={"basis": "legendre", "n": 8},
        summary="any orthonormal basis of the absorption (FOM/OSM are two of them)",
        paper="Jansen & Bavoil 2010, sec. 5")

    def _resolve(self):
        self.basis = self._make_basis()
        self.monotone = bool(self.basis.monotone)      # non-negative coefficients, non-decreasing g_k
        self._check_coefficients()
        P, segments = self.params, self.segments
        near, far = P["near"], P["far"]
        if P["depth_range"] == "texel":
            if near is not None or far is not None:
                name = "near" if near is not None else "far"
                raise ValueError(f"{name}: near=/far= cannot be combined with depth_range='texel'")
            self.near, self.far = (segments.Float(A.aligned(b)) for b in segments.texel_bounds())
            self._per_texel = True
        else:
            self.near, self.far = depth_range(segments, near, far, open_range=True)   # base.py's rule
            self._per_texel = False
            P.update(near=self.near, far=self.far)

    def _build(self):
        self._coef = self._project()      # flat [texel * K + k]; ``coefficients`` lists it

    def _make_basis(self) -> Basis:
        """The basis this kind projects onto (from ``params``; subclasses fix it)."""
        basis, n = self.params["basis"], self.params["n"]
        basis = make_basis(basis, 8 if isinstance(basis, str) and n is None else n)
        self.params["basis"] = basis.name if isinstance(self.params["basis"], str) else basis
        self.params["n"] = basis.n
        return basis

    def _coefficients_at(self, v: int) -> int | None:
        """Coefficients per texel at size-parameter value ``v`` (None: a Basis instance)."""
        if not isinstance(self.params.get("basis", ""), str):
            return None
        return type(self.basis)(v).n_coefficients

    def _build_bytes(self, K: int) -> float:
        """Estimated peak bytes of the projection with K coefficients per texel: the flat store
        and its copies, plus one batch of (item, coefficient) lanes or the list form's terms."""
        seg = self.segments
        T, S, it = seg.n_texels, seg.n_segments, seg.itemsize
        if self.basis.indexed:
            return it * (2.0 * T * K + 8.0 * LANES_PER_BATCH)
        return it * (2.0 * T + 2.5 * S) * K

    def _check_coefficients(self) -> None:
        """ValueError naming the size parameter and what fits: more than :data:`MAX_COEFFICIENTS`
        per texel (:data:`MAX_LIST_COEFFICIENTS` in list form), or :meth:`_build_bytes` above
        the memory budget."""
        name = self.schema.size
        K = self.basis.n_coefficients
        searchable = self._coefficients_at(self.params[name]) is not None
        if not searchable:
            name = "basis" if "basis" in self.params else name
        cap, cap_name = ((MAX_COEFFICIENTS, "MAX_COEFFICIENTS") if self.basis.indexed else
                         (MAX_LIST_COEFFICIENTS, "MAX_LIST_COEFFICIENTS: a basis without indexed forms"))
        if K > cap:
            hint = "" if not searchable else f"; {self.schema.size} <= {self._largest_within(cap)} fits"
            raise ValueError(f"{name}: {K} coefficients per texel, above the {cap} a texel may hold "
                             f"(avsm_dr.representations.basis.{cap_name}){hint}")
        self._check_build_memory(lambda v: self._build_bytes(self._coefficients_at(v) if searchable else K),
                                 name=name, search=searchable)

    def _largest_within(self, K_max: int) -> int:
        """Largest size-parameter value with at most ``K_max`` coefficients (bisection)."""
        lo, hi = 1, int(self.params[self.schema.size])
        while hi - lo > 1:
            mid = (lo + hi) // 2
            lo, hi = (mid, hi) if self._coefficients_at(mid) <= K_max else (lo, mid)
        return lo

    unity_in_front = False

    def _native_bytes(self) -> float:
        return (self.basis.n_coefficients + (2 if self._per_texel else 0)) * self.segments.itemsize

    precisions = PRECISIONS
    #: The flat store ``[texel * K + k]`` reconstruction reads and :mod:`._precision` quantises:
    #: a_k or a linear transform of them (OSM's cumulative sums), so prefiltering can weight it.
    _stored_attr = "_coef"
    _store = property(lambda self: getattr(self, self._stored_attr))

    def _stored(self):
        """The stored map as coefficients (non-negative for monotone bases), the range."""
        out = (Stored(self._stored_attr, "coefficient", "flat", signed=not self.basis.monotone),)
        if self._per_texel:
            out += (Stored("near", "range", "texel"), Stored("far", "range", "texel"))
        return out

    def _bounds(self, texel=None):
        """(near, far) of the given texels, or global (opaque: no kernel per near/far)."""
        Float = self.Float
        if self._per_texel:
            return dr.gather(Float, self.near, texel), dr.gather(Float, self.far, texel)
        return dr.opaque(Float, self.near), dr.opaque(Float, self.far)

    def _range(self, texel=None):
        """(near, span) for the given texels (arrays) or globally (floats)."""
        near, far = self._bounds(texel)
        dt = self.segments.dtype
        floor = MIN_SPAN_REL[dt] * dr.maximum(dr.abs(near), dr.abs(far)) + MIN_SPAN_ABS[dt]
        return near, dr.maximum(far - near, floor)

    @property
    def coefficients(self) -> list:
        """a_k per texel as a list of K Dr.Jit arrays of length T (from the flat store)."""
        K, T = self.basis.n_coefficients, self.n_texels
        idx = dr.arange(backend.types().UInt32, T) * K
        return [dr.gather(self.Float, self._coef, idx + k) for k in range(K)]

    def _lane_batches(self, n_items: int) -> list:
        """(item, j, kc) per batch of kc coefficients: UInt32 lanes, item-major, of the n_items x kc
        (item, coefficient j) pairs, n_items x kc <= LANES_PER_BATCH (one kernel per batch)."""
        K, UInt32 = self.basis.n_coefficients, backend.types().UInt32
        per = max(1, min(K, LANES_PER_BATCH // max(n_items, 1)))
        out = []
        for j0 in range(0, K, per):
            kc = min(per, K - j0)
            lane = dr.arange(UInt32, n_items * kc)
            out.append((lane // kc, dr.opaque(UInt32, j0) + lane % kc, kc))
        return out

    def _check_index_range(self, T: int, K: int) -> None:
        """ValueError when T x K coefficients exceed what UInt32 indices address."""
        if T * K >= 2**32:
            raise ValueError(f"{self.schema.size or 'n'}: {T} texels x {K} coefficients exceed the "
                             "2^32 - 1 entries that UInt32 indices address")

    def _project(self):
        """a_k per texel, flat ``[texel * K + k]``: without gradients per-texel sums in CSR
        order (:meth:`_project_texels`, :meth:`_sum_per_texel`: the same bits every run),
        with them :meth:`_project_scatter` (no reverse mode through symbolic loops)."""
        seg, basis = self.segments, self.basis
        self._check_index_range(seg.n_texels, basis.n_coefficients)
        if seg.n_segments and not seg.requires_grad:
            return self._project_texels() if basis.indexed else self._sum_per_texel(self._list_terms())
        return self._project_scatter()

    def _project_scatter(self):
        """a_k by scatter-add (float atomics: the order varies between runs): list bases
        :meth:`_scatter_terms`, indexed ones over (segment, coefficient) lanes, a kernel per
        batch of coefficients whatever K."""
        seg, basis = self.segments, self.basis
        if not basis.indexed:
            return self._scatter_terms(self._list_terms())
        Float, UInt32 = seg.Float, backend.types().UInt32
        T, K, S = seg.n_texels, basis.n_coefficients, seg.n_segments
        flat = dr.zeros(Float, T * K)
        if S == 0:
            return flat
        texel = seg.texel_of_segment()
        near, span = self._range(texel if self._per_texel else None)
        c0, c1, tau_in, tau_front = clip_segment(seg.z0, seg.z1, seg.optical_depth, near, span)
        dr.eval(texel, c0, c1, tau_in, tau_front)
        batches = self._lane_batches(S)
        for s, j, _ in batches:                              # segment, coefficient
            u0, u1 = dr.gather(Float, c0, s), dr.gather(Float, c1, s)
            val = (dr.gather(Float, tau_in, s) * basis.average_at(j, u0, u1)
                   + dr.gather(Float, tau_front, s) * basis.f_at(j, dr.zeros(Float, dr.width(s))))
            dr.scatter_reduce(dr.ReduceOp.Add, flat, val, dr.gather(UInt32, texel, s) * K + j)
            if len(batches) > 1:
                dr.eval(flat)
        dr.eval(flat)
        return flat

    def _list_terms(self):
        """``terms(z0, z1, tau, texel)`` of a basis in list form: each segment's
        ``tau_in avg_k + tau_front f_k(0)`` (:func:`clip_segment`, ``Basis.average``)."""
        basis = self.basis
        f_near = basis.f(dr.zeros(self.segments.Float, 1))      # f_k(0): the part in front of near

        def terms(z0, z1, tau, texel):
            near, span = self._range(texel if self._per_texel else None)
            c0, c1, t_in, t_front = clip_segment(z0, z1, tau, near, span)
            avg = basis.average(c0, c1)                        # mean of f_k over [c0, c1]
            return [t_in * avg[k] + t_front * f_near[k] for k in range(basis.n_coefficients)]

        return terms

    def _scatter_terms(self, terms):
        """Flat ``[texel * K + k]`` sums over each texel's segments of ``terms(z0, z1, tau,
        texel)`` (K values per segment) by scatter-add, one per k (evaluated every LIST_CHUNK
        coefficients beyond LIST_UNROLL); differentiable."""
        seg = self.segments
        UInt32, K = backend.types().UInt32, self.basis.n_coefficients
        flat = dr.zeros(seg.Float, seg.n_texels * K)
        if seg.n_segments == 0:
            return flat
        texel = seg.texel_of_segment()
        every, base = terms(seg.z0, seg.z1, seg.optical_depth, texel), texel * K
        for k in range(K):
            kk = dr.opaque(UInt32, k) if K > LIST_UNROLL else k    # one kernel per chunk
            dr.scatter_reduce(dr.ReduceOp.Add, flat, every[k], base + kk)
            if K > LIST_UNROLL and k % LIST_CHUNK == LIST_CHUNK - 1:
                dr.eval(flat)
        dr.eval(flat)
        return flat

    def _sum_per_texel(self, terms):
        """:meth:`_scatter_terms` without atomics (:func:`._loops.texel_sums`: one lane per
        texel adds its segments in CSR order, the same bits every run).  Below
        LIST_UNROLL coefficients the terms are computed inside that loop (so a list basis'
        ``f`` / ``average`` must not ``dr.eval``), from it on for every segment first, then
        summed LIST_CHUNK coefficients at a time."""
        seg = self.segments
        Float, UInt32 = seg.Float, backend.types().UInt32
        T, K = seg.n_texels, self.basis.n_coefficients
        flat = dr.zeros(Float, T * K)
        if K < LIST_UNROLL:
            arrays = (seg.z0, seg.z1, seg.optical_depth)
            texel, sums = texel_sums(seg, lambda i, t: terms(*(dr.gather(Float, x, i) for x in arrays), t), K,
                                     label="basis_project")
            for k, s in enumerate(sums):
                dr.scatter(flat, s, texel * K + k)
            dr.eval(flat)
            return flat
        every = terms(seg.z0, seg.z1, seg.optical_depth, seg.texel_of_segment())
        for k0 in range(0, K, LIST_CHUNK):
            chunk = every[k0:k0 + LIST_CHUNK]
            dr.eval(*chunk)
            texel, sums = texel_sums(seg, lambda i, _t, c=chunk: [dr.gather(Float, v, i) for v in c], len(chunk),
                                     label="basis_project")
            for k, s in enumerate(sums, start=k0):
                dr.scatter(flat, s, texel * K + dr.opaque(UInt32, k))        # one kernel per chunk
            dr.eval(flat)
        return flat

    def _project_texels(self):
        """a_k of an indexed basis with one lane per (non-empty texel, coefficient), each
        summing the texel's segments in CSR order in a register (the expressions of
        :meth:`_project_scatter`), then one plain scatter: the same bits every run."""
        seg, basis = self.segments, self.basis
        Float, UInt32 = seg.Float, backend.types().UInt32
        T, K = seg.n_texels, basis.n_coefficients
        flat = dr.zeros(Float, T * K)
        lanes, first, end = texel_lanes(seg)
        z0, z1, tau = seg.z0, seg.z1, seg.optical_depth
        batches = self._lane_batches(dr.width(lanes))
        if len(batches) > 1:
            dr.eval(first, end)
        for t, j, _ in batches:                              # texel's lane, coefficient
            texel = dr.gather(UInt32, lanes, t)
            stop = dr.gather(UInt32, end, t)
            near, span = self._range(texel if self._per_texel else None)
            f_near = basis.f_at(j, dr.zeros(Float, dr.width(t)))        # f_j(0): in front of near

            def body(i, acc):
                c0, c1, t_in, t_front = clip_segment(dr.gather(Float, z0, i), dr.gather(Float, z1, i),
                                                     dr.gather(Float, tau, i), near, span)
                return i + 1, acc + (t_in * basis.average_at(j, c0, c1) + t_front * f_near)

            _, acc = dr.while_loop((dr.gather(UInt32, first, t), dr.zeros(Float, dr.width(t))),
                                   lambda i, acc: i < stop, body, label="basis_project")
            dr.scatter(flat, acc, texel * K + j)
            dr.eval(flat)
        return flat

    def normalized_depth(self, texel, depth):
        """u = clamp((depth - near) / (far - near), 0, 1) for each receiver."""
        near, span = self._range(texel)
        return dr.clip((depth - near) / span, 0, 1)

    def _optical_depth(self, texel, depth):
        """D at ``depth`` along texel ``texel``: :meth:`_reconstruct_from` the stored map."""
        return self._reconstruct_from(self._store, texel, self.normalized_depth(texel, depth))

    def _reconstruct_from(self, store, row, u):
        """D(u) = sum_k a_k g_k(u) with a_k read from ``store[row * K + k]`` (row: UInt32 per
        receiver; u: normalised depth per receiver)."""
        Float, UInt32 = self.Float, backend.types().UInt32
        basis, K = self.basis, self.basis.n_coefficients
        R = dr.width(u)
        D = dr.zeros(Float, R)
        if basis.indexed:
            batches = self._lane_batches(R)
            for r, j, kc in batches:                         # receiver, coefficient
                a = dr.gather(Float, store, dr.gather(UInt32, row, r) * K + j)
                D += dr.block_sum(a * basis.g_at(j, dr.gather(Float, u, r)), kc)
                if len(batches) > 1:
                    dr.eval(D)
            return D
        base = row * K
        for k, gk in enumerate(basis.g(u)):
            kk = dr.opaque(UInt32, k) if K > LIST_UNROLL else k
            D += dr.gather(Float, store, base + kk) * gk
            if K > LIST_UNROLL and k % LIST_CHUNK == LIST_CHUNK - 1:
                dr.eval(D)
        return D

    prefilterable = True                  # linear in the coefficients

    def _prefiltered_eval(self, coords, depth, width, height, filter, radius):
        """T from the filtered coefficient map: per receiver ``a_k = sum_j w_j a_k[tex_j] /
        sum_j w_j`` over the filter's taps (:func:`~avsm_dr.filtering.filtered_eval`), then
        ``exp(-sum_k a_k g_k(u))``, as hardware filtering of a coefficient texture does.
        ValueError with a per-texel range (each texel's a_k live on its own [near, far])."""
        if self._per_texel:
            raise ValueError("prefilter: needs depth_range='global'; with 'texel' every texel's "
                             "coefficients live on its own [near, far] and cannot be averaged")
        t = backend.types()
        Float, UInt32, Int32 = self.Float, t.UInt32, t.Int32
        store, K, R = self._store, self.basis.n_coefficients, coords.shape[0]
        self._check_index_range(R, K)
        flat = dr.zeros(Float, R * K)                   # receiver-major [r * K + k]
        idx = dr.arange(UInt32, R) * K
        for k in range(K):
            kk = dr.opaque(UInt32, k) if K > LIST_UNROLL else k
            a_k = filtered_eval(lambda tex, _depth, kk=kk: dr.gather(Float, store, tex * K + kk), coords, depth,
                                width, height, filter, radius, Float, UInt32, Int32)
            dr.scatter(flat, a_k, idx + kk)
            if K > LIST_UNROLL and k % LIST_CHUNK == LIST_CHUNK - 1:
                dr.eval(flat)
        u = self.normalized_depth(None, depth)
        return dr.clip(dr.exp(-self._reconstruct_from(flat, dr.arange(UInt32, R), u)), 0, 1)

    def _eval_texels(self, texel, depth):
        return dr.clip(dr.exp(-self._optical_depth(texel, depth)), 0, 1)

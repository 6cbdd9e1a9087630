"""Occluder segments along light rays, one CSR list per shadow-map texel.

Texel ``k`` owns segments ``offsets[k] : offsets[k+1]``.  Segment ``i`` spans the
light-space depths ``z0[i] <= z1[i]`` and holds a uniform density, so its
transmittance at a depth ``d`` is ``exp(-tau_i * clamp((d - z0_i) / (z1_i - z0_i), 0, 1))``
with ``tau_i`` the segment's optical depth (``-ln`` of its exit transmittance).
A zero-length segment is a step at ``z0`` (a receiver at exactly ``z0`` is behind it).

Storage dtype (float32 or float64) limits, checked at :meth:`Segments.from_arrays`:
every depth, and the depth range ``max z1 - min z0`` (hence every length), must be
finite in that dtype (``ValueError`` naming ``z0``/``z1`` otherwise).  Subnormal depths and
optical depths (below the dtype's smallest normal number) are stored as 0: Dr.Jit's CPU
worker threads flush subnormals to zero while the calling thread does not, so they would
otherwise give results that depend on the array size.  :meth:`Segments.check_depth` applies
the same rules to other depths (receivers, near/far).  A positive length below
:data:`MIN_LENGTH` is stored as a zero-length step: its density would overflow float64.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import drjit as dr
import numpy as np

from . import _arrays as A
from . import backend
from . import validation as V
from .segment_dtype import OVERFLOW_HINT, check_in_dtype, check_span, check_tiny, flushed, has_subnormal
from .texel_sort import TIE, UNSORTED, break_ties, float_keys, shuffle_key, sort_texels_view, view_order
from .texel_sort import plan as sort_plan

#: Optical depth stored for a fully opaque segment (exit transmittance exactly 0).
#: ``exp(-1e4)`` is 0 in float32 and float64 alike, and the value stays finite so
#: that products with zero-length fractions never make NaN.
OPAQUE_OPTICAL_DEPTH = 1.0e4
#: Shortest positive segment length (2.4e-295): below it the summed density of up to 2^32
#: segments, OPAQUE_OPTICAL_DEPTH / length each, could overflow float64; shorter ones are
#: stored as zero-length steps at z0 (only within ~1e-279 of depth 0 in float64).
MIN_LENGTH = OPAQUE_OPTICAL_DEPTH * 2.0**32 / float(np.finfo(np.float64).max)
#: float32 maps with many equal z0 rank segments inside their runs of equal z0
#: (:func:`~avsm_dr.texel_sort.break_ties`) while ``sum count^2 <= DEVICE_SORT_WORK * S``
#: (:func:`device_sortable`), else sort them by stable key passes (more memory, any counts).
DEVICE_SORT_WORK = 256
#: Equal-z0 texels of at most this many segments re-sort on the host (an exact capture's few zero-length ones).
HOST_UNTIE = 1 << 10
_FIELDS = ("z0", "z1", "optical_depth")     # the per-segment arrays (class _Linked)
#: Insertion orders of a texel's segments that :meth:`Segments.in_order` makes from any
#: Segments: front to back, back to front, a seeded shuffle (:func:`shuffle_key`).
REORDERS = ("depth", "reverse_depth", "random")
#: Values of :attr:`Segments.order`: :data:`REORDERS`, 'submission' (a renderer's draw order,
#: made by :func:`~avsm_dr.capture.capture`) and 'unknown' (not recorded).
ORDERS = REORDERS + ("submission", "unknown")
#: The keys of a Segments' cache that depend on its offsets only: their device copy, the
#: counts, each segment's texel, the sort plan (what :meth:`Segments.drop_cache` keeps by default).
LAYOUT_KEYS = ("offsets", "counts", "texel_of", "sort_plan")
#: Every key a Segments caches: the layout, the depth bounds, exact-curve points, greedy's ranks.
CACHE_KEYS = LAYOUT_KEYS + ("bounds", "curve_points", "vw_removal_rank")


def device_sortable(counts: np.ndarray) -> bool:
    """``sum count^2 <= DEVICE_SORT_WORK * sum count``: a per-texel sort of ``count``
    comparisons per segment is cheap enough (:data:`DEVICE_SORT_WORK`)."""
    c = np.asarray(counts, np.int64)                  # no float64 copy (1-9 ms at 10^6 texels, measured)
    return int(c @ c) <= DEVICE_SORT_WORK * max(int(c.sum()), 1)


def run_index(starts, n: int):
    """(n,) Dr.Jit UInt32 run of each of ``n`` elements, runs starting at ``starts`` (UInt32,
    ascending, repeated for empty runs, the first 0 left out): a 1 added at every start, then an
    inclusive prefix sum (``n`` opaque, mode Local: no compile per size)."""
    UInt32 = backend.types().UInt32
    flag = dr.zeros(UInt32, n)
    if n == 0 or dr.width(starts) == 0:             # one run (or nothing)
        return flag
    dr.scatter_reduce(dr.ReduceOp.Add, flag, UInt32(1), starts, starts < dr.opaque(UInt32, n),
                      mode=dr.ReduceMode.Local)
    return dr.cumsum(flag)


def key_order(counts: np.ndarray, offsets_dr, texel, key, group=None, layout=None):
    """The permutation (Dr.Jit UInt32, S) sorting segments by ``(texel, key, index)``: ``texel``
    and ``key`` (< 2^32) UInt32 per segment; ``group`` = (index, texel) of every CSR position
    when the segments are not in texel order (None: they are).  On the device for any counts
    (words ``key << 32 | index``, :func:`~avsm_dr.texel_sort.sort_texels_view` with ``layout``)."""
    UInt32 = backend.types().UInt32
    U32 = dr.detached_t(UInt32)
    index, gtex = (dr.arange(UInt32, dr.width(texel)), texel) if group is None else group
    pay, base, _, _ = sort_texels_view(counts, offsets_dr, "index", (U32(index), U32(key)), ties=False, layout=layout)
    return UInt32(view_order(pay, base, U32(offsets_dr), U32(gtex)))


def _per_segment(x, name: str, n: int) -> np.ndarray:
    """Host float64 copy of a per-segment array: 1-D, ``n`` values, finite (ValueError naming ``name``)."""
    arr = A.host(x, name)
    if arr.ndim != 1:
        raise ValueError(f"{name}: expected a 1-D array, got shape {arr.shape}")
    if arr.size != n:
        raise ValueError(f"{name}: length {arr.size} does not match offsets[-1] = {n}")
    A.check_finite(arr, name)
    return arr


def _recipe(src, Float, dtype: str, flush: bool, clamp: bool = False):
    """``fn()``: ``src`` (Dr.Jit or host) as ``Float``, clamped to OPAQUE_OPTICAL_DEPTH when
    ``clamp``, subnormals set to 0 when ``flush``; ``src`` itself when it needs neither."""
    def fn():
        x = A.to_float(src, Float)
        if clamp:
            x = dr.minimum(x, OPAQUE_OPTICAL_DEPTH)
        return flushed(x, dtype) if flush else x
    return fn


class _Linked:
    """A :class:`Segments` array attribute (``z0``, ``z1``, ``optical_depth``) that stays
    linked to the caller's grad-enabled arrays across ``dr.backward``.

    Reverse mode frees the graph edges it traverses, so an array *derived* from a caller's
    leaf (a clamp, a cast, ``-ln`` of a transmittance, a gather of :meth:`Segments.sorted`)
    would pass no gradient to it in a second build.  Such a field carries a recipe
    (:meth:`Segments._link`): every read outside a symbolic region re-derives all linked
    fields of the object from the caller's arrays (new, lazy nodes; nothing is copied);
    inside one (a loop body, where a new array could not be gathered from) the arrays of
    the last such read are returned.  Fields without a recipe (the caller's own arrays, or
    arrays without gradients) are plain attributes."""

    def __set_name__(self, owner, name):
        self.name, self.slot = name, "_" + name

    def __get__(self, obj, owner=None):
        if obj is None:
            raise AttributeError(self.name)         # a dataclass field without a default
        d = obj.__dict__
        links = d.get("_links")
        if links and not dr.flag(dr.JitFlag.SymbolicScope):
            for name, fn in links.items():
                d["_" + name] = fn()
        return d[self.slot]

    def __set__(self, obj, value):
        obj.__dict__[self.slot] = value
        links = obj.__dict__.get("_links")
        if links and self.name in links:        # a new dict: copies of obj keep theirs
            obj.__dict__["_links"] = {k: fn for k, fn in links.items() if k != self.name}


@dataclass(eq=False)
class Segments:
    """Segments of all texels (CSR).  Build with :meth:`from_arrays`.

    Attributes: ``offsets`` (T+1,) int64 NumPy; ``z0``, ``z1``, ``optical_depth``
    Dr.Jit float arrays of length S (AD graphs kept); ``dtype`` 'float32'|'float64';
    ``order`` the insertion order the segments of each texel are stored in, one of
    :data:`ORDERS` ('unknown' unless given or made by :meth:`sorted` / :meth:`in_order` /
    ``ad.capture``; 'depth' when built with ``sorted_by_depth=True``).  Reusable under
    reverse mode: ``dr.backward`` after one build leaves the next build's gradients intact
    (:class:`_Linked`).
    """

    offsets: np.ndarray
    z0: Any = _Linked()
    z1: Any = _Linked()
    optical_depth: Any = _Linked()
    dtype: str = "float32"
    sorted_by_depth: bool = False
    _cache: dict = field(default_factory=dict, repr=False)
    order: str = "unknown"

    def __post_init__(self):
        if self.order == "unknown" and self.sorted_by_depth:
            self.order = "depth"

    @classmethod
    def from_arrays(cls, offsets, z0, z1, transmittance=None, optical_depth=None,
                    dtype: str | None = None, order: str = "unknown") -> "Segments":
        """Validate and pack segments.

        Parameters
        ----------
        offsets
            (T+1,) non-decreasing integers, offsets[0] = 0, offsets[-1] = S.
        z0, z1
            (S,) light-space entry/exit depths, z0 <= z1, finite.
        transmittance
            (S,) exit transmittance in [0, 1] (0 = opaque); give this or ``optical_depth``.
        optical_depth
            (S,) tau >= 0 finite (values above OPAQUE_OPTICAL_DEPTH are clamped).
        dtype
            'float32' (default) or 'float64'; default follows Dr.Jit float64 input.
        order
            the insertion order the arrays are in, one of :data:`ORDERS` (a label recorded
            as :attr:`order`, not checked against the depths).
        """
        V.one_of(order, "order", ORDERS)
        off = A.host(offsets, "offsets", np.float64)
        if off.ndim != 1 or off.size < 2:
            raise ValueError(f"offsets: expected a 1-D array of T+1 >= 2 entries, got shape {off.shape}")
        A.check_finite(off, "offsets")
        if np.any(off != np.round(off)) or off[0] != 0:
            raise ValueError("offsets: must be integers starting at 0")
        if np.any(np.diff(off) < 0):
            raise ValueError("offsets: must be non-decreasing")
        if off[-1] >= 2**32:
            raise ValueError(f"offsets: {off[-1]:.6g} segments exceed the 2^32 - 1 that UInt32 indices address")
        off = off.astype(np.int64)
        n = int(off[-1])
        if dtype is None:
            f64 = any(A.is_drjit(x) and A.dtype_of(x) == "float64" for x in (z0, z1, transmittance, optical_depth))
            dtype = "float64" if f64 else "float32"
        Float = A.float_type(dtype)
        z0h, z1h = _per_segment(z0, "z0", n), _per_segment(z1, "z1", n)
        z0f, z1f = (check_in_dtype(h, name, dtype) for h, name in ((z0h, "z0"), (z1h, "z1")))
        if np.any(z1h < z0h):
            raise ValueError(f"z1: {int(np.count_nonzero(z1h < z0h))} segment(s) have z1 < z0")
        if n:   # the depth range (basis spans), hence every length, must be finite in dtype too
            check_span(z0f.min(), z1f.max(), dtype, "z1", "the depth range max(z1) - min(z0)",
                       f"; rescale the scene{OVERFLOW_HINT[dtype]}")
        if (transmittance is None) == (optical_depth is None):
            raise ValueError("transmittance: pass exactly one of transmittance= or optical_depth=")
        # Each stored array comes from a recipe over the caller's arrays: a grad-enabled Dr.Jit
        # input of the storage type that needs no change is kept itself, anything derived keeps
        # its recipe (re-derived on reads, so dr.backward cannot orphan it: class _Linked).
        z0_of = _recipe(z0 if A.is_drjit(z0) else z0f, Float, dtype, has_subnormal(z0h, dtype))
        z1_raw = _recipe(z1 if A.is_drjit(z1) else z1f, Float, dtype, has_subnormal(z1h, dtype))
        z1_of = z1_raw
        length = z1f.astype(dtype) - z0f.astype(dtype)   # a density tau / length overflowing float64: a step
        short = (length > 0) & (length < MIN_LENGTH)
        if short.any():
            short_d = backend.types().Bool(short)

            def z1_of():
                return dr.select(short_d, z0_of(), z1_raw())
        z0d, z1d = z0_of(), z1_of()
        if transmittance is not None:
            th = _per_segment(transmittance, "transmittance", n)
            if np.any((th < 0) | (th > 1)):
                raise ValueError("transmittance: values must lie in [0, 1] (opacity above 1 or negative)")
        else:
            oh = _per_segment(optical_depth, "optical_depth", n)
            if np.any(oh < 0):
                raise ValueError("optical_depth: values must be >= 0 (negative density)")
        if n == 0:      # every texel is empty (T = 1 everywhere)
            return cls(off, Float(), Float(), Float(), dtype, order=order)
        if transmittance is not None:
            tiny = float(np.exp(-OPAQUE_OPTICAL_DEPTH)) if dtype == "float64" else 0.0

            def tau_of():
                # -ln t, with t = 0 (opaque) mapped to OPAQUE_OPTICAL_DEPTH without an
                # infinite derivative leaking into the AD graph.
                t = A.to_float(transmittance, Float)
                safe = dr.maximum(t, 1e-300 if dtype == "float64" else 1e-38)
                return dr.select(t > tiny, dr.minimum(-dr.log(safe), OPAQUE_OPTICAL_DEPTH), OPAQUE_OPTICAL_DEPTH)
        else:
            if A.is_drjit(optical_depth):   # clamped and flushed only where needed (recipe)
                tau_of = _recipe(optical_depth, Float, dtype, has_subnormal(oh, dtype),
                                 clamp=bool(np.any(oh > OPAQUE_OPTICAL_DEPTH)))
            else:   # clamped on the host first: a value beyond the dtype's range must not become inf
                tau_of = _recipe(np.minimum(check_tiny(oh, dtype), OPAQUE_OPTICAL_DEPTH), Float, dtype, False)
        caller = {"z0": z0, "z1": z1, "optical_depth": optical_depth}
        seg = cls(off, z0d, z1d, tau_of(), dtype, order=order)
        return seg._link(**{k: fn for k, fn in (("z0", z0_of), ("z1", z1_of), ("optical_depth", tau_of))
                            if seg.__dict__["_" + k] is not caller[k]})

    def _link(self, **recipes) -> "Segments":
        """Attach recipes ``name=fn`` (``fn()`` derives the field from the caller's arrays, see
        :class:`_Linked`) to the fields whose current array carries gradients; returns self."""
        live = {k: fn for k, fn in recipes.items() if dr.grad_enabled(self.__dict__["_" + k])}
        if live:
            self.__dict__["_links"] = {**self.__dict__.get("_links", {}), **live}
        return self

    @property
    def Float(self):
        return type(self.z0)

    @property
    def itemsize(self) -> int:
        """Bytes per stored float (4 for float32, 8 for float64)."""
        return 4 if self.dtype == "float32" else 8

    @property
    def requires_grad(self) -> bool:
        """True when z0, z1 or optical_depth carry gradients."""
        return any(dr.grad_enabled(x) for x in (self.z0, self.z1, self.optical_depth))

    @property
    def n_texels(self) -> int:
        return int(self.offsets.size - 1)

    @property
    def n_segments(self) -> int:
        return int(self.offsets[-1])

    @property
    def counts(self) -> np.ndarray:
        """(T,) number of segments per texel (cached, read-only)."""
        if (c := self._cache.get("counts")) is None:
            c = self._cache["counts"] = np.diff(self.offsets)
            c.flags.writeable = False
        return c

    @property
    def max_count(self) -> int:
        return int(self.counts.max()) if self.n_texels else 0

    def _sort_plan(self) -> dict:
        """:func:`~avsm_dr.texel_sort.plan` of these counts (cached)."""
        if "sort_plan" not in self._cache:
            self._cache["sort_plan"] = sort_plan(self.counts, self.offsets_dr())
        return self._cache["sort_plan"]

    def offsets_dr(self):
        """offsets as a Dr.Jit UInt32 array (cached)."""
        if "offsets" not in self._cache:
            self._cache["offsets"] = A.to_uint32(self.offsets)
        return self._cache["offsets"]

    def texel_of_segment(self):
        """(S,) texel index of every segment, Dr.Jit UInt32 (cached), built on the device:
        ``texel(i) = #{k in 1..T-1 : offsets[k] <= i}`` (:func:`run_index`)."""
        if "texel_of" not in self._cache:
            UInt32 = backend.types().UInt32
            starts = dr.gather(UInt32, self.offsets_dr(), dr.arange(UInt32, 1, self.n_texels))
            self._cache["texel_of"] = run_index(starts, self.n_segments)
        return self._cache["texel_of"]

    def bounds(self) -> tuple[float, float]:
        """Global (near, far): min z0 and max z1 over all segments ((0, 1) if none)."""
        if self.n_segments == 0:
            return 0.0, 1.0
        if "bounds" not in self._cache:  # reduced on the device: no host copy of S values
            self._cache["bounds"] = (float(dr.min(dr.detach(self.z0))[0]), float(dr.max(dr.detach(self.z1))[0]))
        return self._cache["bounds"]

    def texel_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Tight per-texel (near, far) as float64 NumPy arrays; empty texels get (0, 1).  One lane per
        texel takes min z0 / max z1 over its CSR range on the device (no float64 host copy of S segments)."""
        U, F, off, T = backend.types().UInt32, dr.detached_t(self.Float), self.offsets_dr(), self.n_texels
        z0, z1 = (F(dr.detach(z)) if self.n_segments else F(0.0) for z in (self.z0, self.z1))   # F(0): never read
        _, lo, hi = dr.while_loop((dr.gather(U, off, dr.arange(U, T)), dr.full(F, np.inf, T), dr.full(F, -np.inf, T)),
                                  lambda i, lo, hi: i < dr.gather(U, off, dr.arange(U, 1, T + 1)), lambda i, lo, hi: (
                                      i + 1, dr.minimum(lo, dr.gather(F, z0, i)), dr.maximum(hi, dr.gather(F, z1, i))))
        return tuple(np.where(self.counts > 0, x.numpy(), e).astype(np.float64) for x, e in ((lo, 0), (hi, 1)))

    def numpy(self) -> dict[str, np.ndarray]:
        """Host copies (float64) of offsets, z0, z1, optical_depth."""
        return {"offsets": self.offsets.copy(), **{k: A.host(getattr(self, k), k) for k in _FIELDS}}

    def sorted(self) -> "Segments":
        """Segments of each texel sorted by (z0, z1), ties in their stored order (a stable
        lexsort, :meth:`depth_order`); gradients follow the permutation."""
        if self.sorted_by_depth:
            return self
        return self._gathered(self.offsets, self.depth_order(), True, self._layout_cache(), "depth")

    def depth_order(self):
        """The permutation (Dr.Jit UInt32, S) that sorts each texel's segments by (z0, z1),
        ties in stored order; None when they are already in order (:meth:`depth_view`)."""
        view = self.depth_view()
        return None if view is None else view_order(*view, self.offsets_dr(), self.texel_of_segment())

    def depth_view(self, words: bool = False):
        """The order of :meth:`sorted` without sorted copies, for a consumer walking each texel
        (e.g. the AVSM build): None when every texel is already in order, else ``(index,
        start)`` (Dr.Jit UInt32): texel ``t``'s ``r``-th segment in (z0, z1) order is segment
        ``index[start[t] + r]``; ``words`` (float32): its sort word ``key(z0) << 32 | position``
        instead (UInt64, z0 from :func:`~avsm_dr.texel_sort.float_of_key`: one read less).

        float32: by z0 with :func:`~avsm_dr.texel_sort.sort_texels_view` (words ``key(z0) << 32
        | position``), texels with equal z0 sorted again by (z1, position) then (z0, that order)
        (:meth:`_untie`), or, where they hold over 1/8 of the segments and
        :func:`device_sortable`, ranked in place by (z1, position) inside their runs of equal z0
        (:func:`~avsm_dr.texel_sort.break_ties`: less memory and time there); float64 (after a
        check that some texel is out of order): by the four 32-bit halves of the z0 and z1 keys
        (:meth:`_key_sort`).  On the device for any counts."""
        if self.sorted_by_depth or self.n_segments < 2:
            return None
        UInt32 = backend.types().UInt32
        z0 = dr.detached_t(self.Float)(dr.detach(self.z0))
        if self.dtype == "float32":                             # words key(z0) << 32 | position
            pay, start, flags, tied = sort_texels_view(self.counts, self.offsets_dr(), "float", (z0,),
                                                       layout=self._sort_plan(), words=words)
            if not flags & TIE:
                return (pay if words else UInt32(pay), UInt32(start)) if flags & UNSORTED else None
            if device_sortable(self.counts) and 8 * int(self.counts[tied].sum()) > self.n_segments:
                low = break_ties(dr.detached_t(UInt32)(pay), start, self.offsets_dr(), self.texel_of_segment(),
                                 float_keys(z0)[0], dr.detached_t(self.Float)(dr.detach(self.z1)))  # in place
                pay = (pay & 0xFFFFFFFF00000000) | type(pay)(low) if words else low   # a run's key stays
            else:
                pay = self._untie(pay, start, tied)               # equal z0: by z1, then position
            dr.eval(pay)
            return pay if words else UInt32(pay), UInt32(start)
        if self._in_order():
            return None
        idx, off, _ = self._key_sort(np.arange(self.n_texels), self._depth_keys())
        return UInt32(idx), UInt32(off)

    def _untie(self, pay, start, texels):
        """``pay`` (a :func:`~avsm_dr.texel_sort.sort_texels_view` layout by ``(z0, position)``,
        payloads or whole words) with ``texels`` (NumPy, those where two segments share z0)
        re-sorted by ``(z0, z1, position)`` (:meth:`_key_sort`)."""
        U32, c = type(start), self.counts[texels]
        if c.sum() <= HOST_UNTIE:                     # few: (texel, z0, z1, position) sorted by NumPy
            t = np.repeat(np.arange(c.size), c)
            slot = U32(A.aligned(np.repeat(dr.gather(U32, start, U32(A.aligned(texels, np.uint32))).numpy(), c)
                                 + np.arange(t.size) - np.repeat(np.cumsum(c) - c, c), np.uint32))
            w = dr.gather(type(pay), pay, slot).numpy()
            pos, F = U32(A.aligned(w & 0xFFFFFFFF, np.uint32)), dr.detached_t(self.Float)
            z0, z1 = (dr.gather(F, F(dr.detach(z)), pos).numpy() for z in (self.z0, self.z1))
            dr.scatter(pay, type(pay)(A.aligned(w[np.lexsort((w & 0xFFFFFFFF, z1, z0, t))])), slot)
            return pay
        idx, soff, stex = self._key_sort(texels, keys := self._depth_keys())
        local = dr.arange(U32, dr.width(idx)) - dr.gather(U32, soff, stex)
        first = dr.gather(U32, start, U32(A.aligned(texels, np.uint32)))    # each texel's first slot
        idx = (type(pay)(keys[0](idx)) << 32) | type(pay)(idx) if dr.type_v(pay) == dr.VarType.UInt64 else idx  # words
        dr.scatter(pay, idx, dr.gather(U32, first, stex) + local)
        return pay

    def _depth_keys(self) -> list:
        """Functions ``key(index)`` (UInt32 of segments ``index``), most significant first: the
        order-preserving keys of z0, then of z1 (:func:`~avsm_dr.texel_sort.float_keys`: one
        each for float32, two halves each for float64)."""
        F = dr.detached_t(self.Float)
        z0, z1 = F(dr.detach(self.z0)), F(dr.detach(self.z1))
        halves = 1 if self.dtype == "float32" else 2
        return [lambda i, z=z, h=h: float_keys(dr.gather(F, z, i))[h] for z in (z0, z1) for h in range(halves)]

    def _key_sort(self, texels: np.ndarray, keys):
        """``(index, offsets, texel)`` (Dr.Jit UInt32): the ``r``-th segment of texel ``texels[j]``
        by ``(keys[0], keys[1], ..., position)`` is segment ``index[offsets[j] + r]``, and
        ``texel[offsets[j] + r] = j``.  One stable :func:`key_order` pass per key (``key(index)``:
        UInt32 keys of segments ``index``), the last key first (least significant digit first),
        on the segments of ``texels`` (NumPy ints) only."""
        U32 = dr.detached_t(backend.types().UInt32)
        c = self.counts[texels]
        sub = np.concatenate([[0], np.cumsum(c)])
        soff, n = U32(A.aligned(sub, np.uint32)), int(sub[-1])
        stex = U32(run_index(dr.gather(U32, soff, dr.arange(U32, 1, c.size)), n))
        first = dr.gather(U32, U32(self.offsets_dr()), U32(A.aligned(texels, np.uint32)))
        idx = dr.gather(U32, first, stex) + dr.arange(U32, n) - dr.gather(U32, soff, stex)
        dr.eval(stex, idx)
        lay = sort_plan(c, soff)
        for key in reversed(keys):
            k = key(idx)
            dr.eval(k)                                # gathered by the sort: an array, not an expression
            idx = dr.gather(U32, idx, U32(key_order(c, soff, stex, k, layout=lay)))
            dr.eval(idx)
        return idx, soff, stex

    def _layout_cache(self) -> dict:
        """The cached device copies that depend on the offsets only (:data:`LAYOUT_KEYS`)."""
        return {k: v for k, v in self._cache.items() if k in LAYOUT_KEYS}

    def drop_cache(self, keep=LAYOUT_KEYS) -> "Segments":
        """Forget what earlier calls and builds cached on these segments, but the keys ``keep``
        (names from :data:`CACHE_KEYS`; default the layout, :data:`LAYOUT_KEYS`); returns self.

        A later build then computes again what it needs, as on fresh segments: time a build
        cold as ``build(kind, seg.drop_cache())`` (otherwise ``greedy`` and ``optimal`` reuse
        the exact curve's points, and ``greedy`` its removal order, of an earlier build)."""
        keep = {V.one_of(k, "keep", CACHE_KEYS) for k in (keep if isinstance(keep, (tuple, list, set)) else [keep])}
        for k in set(self._cache) - keep:
            del self._cache[k]
        return self

    def in_order(self, order: str, seed: int | None = None) -> "Segments":
        """The segments of every texel in insertion order ``order`` (same offsets; gradients
        follow the permutation), recorded as :attr:`order`:

        * ``'depth'``: front to back, :meth:`sorted` (by (z0, z1), ties in stored order);
        * ``'reverse_depth'``: back to front, each texel's ``'depth'`` order reversed;
        * ``'random'``: a seeded shuffle of each texel's ``'depth'`` order, by the keys
          :func:`shuffle_key` ``(seed, texel, rank)`` (ties by rank): the same seed gives the
          same order, whatever the thread count or the order the segments came in.

        seed: integer in [0, 2^32) of ``'random'`` (default 0; ValueError naming ``seed``
        when given with another order)."""
        V.one_of(order, "order", REORDERS)
        if seed is not None and order != "random":
            raise ValueError(f"seed: only the 'random' order takes a seed, got seed={seed!r} with order={order!r}")
        seed = V.integer(0 if seed is None else seed, "seed", 0, 2**32 - 1)
        base = self.sorted()
        if order == "depth":
            return base
        n = base.n_segments
        if n < 2:
            return base._gathered(base.offsets, None, False, base._layout_cache(), order)
        UInt32 = backend.types().UInt32
        tex = base.texel_of_segment()
        off = base.offsets_dr()
        rank = dr.arange(UInt32, n) - dr.gather(UInt32, off, tex)
        if order == "reverse_depth":     # slot r of texel t <- slot count_t - 1 - r
            idx = dr.gather(UInt32, off, tex + 1) - 1 - rank
        else:
            idx = key_order(base.counts, off, tex, shuffle_key(seed, UInt32(tex), rank), layout=base._sort_plan())
        return base._gathered(base.offsets, idx, False, base._layout_cache(), order)

    def _gathered(self, offsets, idx, sorted_by_depth: bool, cache=None, order: str | None = None) -> "Segments":
        """Segments over ``offsets`` holding segments ``idx`` (Dr.Jit UInt32; None: all, in
        order), labelled ``order`` (default: this object's); fields with gradients keep
        recipes over this object's (:class:`_Linked`)."""
        Float = self.Float

        def recipe(name):
            if idx is None:
                return lambda: getattr(self, name)
            return lambda: dr.gather(Float, getattr(self, name), idx)

        fns = {k: recipe(k) for k in _FIELDS}
        out = Segments(offsets, *(fns[k]() for k in _FIELDS), self.dtype, sorted_by_depth,
                       {} if cache is None else cache, self.order if order is None else order)
        return out._link(**fns)

    def _in_order(self) -> bool:
        """Every texel's ``(z0, z1)`` non-decreasing (pairs of neighbours in one texel, on the device)."""
        UInt32 = backend.types().UInt32
        z0, z1 = dr.detach(self.z0), dr.detach(self.z1)
        tex, Float = self.texel_of_segment(), type(z0)
        i = dr.arange(UInt32, self.n_segments - 1)
        same = dr.gather(UInt32, tex, i) == dr.gather(UInt32, tex, i + 1)
        (a0, b0), (a1, b1) = ((dr.gather(Float, z, i), dr.gather(Float, z, i + 1)) for z in (z0, z1))
        return not bool(dr.any(same & ((b0 < a0) | ((b0 == a0) & (b1 < a1))))[0])

    def check_depth(self, value, name: str):
        """``value`` (a depth: scalar or 1-D array) checked against the storage dtype:
        finite there (``ValueError`` naming ``name`` otherwise, e.g. ``far=1e39`` with
        float32 segments), and with subnormal values set to 0 (module docstring).
        Returns a Python float for a scalar, a float64 NumPy array otherwise."""
        arr = A.host(value, name)
        A.check_finite(arr, name)
        out = check_in_dtype(np.atleast_1d(arr).ravel(), name, self.dtype).reshape(arr.shape)
        return float(out) if out.ndim == 0 else out

    def check_depth_range(self, near, far) -> tuple[float, float]:
        """(near, far) as floats checked with :meth:`check_depth`, and ``far - near``
        finite in the storage dtype (the basis methods divide by it)."""
        lo, hi = self.check_depth(near, "near"), self.check_depth(far, "far")
        check_span(lo, hi, self.dtype, "far", "the range far - near")
        return lo, hi

    def select_texels(self, texels) -> "Segments":
        """A new Segments with only the given texels (in that order; repeats allowed).

        texels: 1-D non-empty integers in [0, n_texels) (negative indices are refused, not
        counted from the end)."""
        arr = A.host(texels, "texels")
        if arr.ndim != 1 or arr.size == 0:
            raise ValueError(f"texels: expected a non-empty 1-D array of texel indices, got shape {arr.shape}")
        A.check_finite(arr, "texels")
        if np.any(arr != np.round(arr)) or np.any(arr < 0) or np.any(arr >= self.n_texels):
            raise ValueError(f"texels: indices must be integers in [0, {self.n_texels})")
        texels = arr.astype(np.int64)
        off = np.concatenate([[0], np.cumsum(self.counts[texels])]).astype(np.int64)
        idx = np.repeat(self.offsets[texels] - off[:-1], self.counts[texels]) + np.arange(off[-1])
        return self._gathered(off, A.to_uint32(idx), self.sorted_by_depth)

    def texel_range(self, t0: int, t1: int) -> "Segments":
        """A new Segments with texels ``t0 .. t1 - 1`` (``0 <= t0 < t1 <= n_texels``): as
        :meth:`select_texels` of that range, gathered without an index array."""
        t0 = V.integer(t0, "t0", 0, self.n_texels - 1)
        t1 = V.integer(t1, "t1", t0 + 1, self.n_texels)
        s0, U32 = int(self.offsets[t0]), backend.types().UInt32
        idx = dr.arange(U32, int(self.offsets[t1]) - s0) + dr.opaque(U32, s0)
        return self._gathered(self.offsets[t0:t1 + 1] - s0, idx, self.sorted_by_depth)

    def __repr__(self) -> str:
        return (f"Segments(texels={self.n_texels}, segments={self.n_segments}, "
                f"max_per_texel={self.max_count}, dtype={self.dtype}, order={self.order})")

"""The interface every transmittance representation implements.

Contract (stated once here; subclasses document only what differs):

* ``build`` consumes a :class:`~avsm_dr.segments.Segments` and keeps fixed-size
  per-texel buffers (``[coefficient or node][texel]`` Dr.Jit arrays).
* ``eval(texel, depth)`` returns the transmittance ``T`` of each receiver,
  ``0 <= T <= 1``; ``T = 1`` in front of the first blocker for node methods
  (exact, AVSM, DSM), up to their depth resolution for basis methods (OSM, FOM);
  representations with ``monotone = True`` guarantee ``T`` non-increasing in depth.
* ``nbytes_per_texel`` is the exact storage of the compressed form, the *dense* layout
  (variable-size forms such as DSM: the mean over texels).
* ``nbytes_sparse`` / ``nbytes_sparse_per_texel``, the *sparse* layout, one rule for every
  kind: one occupancy bit per texel (``T / 8`` bytes), then per non-empty texel its payload
  (``texel_payload_bytes``) plus, for ``variable_size`` kinds, a 4-byte CSR offset;
  sparse <= dense + 1/8 per texel.
* Gradients flow from ``T`` back to the segments' ``optical_depth`` (and
  ``z0``/``z1``) wherever the representation is differentiable.

Depth range (every kind with ``near``/``far``, one rule: :func:`depth_range`): None means
the segments' global bounds ``[min z0, max z1]``; an explicit range must contain every
segment (``near <= min z0``, ``max z1 <= far`` in the storage dtype, ``far - near`` finite),
else ``ValueError`` naming ``near``, ``far`` or both.  Receivers outside the range follow
the kind's ``eval`` convention (T = 1 in front, the total transmittance behind ``far``).
"""
from __future__ import annotations

import abc
from typing import Any

import numpy as np

from .. import _arrays as A
from .. import backend
from .. import validation as V
from ..filtering import filtered_eval
from ..segments import Segments
from ._loops import REVERSE_MODES, TRAJECTORY_BUDGET_WORDS, safe_chunk
from ._precision import check_precision, code_bytes, quantise
from .schema import Param, Schema
from ._lookup_args import lookup_args


def depth_range(segments: Segments, near, far, open_range: bool = False) -> tuple[float, float]:
    """(near, far) by the module docstring's rule; ``open_range``: an explicit range also
    needs ``near < far`` (the basis kinds divide by the span).  ValueError names the argument."""
    lo, hi = segments.bounds()
    given = near is not None or far is not None
    near, far = segments.check_depth_range(lo if near is None else near, hi if far is None else far)
    ft = np.dtype(segments.dtype).type                   # compare the values the kernels store
    cut_near = segments.n_segments > 0 and float(ft(near)) > lo
    cut_far = segments.n_segments > 0 and float(ft(far)) < hi
    if cut_near or cut_far:
        a, b = str(ft(lo)), str(ft(hi))                 # shortest digits in the storage dtype
        where = [f"near: {near!r} is after the content's start {a}"] if cut_near else []
        where += [f"far: {far!r} is before the content's end {b}"] if cut_far else []
        need = ", ".join(([f"near <= {a}"] if cut_near else []) + ([f"far >= {b}"] if cut_far else []))
        raise ValueError(f"{' and '.join(where)}; the segments span [{a}, {b}] and an explicit "
                         f"[near, far] must contain every segment ({need}; None: the segments' bounds)")
    if near > far or (open_range and given and not near < far):
        raise ValueError(f"near: need near {'<' if open_range else '<='} far, got near={near!r}, far={far!r}")
    return near, far


def node_build_bytes(n_texels: int, nodes: int, itemsize: int) -> float:
    """Estimated peak bytes of a node-list build (AVSM and its kin): per texel its ``2N + 5``
    loop-state words read, written and compacted, ``3 (2N + 5) itemsize``."""
    return 3.0 * (2 * int(nodes) + 5) * int(itemsize) * int(n_texels)


#: Bytes of one CSR offset in the sparse layout (:attr:`Representation.nbytes_sparse`).
SPARSE_OFFSET_BYTES = 4

#: Largest ``chunk`` (iterations per checkpoint): Dr.Jit's ``max_iterations`` limit; a
#: chunk whose trajectory exceeds the budget is refused when the build runs.
MAX_CHUNK = 65536


class Representation(abc.ABC):
    """Base class: parameter schema, traits, reverse-mode policy, validation, filtering
    and dispatch to the per-texel kernel.

    A kind is one subclass with a ``schema`` (:class:`~.schema.Schema`) registered with
    ``@register("name")``; it implements ``_eval_texels`` and ``_native_bytes`` and reads its
    validated parameters from ``self.params``.  The build is one template,
    ``__init__(segments, **params)``: :meth:`_validate`, :meth:`_resolve` (derived
    parameters and memory checks, once), :meth:`_build`, :meth:`_apply_precision`.
    Every kind also takes ``reverse`` and ``chunk`` (:meth:`checkpoint_chunk`) and
    ``precision`` (:mod:`._precision`, of the buffers the kind declares in :meth:`_stored`)."""

    kind: str = "base"
    schema: Schema = Schema()
    #: Storage precisions the kind accepts besides None (:mod:`._precision`).
    precisions: tuple = ()

    def __init__(self, segments: Segments, **params: Any):
        self._validate(segments, params)
        with backend.exact_float64(segments.Float):     # float64 on CUDA: IEEE rcp and derivatives
            self._resolve()
            self._build()
            self._apply_precision()

    def _validate(self, segments: Segments, params: dict) -> None:
        """Check ``segments`` and the base parameters (``reverse``, ``chunk``, ``precision``),
        then the kind's against its schema into ``self.params`` (ValueError naming them)."""
        if not isinstance(segments, Segments):
            raise ValueError(f"segments: expected avsm_dr.Segments, got {type(segments).__name__}")
        reverse = params.pop("reverse", "auto")
        chunk = params.pop("chunk", None)
        self.precision = check_precision(params.pop("precision", None))
        if self.precision is not None and self.precision not in self.precisions:
            raise ValueError(f"precision: kind {self.kind!r} accepts {self.precisions or 'only None'}, "
                             f"got {self.precision!r}{self._precision_note}")
        V.one_of(reverse, "reverse", REVERSE_MODES)
        if chunk is not None:
            chunk = Param("chunk", "int", min=1, max=MAX_CHUNK).validate(chunk)
        self.segments = segments
        self.reverse, self._chunk = reverse, chunk
        self.params: dict[str, Any] = self.schema.validate(self.kind, params)

    def _resolve(self) -> None:
        """The kind's derived parameters and checks before allocating."""

    def _build(self) -> None:
        """Build the compressed form from ``self.segments``."""

    def _check_build_memory(self, need, name: str | None = None, search: bool = True) -> None:
        """Before allocating: ValueError naming ``name`` (default: the schema's size
        parameter) when ``need(v)``, the build's estimated peak bytes at that parameter's
        value v, exceeds :func:`avsm_dr.validation.memory_budget`; the message names the
        largest value that fits (``search``) or asks for fewer texels."""
        name = name or self.schema.size
        p = self.schema.param(name)
        lo = p.min if search and p.min is not None and not p.open_min else None
        lo = int(lo) if lo is not None and p.type == "int" else lo
        rule = self.schema.constraint
        V.check_memory(name, self.params[name], need, lo=lo, what=f"over {self.n_texels} texels",
                       allowed=None if rule is None else lambda v: not rule({**self.params, name: v}))

    def _check_node_memory(self) -> None:
        """:meth:`_check_build_memory` of a node-list build over its ``nodes`` (:func:`node_build_bytes`)."""
        seg = self.segments
        self._check_build_memory(lambda n: node_build_bytes(seg.n_texels, n, seg.itemsize))

    #: Why some precisions are refused (appended to the ValueError).
    _precision_note: str = ""

    def _stored(self) -> tuple:
        """The stored buffers :mod:`._precision` quantises (:class:`~._precision.Stored`)."""
        return ()

    def _apply_precision(self) -> None:
        """Quantise the stored buffers to ``self.precision``; ``_stored_nbytes``: their bytes."""
        if self.precision is not None:
            self._stored_nbytes = quantise(self, self._stored())

    #: Sparse layout (:attr:`nbytes_sparse`): True for variable-size kinds, which keep a
    #: CSR offset (:data:`SPARSE_OFFSET_BYTES`) per non-empty texel.
    variable_size: bool = False
    #: Best-practice configuration (``describe(kind)["preset"]``): parameters over the defaults.
    PRESET: dict = {}
    #: Capture options the preset assumes (``describe(kind)["preset_capture"]``).
    PRESET_CAPTURE: dict = {}
    #: Configurations reported beside the preset, {label: params} (``"preset_variants"``).
    PRESET_VARIANTS: dict = {}
    #: None: the preset is best practice; else why it is not yet tuned (``"preset_tuned"`` False).
    PRESET_UNTUNED: str | None = None

    def _set_nodes(self, counts) -> None:
        """A variable-size kind's CSR layout from its (T,) node counts: ``node_counts``,
        ``node_offsets`` (T+1,) int64, the lookup's UInt32 offsets and largest count."""
        self.node_counts = counts
        self.node_offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self._offsets_dr = backend.types().UInt32(A.aligned(self.node_offsets.astype(np.uint32)))
        self._max_nodes = int(counts.max(initial=0))

    def texel_payload_bytes(self):
        """Bytes one non-empty texel stores in the sparse layout, offset excluded: a number
        (fixed-size kinds; default: :attr:`nbytes_per_texel`) or a (T,) float64 array
        (variable-size kinds, only the non-empty texels' entries counted; default: a
        (depth, value) pair per node of ``node_counts``)."""
        if self.variable_size:
            return self._csr_payload(self.node_counts, 2 * self.segments.itemsize)
        return self.nbytes_per_texel

    def _csr_payload(self, counts, entry_bytes: float, texel_bytes: float = 0.0) -> np.ndarray:
        """Payload per texel of a variable-size kind, ``texel_bytes + counts entry_bytes``
        (precision None); with a ``precision``: the mean quantised bytes per texel plus
        ``(counts - mean) x`` the code bytes of the kind's ``'csr'`` buffers."""
        counts = np.asarray(counts, np.float64)
        if self.precision is None:
            return texel_bytes + counts * entry_bytes
        code = sum(code_bytes(f.meaning, self.precision) for f in self._stored() if f.layout == "csr")
        return self._stored_nbytes + (counts - (counts.mean() if counts.size else 0.0)) * code

    @property
    def nbytes_sparse(self) -> float:
        """Total bytes of the sparse layout (module docstring)."""
        occupied = self.segments.counts > 0
        n = int(np.count_nonzero(occupied))
        pay = self.texel_payload_bytes()
        body = float(np.asarray(pay, np.float64)[occupied].sum()) if np.ndim(pay) else n * float(pay)
        return self.n_texels / 8 + body + (SPARSE_OFFSET_BYTES * n if self.variable_size else 0)

    @property
    def nbytes_sparse_per_texel(self) -> float:
        """:attr:`nbytes_sparse` / T (<= ``nbytes_per_texel + 1/8``)."""
        return self.nbytes_sparse / max(self.n_texels, 1)

    # Traits (a kind overrides them as attributes or properties).
    #: T is guaranteed non-increasing in depth (to float rounding).
    monotone: bool = True
    #: Gradients w.r.t. the segments' optical depths are supported.
    differentiable: bool = True
    #: T = 1 exactly in front of the texel's first segment (node methods; basis methods
    #: spread absorption over their depth resolution).
    unity_in_front: bool = True
    #: ``eval(..., prefilter=True)`` is supported: the kind is linear in a stored map.
    prefilterable: bool = False
    #: State words per lane of the build loop reverse mode must store (0: no loop, or a sum
    #: loop that reverse mode recomputes).
    loop_state_words: int = 0

    def _prefiltered_eval(self, coords, depth, width, height, filter, radius):
        """T reconstructed once from the filtered stored map (prefilterable kinds only)."""
        raise NotImplementedError

    @property
    def chunk(self) -> int:
        """Iterations per checkpointed chunk (given, or the largest that fits the budget)."""
        return self._chunk or safe_chunk(self.loop_state_words)

    def checkpoint_chunk(self, segments: Segments | None = None) -> int | None:
        """How to run this kind's build loops over ``segments`` (default: its own): None for
        a plain ``dr.while_loop`` (no loop state or no gradient), else the checkpoint chunk
        length (``reverse='checkpoint'``, or 'auto' with a trajectory ``max_count x
        loop_state_words`` above :data:`TRAJECTORY_BUDGET_WORDS`).  ValueError: 'trajectory'
        or a ``chunk`` beyond that budget (the CPU worker stack would overflow)."""
        seg = segments if segments is not None else self.segments
        words = self.loop_state_words
        if words == 0 or not seg.requires_grad:
            return None
        traj = int(seg.max_count) * int(words)            # per-lane trajectory words (:mod:`._loops`)
        if self.reverse == "trajectory":
            if traj > TRAJECTORY_BUDGET_WORDS:
                raise ValueError(
                    f"reverse: 'trajectory' would keep {traj} words per lane ({seg.max_count} segments x "
                    f"{words} state words), above the budget of {TRAJECTORY_BUDGET_WORDS} that Dr.Jit's "
                    "per-lane trajectory survives; use reverse='auto' or 'checkpoint'")
            return None
        if self.reverse == "checkpoint" or traj > TRAJECTORY_BUDGET_WORDS:
            run = min(self.chunk, seg.max_count) * words          # one chunk's trajectory
            if run > TRAJECTORY_BUDGET_WORDS:
                raise ValueError(
                    f"chunk: {self.chunk} iterations per checkpoint keep {run} words per lane "
                    f"({words} state words each), above the budget of {TRAJECTORY_BUDGET_WORDS} that "
                    f"Dr.Jit's per-lane trajectory survives; chunk <= {safe_chunk(words)} fits "
                    "(or leave chunk=None)")
            return self.chunk
        return None

    @abc.abstractmethod
    def _eval_texels(self, texel, depth):
        """T at ``depth`` (Float) along texel ``texel`` (UInt32); one lane per receiver."""

    @property
    def nbytes_per_texel(self) -> float:
        """Storage of the compressed form per texel in bytes (variable-size forms: the mean):
        with a ``precision`` the quantised buffers (:mod:`._precision`) plus, for
        ``variable_size`` kinds, the CSR offset; else :meth:`_native_bytes`."""
        if self.precision is not None:
            return self._stored_nbytes + (SPARSE_OFFSET_BYTES if self.variable_size else 0)
        return self._native_bytes()

    def _native_bytes(self) -> float:
        """:attr:`nbytes_per_texel` in the segments' own dtype (a kind defines it, or the property)."""
        raise NotImplementedError

    @property
    def n_texels(self) -> int:
        """Number of shadow-map texels."""
        return self.segments.n_texels

    @property
    def Float(self):
        """The Dr.Jit float type of the segments (Float32 or Float64 of the backend)."""
        return self.segments.Float

    def eval(self, texel, depth, filter: str = "point", width: int | None = None,
             height: int | None = None, radius: float = 1.0, prefilter: bool = False):
        """Transmittance at receivers.

        Parameters
        ----------
        texel
            (K,) integer texel indices, or (K, 2) float continuous shadow-map
            coordinates (x, y) in texel units (needs ``width``/``height``).
        depth
            (K,) light-space receiver depths (or a scalar), NumPy or Dr.Jit.
        filter
            'point' | 'bilinear' | 'box' | 'gaussian' (see :mod:`avsm_dr.filtering`).
        width, height
            the shadow map's size in texels, for continuous coordinates.
        radius
            the filter's radius in texels (box, gaussian).
        prefilter
            False (default): filter the reconstructed T, ``sum_j w_j T_j``.  True
            (kinds with ``prefilterable``, a non-point filter): filter the stored map,
            ``a = sum_j w_j a[tex_j]``, and reconstruct T once, as hardware filtering of
            a coefficient texture does (see the kind's ``_prefiltered_eval``).

        Returns
        -------
        Float
            Dr.Jit array of length K (``np.asarray`` works; AD graph kept)."""
        with backend.exact_float64(self.Float):
            a = lookup_args(self, self._eval_texels, texel, depth, filter, width, height, radius, prefilter)
            if a.T is not None:                       # a point lookup checked in its own kernel
                return a.T
            if a.coords is None:
                return self._eval_texels(a.texel, a.depth)
            if prefilter:
                return self._prefiltered_eval(a.coords, a.depth, a.width, a.height, filter, a.radius)
            t = backend.types()
            return filtered_eval(self._eval_texels, a.coords, a.depth, a.width, a.height, filter, a.radius,
                                 self.Float, t.UInt32, t.Int32)

    def __repr__(self) -> str:
        p = ", ".join(f"{k}={v!r}" for k, v in self.params.items())
        return f"{type(self).__name__}({p}; texels={self.n_texels})"


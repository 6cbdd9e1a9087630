"""The interface every transmittance representation implements.

Contract (stated once here; subclasses document only what differs):

* ``build`` consumes a :class:`~avsm_dr.segments.Segments` and keeps fixed-size
  per-texel buffers (``[coefficient or node][texel]`` Dr.Jit arrays).
* ``eval(texel, depth)`` returns the transmittance ``T`` of each receiver,
  ``0 <= T <= 1``; ``T = 1`` in front of the first blocker for node methods
  (exact, AVSM, DSM), up to their depth resolution for basis methods (OSM, FOM);
  representations with ``monotone = True`` guarantee ``T`` non-increasing in depth.
* ``nbytes_per_texel`` is the exact storage of the compressed form
  (for variable-size forms such as DSM: the mean over texels).
* Gradients flow from ``T`` back to the segments' ``optical_depth`` (and
  ``z0``/``z1``) wherever the representation is differentiable.

Depth range (every kind with ``near``/``far``, one rule: :func:`depth_range`): None means
the segments' global bounds ``[min z0, max z1]``; an explicit range must contain every
segment, ``near <= min z0`` and ``max z1 <= far`` compared in the storage dtype (the values
the kernels use), and ``far - near`` must be finite there.  A range that cuts the content
raises ``ValueError`` naming ``near`` (the content starts before it), ``far`` (it ends after
it) or both, with the values and the content's span.  Receivers outside the range follow
the kind's ``eval`` convention (T = 1 in front of the first blocker / at ``u = 0``, the
total transmittance behind ``far``).
"""
from __future__ import annotations

import abc
from typing import Any

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import _device_checks as DC
from .. import backend
from .. import validation as V
from ..filtering import FILTERS, check_radius, check_size, filtered_eval
from ..segments import Segments, flush_subnormal
from ._loops import REVERSE_MODES, TRAJECTORY_BUDGET_WORDS, safe_chunk, trajectory_words
from ._precision import check_precision, quantise
from .schema import Param, Schema


def depth_range(segments: Segments, near, far, open_range: bool = False) -> tuple[float, float]:
    """(near, far) of a kind's depth range by the module docstring's rule: the given values
    (None: the segments' bounds), finite in the storage dtype with a finite span, and
    containing every segment; ``open_range``: an explicit range also needs ``near < far``
    (the basis kinds divide by the span).  ValueError names the argument at fault."""
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
    loop-state words read, written and compacted, ``3 (2N + 5) itemsize`` (measured: AVSM-64,
    float32, 4 M texels, one segment each: 1300 bytes per texel of RSS, this gives 1596)."""
    return 3.0 * (2 * int(nodes) + 5) * int(itemsize) * int(n_texels)


#: Largest ``chunk`` (iterations per checkpoint): Dr.Jit's ``max_iterations`` limit; a
#: chunk whose trajectory exceeds the budget is refused when the build runs.
MAX_CHUNK = 65536


class _Built(abc.ABCMeta):
    """Metaclass running the shared post-build step once the whole constructor (the
    subclass' build included) has run: storage quantisation (``precision``)."""

    def __call__(cls, *args, **kwargs):
        obj = super().__call__(*args, **kwargs)
        obj._apply_precision()
        return obj


class Representation(metaclass=_Built):
    """Base class: parameter schema, traits, reverse-mode policy, validation, filtering
    and dispatch to the per-texel kernel.

    A kind is one subclass with a ``schema`` (:class:`~.schema.Schema`: parameters with
    defaults and ranges, the size parameter and its sweep) registered with
    ``@register("name")``; it implements ``_eval_texels`` and ``nbytes_per_texel`` and
    reads its validated parameters from ``self.params``.

    Every kind also accepts ``reverse`` ('auto' | 'trajectory' | 'checkpoint') and
    ``chunk`` (iterations per checkpoint): how reverse mode stores the build loops of
    kinds whose ``loop_state_words > 0`` (see :mod:`._loops`).  'auto' checkpoints only
    when ``max segments per texel x loop_state_words`` exceeds the trajectory budget;
    'trajectory' refuses (ValueError) what would overflow it.

    And ``precision`` (None | 'float32' | 'float16' | 'unorm16' | 'unorm8'): the storage
    format of the kind's stored buffers (:mod:`._precision`; None, the default: the
    segments' own dtype).  A kind lists what it accepts in ``precisions`` and declares its
    buffers in :meth:`_stored`; they are quantised once, after the build, by shared code.
    """

    kind: str = "base"
    schema: Schema = Schema()
    #: Storage precisions the kind accepts besides None (see :mod:`._precision`); opt-in: a
    #: kind lists them and declares its buffers in :meth:`_stored`.
    precisions: tuple = ()

    def __init__(self, segments: Segments, **params: Any):
        if not isinstance(segments, Segments):
            raise ValueError(f"segments: expected avsm_dr.Segments, got {type(segments).__name__}")
        reverse = params.pop("reverse", "auto")
        chunk = params.pop("chunk", None)
        self.precision = check_precision(params.pop("precision", None))
        if self.precision is not None and self.precision not in self.precisions:
            raise ValueError(f"precision: kind {self.kind!r} accepts {self.precisions or 'only None'}, "
                             f"got {self.precision!r}{self._precision_note}")
        if reverse not in REVERSE_MODES:
            raise ValueError(f"reverse: expected one of {REVERSE_MODES}, got {reverse!r}")
        if chunk is not None:
            chunk = Param("chunk", "int", min=1, max=MAX_CHUNK).validate(chunk)
        self.segments = segments
        self.reverse, self._chunk = reverse, chunk
        self.params: dict[str, Any] = self.schema.validate(self.kind, params)

    # --------------------------------------------------------------- memory
    def _check_build_memory(self, need, name: str | None = None, search: bool = True) -> None:
        """Before allocating: ValueError naming ``name`` (default: the schema's size
        parameter) when ``need(v)``, the build's estimated peak bytes at that parameter's
        value v, exceeds :func:`avsm_dr.validation.memory_budget`; the message names the
        largest value that fits (``search``) or asks for fewer texels."""
        name = name or self.schema.size
        p = self.schema.param(name)
        lo = p.min if search and p.min is not None and not p.open_min else None
        lo = int(lo) if lo is not None and p.type == "int" else lo
        rule = self.schema.constraint                     # e.g. moments: 4, 6 or 8 power moments
        V.check_memory(name, self.params[name], need, lo=lo, what=f"over {self.n_texels} texels",
                       allowed=None if rule is None else lambda v: not rule({**self.params, name: v}))

    # -------------------------------------------------------------- storage
    #: Why some precisions are refused (appended to the ValueError).
    _precision_note: str = ""

    def _stored(self) -> tuple:
        """The stored buffers :mod:`._precision` quantises (:class:`~._precision.Stored`)."""
        return ()

    def _apply_precision(self) -> None:
        """Quantise the stored buffers to ``self.precision`` (after the build; no-op for
        None); ``_stored_nbytes`` then holds their bytes per texel."""
        if self.precision is not None:
            self._stored_nbytes = quantise(self, self._stored())

    # --------------------------------------------------------------- traits
    @property
    def monotone(self) -> bool:
        """True when T is guaranteed non-increasing in depth (to float rounding)."""
        return True

    @property
    def differentiable(self) -> bool:
        """True when gradients w.r.t. the segments' optical depths are supported."""
        return True

    @property
    def unity_in_front(self) -> bool:
        """True when T = 1 exactly in front of the texel's first segment (node methods);
        basis methods spread absorption over their depth resolution."""
        return True

    @property
    def prefilterable(self) -> bool:
        """True when ``eval(..., prefilter=True)`` is supported: the kind is linear in a
        stored per-texel map, so filtering the map and reconstructing once is defined."""
        return False

    def _prefiltered_eval(self, coords, depth, width, height, filter, radius):
        """T reconstructed once from the filtered stored map (prefilterable kinds only)."""
        raise NotImplementedError

    @property
    def loop_state_words(self) -> int:
        """State words per lane of the build loop reverse mode must store (0: no loop, or
        a sum loop that reverse mode recomputes)."""
        return 0

    # ------------------------------------------------------- reverse policy
    @property
    def chunk(self) -> int:
        """Iterations per checkpointed chunk (given, or the largest that fits the budget)."""
        return self._chunk or safe_chunk(self.loop_state_words)

    def checkpoint_chunk(self, segments: Segments | None = None) -> int | None:
        """How to run this kind's build loops over ``segments`` (default: its own):
        None for a plain ``dr.while_loop``, else the checkpoint chunk length.

        Plain when there is no loop state or no gradient; checkpointed when asked
        (``reverse='checkpoint'``) or when 'auto' finds the trajectory
        ``max_count x loop_state_words`` above :data:`TRAJECTORY_BUDGET_WORDS`;
        ``reverse='trajectory'`` beyond the budget raises ValueError (the CPU worker
        stack would overflow: a segfault, measured at ~4 x the budget)."""
        seg = segments if segments is not None else self.segments
        words = self.loop_state_words
        if words == 0 or not seg.requires_grad:
            return None
        traj = trajectory_words(words, seg.max_count)
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

    # --------------------------------------------------------------- kernel
    @abc.abstractmethod
    def _eval_texels(self, texel, depth):
        """T at ``depth`` (Float) along texel ``texel`` (UInt32); one lane per receiver."""

    @property
    @abc.abstractmethod
    def nbytes_per_texel(self) -> float:
        """Storage of the compressed form per texel in bytes (variable-size forms: mean)."""

    @property
    def n_texels(self) -> int:
        """Number of shadow-map texels."""
        return self.segments.n_texels

    @property
    def Float(self):
        """The Dr.Jit float type of the segments (Float32 or Float64 of the backend)."""
        return self.segments.Float

    # ----------------------------------------------------------- public API
    def eval(self, texel, depth, filter: str = "point", width: int | None = None,
             height: int | None = None, radius: float = 1.0, prefilter: bool = False):
        """Transmittance at receivers.

        texel: (K,) integer texel indices, or (K, 2) float continuous shadow-map
            coordinates (x, y) in texel units (needs ``width``/``height``).
        depth: (K,) light-space receiver depths (or a scalar), NumPy or Dr.Jit.
        filter: 'point' | 'bilinear' | 'box' | 'gaussian' (see :mod:`avsm_dr.filtering`).
        prefilter: False (default): filter the reconstructed T, ``sum_j w_j T_j``.  True
            (kinds with ``prefilterable``, a non-point filter): filter the stored map,
            ``a = sum_j w_j a[tex_j]``, and reconstruct T once, as hardware filtering of
            a coefficient texture does (see the kind's ``_prefiltered_eval``).
        Returns a Dr.Jit Float of length K (``np.asarray`` works; AD graph kept).
        """
        t = backend.types()
        Float, UInt32, Int32 = self.Float, t.UInt32, t.Int32
        if filter not in FILTERS:
            raise ValueError(f"filter: expected one of {FILTERS}, got {filter!r}")
        if not isinstance(prefilter, (bool, np.bool_)):
            raise ValueError(f"prefilter: expected a bool, got {prefilter!r}")
        if prefilter and not self.prefilterable:
            raise ValueError(f"prefilter: kind {self.kind!r} is not linear in a stored map "
                             "(prefilterable = False); filter its T instead (prefilter=False)")
        if prefilter and filter == "point":
            raise ValueError("prefilter: needs a non-point filter ('bilinear', 'box', 'gaussian')")
        width = None if width is None else check_size(width, "width")
        height = None if height is None else check_size(height, "height")
        radius = check_radius(radius, width, height)
        if filter == "point" and (out := DC.host_point_lookup(self._eval_texels, texel, depth, self.n_texels,
                                                               self.segments.dtype, Float)) is not None:
            return out                      # NumPy input checked by min / max, read as it is

        # Dr.Jit input is validated on the device (one flag read back, no copy of the arrays),
        # NumPy integer texels by their min / max and NumPy float depths once converted
        # (:mod:`avsm_dr._device_checks`); what those sufficient checks do not accept takes
        # the host checks below, which raise the messages.
        tex_dev = texel if filter == "point" and DC.flat(texel) else None
        tex_np = filter == "point" and tex_dev is None and (tex_dev := DC.host_texels(texel, self.n_texels)) is not None
        dep_dev = depth if DC.flat(depth) else DC.host_depth(depth, Float)
        if tex_dev is not None and dep_dev is not None and (
                dr.width(tex_dev) == dr.width(dep_dev) or 1 in (dr.width(tex_dev), dr.width(dep_dev))):
            out = DC.point_lookup(self._eval_texels, tex_dev, tex_np, dep_dev, dep_dev is not depth,
                                  self.n_texels, self.segments.dtype, Float)
            if out is not None:
                return out
            tex_dev = dep_dev = None                          # the host checks raise below
        masks = ([DC.texel_mask(tex_dev, self.n_texels)] if tex_dev is not None and not tex_np else []) + \
            ([DC.depth_mask(dep_dev, self.segments.dtype, strict=dep_dev is not depth)] if dep_dev is not None else [])
        if masks and not DC.all_true(*masks):
            tex_dev = dep_dev = None
        dev_t, dev_d = tex_dev is not None, dep_dev is not None

        coords = None
        if dev_t:
            k = dr.width(tex_dev)
        else:
            if A.is_drjit(texel):
                tex_h = A.host(texel, "texel", np.float64)
            else:
                tex_h = np.asarray(texel)
                if tex_h.dtype.kind not in "iuf":
                    raise ValueError(f"texel: expected a numeric array, got dtype {tex_h.dtype}")
                tex_h = tex_h.astype(np.float64)
            if tex_h.ndim == 2:
                if tex_h.shape[1] != 2:
                    raise ValueError(f"texel: continuous coordinates must have shape (K, 2), got {tex_h.shape}")
                if width is None or height is None:
                    raise ValueError("width: continuous texel coordinates need width= and height=")
                coords = tex_h
                k = tex_h.shape[0]
            elif tex_h.ndim <= 1:
                tex_h = np.atleast_1d(tex_h)
                k = tex_h.size
            else:
                raise ValueError(f"texel: expected shape (K,) or (K, 2), got {tex_h.shape}")
            A.check_finite(tex_h, "texel")

        if dev_d:
            depth_dr, d_size = A.to_float(dep_dev, Float), dr.width(dep_dev)
        else:
            if A.is_drjit(depth):
                d_h = A.host(depth, "depth")
                depth_dr = flush_subnormal(A.to_float(depth, Float), d_h, self.segments.dtype)
            else:
                d_h = np.atleast_1d(np.asarray(depth, dtype=np.float64))
                depth_dr = None
            if d_h.ndim > 1:
                raise ValueError(f"depth: expected shape (K,), got {d_h.shape}")
            d_h = self.segments.check_depth(d_h, "depth")   # finite in the storage dtype
            d_size = d_h.size
        if d_size not in (1, k) and k != 1:
            raise ValueError(f"depth: length {d_size} does not match {k} texels")
        if k == 0 or d_size == 0:
            raise ValueError("texel: no receivers given (empty array)")
        n = max(k, d_size)
        if depth_dr is None:
            depth_dr = A.to_float(np.broadcast_to(d_h, (n,)), Float)
        elif d_size == 1 and n > 1:
            depth_dr = dr.repeat(depth_dr, n) if hasattr(dr, "repeat") else depth_dr + dr.zeros(Float, n)
        if dev_t:
            tex_d = A.to_uint32(dr.detach(tex_dev))
            return self._eval_texels(tex_d + dr.zeros(UInt32, n) if k == 1 and n > 1 else tex_d, depth_dr)

        if coords is None:
            if np.any(tex_h != np.round(tex_h)) or np.any(tex_h < 0) or np.any(tex_h >= self.n_texels):
                raise ValueError(f"texel: indices must be integers in [0, {self.n_texels})")
            tex_h = np.broadcast_to(tex_h, (n,)) if tex_h.size == 1 else tex_h
            if filter == "point":
                return self._eval_texels(A.to_uint32(tex_h.astype(np.uint32)), depth_dr)
            if width is None or height is None:
                raise ValueError(f"width: filter {filter!r} needs the shadow map's width= and height=")
            ti = tex_h.astype(np.int64)
            coords = np.stack([ti % width + 0.5, ti // width + 0.5], axis=1)
        if width * height != self.n_texels:
            raise ValueError(f"width: width*height = {width * height} does not match {self.n_texels} texels")
        if coords.shape[0] == 1 and n > 1:
            coords = np.broadcast_to(coords, (n, 2))
        if prefilter:
            return self._prefiltered_eval(np.asarray(coords, np.float64), depth_dr, width, height,
                                          filter, radius)
        return filtered_eval(self._eval_texels, np.asarray(coords, np.float64), depth_dr, width, height,
                             filter, radius, Float, UInt32, Int32)

    def __repr__(self) -> str:
        p = ", ".join(f"{k}={v!r}" for k, v in self.params.items())
        return f"{type(self).__name__}({p}; texels={self.n_texels})"


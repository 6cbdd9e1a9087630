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
"""
from __future__ import annotations

from typing import Any

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import backend
from ..filtering import FILTERS, taps
from ..segments import Segments


class Representation:
    """Base class: validation, filtering and dispatch to the per-texel kernel."""

    kind: str = "base"
    #: True when T is guaranteed non-increasing in depth.
    monotone: bool = True
    #: True when gradients w.r.t. optical depth are supported.
    differentiable: bool = True

    def __init__(self, segments: Segments, **params: Any):
        if not isinstance(segments, Segments):
            raise ValueError(f"segments: expected avsm_dr.Segments, got {type(segments).__name__}")
        self.segments = segments
        self.params: dict[str, Any] = dict(params)

    # --------------------------------------------------------------- kernel
    def _eval_texels(self, texel, depth):
        """T at ``depth`` (Float) along texel ``texel`` (UInt32); one lane per receiver."""
        raise NotImplementedError

    @property
    def nbytes_per_texel(self) -> float:
        raise NotImplementedError

    @property
    def n_texels(self) -> int:
        return self.segments.n_texels

    @property
    def Float(self):
        return self.segments.Float

    # ----------------------------------------------------------- public API
    def eval(self, texel, depth, filter: str = "point", width: int | None = None,
             height: int | None = None, radius: float = 1.0):
        """Transmittance at receivers.

        texel: (K,) integer texel indices, or (K, 2) float continuous shadow-map
            coordinates (x, y) in texel units (needs ``width``/``height``).
        depth: (K,) light-space receiver depths (or a scalar), NumPy or Dr.Jit.
        filter: 'point' | 'bilinear' | 'box' | 'gaussian' (see :mod:`avsm_dr.filtering`).
        Returns a Dr.Jit Float of length K (``np.asarray`` works; AD graph kept).
        """
        t = backend.types()
        Float, UInt32, Int32 = self.Float, t.UInt32, t.Int32
        if filter not in FILTERS:
            raise ValueError(f"filter: expected one of {FILTERS}, got {filter!r}")

        coords = None
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

        if A.is_drjit(depth):
            d_h = A.host(depth, "depth")
            depth_dr = A.to_float(depth, Float)
        else:
            d_h = np.atleast_1d(np.asarray(depth, dtype=np.float64))
            depth_dr = None
        if d_h.ndim > 1:
            raise ValueError(f"depth: expected shape (K,), got {d_h.shape}")
        A.check_finite(d_h, "depth")
        if d_h.size not in (1, k) and k != 1:
            raise ValueError(f"depth: length {d_h.size} does not match {k} texels")
        if k == 0 or d_h.size == 0:
            raise ValueError("texel: no receivers given (empty array)")
        n = max(k, d_h.size)
        if depth_dr is None:
            depth_dr = A.to_float(np.broadcast_to(d_h, (n,)), Float)
        elif d_h.size == 1 and n > 1:
            depth_dr = dr.repeat(depth_dr, n) if hasattr(dr, "repeat") else depth_dr + dr.zeros(Float, n)

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
        x = A.to_float(coords[:, 0], Float)
        y = A.to_float(coords[:, 1], Float)
        total = Float(0)
        for tex, w in taps(x, y, width, height, filter, radius, Float, UInt32, Int32):
            total += w * self._eval_texels(tex, depth_dr)
        return total

    def __repr__(self) -> str:
        p = ", ".join(f"{k}={v!r}" for k, v in self.params.items())
        return f"{type(self).__name__}({p}; texels={self.n_texels})"


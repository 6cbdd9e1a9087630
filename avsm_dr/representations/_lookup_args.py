"""A lookup's arguments, checked and converted once (:meth:`.base.Representation.eval`).

Three validation paths, cheapest first (:mod:`avsm_dr._device_checks`): 1. NumPy point
lookups whose min / max prove them valid, evaluated in one launch; 2. Dr.Jit texels / depths,
checked on the device; 3. the host checks below, which raise the ``ValueError`` messages
(naming ``texel``, ``depth``, ``width``, ...) or handle the input (subnormals flushed,
scalars broadcast).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import _device_checks as DC
from .. import backend
from .. import validation as V
from ..filtering import FILTERS, check_radius
from ..segment_dtype import flushed, has_subnormal


@dataclass
class Lookup:
    """A lookup's checked arguments: ``T`` when a fast path evaluated the point lookup, else
    ``depth`` (Float (n,), AD graph kept) with ``texel`` (UInt32 (n,), point) or ``coords``
    ((n, 2) float64 texel units, filtered over ``width`` x ``height`` with ``radius``)."""

    T: Any = None
    texel: Any = None
    coords: np.ndarray | None = None
    depth: Any = None
    width: int | None = None
    height: int | None = None
    radius: float = 1.0


def _device_checked(rep, kernel, texel, depth, filter: str):
    """Paths 1 and 2: ``(T, None, None, False)`` when a point lookup was evaluated, else
    ``(None, tex_dev, dep_dev, tex_np)`` (None: the host checks take it; ``tex_np``: NumPy
    texels already checked by their min / max)."""
    seg, Float, n_texels = rep.segments, rep.Float, rep.n_texels
    if filter == "point" and (T := DC.host_point_lookup(kernel, texel, depth, n_texels, seg.dtype,
                                                        Float)) is not None:
        return T, None, None, False            # NumPy input checked by min / max, read as it is
    tex_dev = texel if filter == "point" and DC.flat(texel) else None
    tex_np = filter == "point" and tex_dev is None and (tex_dev := DC.host_texels(texel, n_texels)) is not None
    dep_dev = depth if DC.flat(depth) else DC.host_depth(depth, Float)
    if tex_dev is not None and dep_dev is not None and (
            dr.width(tex_dev) == dr.width(dep_dev) or 1 in (dr.width(tex_dev), dr.width(dep_dev))):
        T = DC.point_lookup(kernel, tex_dev, tex_np, dep_dev, dep_dev is not depth, n_texels, seg.dtype, Float)
        if T is not None:
            return T, None, None, False
        return None, None, None, False                     # the host checks raise
    masks = ([DC.texel_mask(tex_dev, n_texels)] if tex_dev is not None and not tex_np else []) + \
        ([DC.depth_mask(dep_dev, seg.dtype, strict=dep_dev is not depth)] if dep_dev is not None else [])
    if masks and not DC.all_true(*masks):
        return None, None, None, False
    return None, tex_dev, dep_dev, tex_np


def _host_texels(texel, width, height):
    """Path 3 for ``texel``: ``(indices, coords, k)``, float64 host indices (K,) or
    continuous coordinates (K, 2) (then ``indices`` is None), checked finite."""
    tex_h = A.host(texel, "texel", np.float64)      # numbers only (no bool, str, complex)
    coords = None
    if tex_h.ndim == 2:
        if tex_h.shape[1] != 2:
            raise ValueError(f"texel: continuous coordinates must have shape (K, 2), got {tex_h.shape}")
        if width is None or height is None:
            raise ValueError("width: continuous texel coordinates need width= and height=")
        coords, k = tex_h, tex_h.shape[0]
    elif tex_h.ndim <= 1:
        tex_h = np.atleast_1d(tex_h)
        k = tex_h.size
    else:
        raise ValueError(f"texel: expected shape (K,) or (K, 2), got {tex_h.shape}")
    A.check_finite(tex_h, "texel")
    return (None if coords is not None else tex_h), coords, k


def _host_depths(seg, depth, Float):
    """Path 3 for ``depth``: ``(host depths, Dr.Jit depths or None)``, finite in the storage
    dtype; a Dr.Jit ``depth`` is kept (AD graph) with its subnormals flushed."""
    raw = np.atleast_1d(A.host(depth, "depth"))          # numbers only (no bool, str, complex)
    if raw.ndim > 1:
        raise ValueError(f"depth: expected shape (K,), got {raw.shape}")
    d_h = seg.check_depth(raw, "depth")                  # finite in the storage dtype
    depth_dr = A.to_float(depth, Float) if A.is_drjit(depth) else None
    if depth_dr is not None and has_subnormal(raw, seg.dtype):
        depth_dr = flushed(depth_dr, seg.dtype)
    return d_h, depth_dr


def lookup_args(rep, kernel, texel, depth, filter: str = "point", width: int | None = None,
                height: int | None = None, radius: float = 1.0, prefilter: bool = False) -> Lookup:
    """The checked arguments of ``rep.eval(texel, depth, filter, width, height, radius,
    prefilter)`` (its docstring gives them); ``kernel``: ``rep``'s per-texel lookup
    ``(UInt32 texel, Float depth) -> Float``, run here by the point fast paths."""
    V.one_of(filter, "filter", FILTERS)
    if not isinstance(prefilter, (bool, np.bool_)):
        raise ValueError(f"prefilter: expected a bool, got {prefilter!r}")
    if prefilter and not rep.prefilterable:
        raise ValueError(f"prefilter: kind {rep.kind!r} is not linear in a stored map "
                         "(prefilterable = False); filter its T instead (prefilter=False)")
    if prefilter and filter == "point":
        raise ValueError("prefilter: needs a non-point filter ('bilinear', 'box', 'gaussian')")
    width = None if width is None else V.integer(width, "width", 1)
    height = None if height is None else V.integer(height, "height", 1)
    radius = check_radius(radius, width, height)
    T, tex_dev, dep_dev, tex_np = _device_checked(rep, kernel, texel, depth, filter)
    if T is not None:
        return Lookup(T=T)
    seg, Float, UInt32 = rep.segments, rep.Float, backend.types().UInt32
    tex_h, coords, k = (None, None, dr.width(tex_dev)) if tex_dev is not None else _host_texels(texel, width, height)
    if dep_dev is not None:
        depth_dr, d_size = A.to_float(dep_dev, Float), dr.width(dep_dev)
    else:
        d_h, depth_dr = _host_depths(seg, depth, Float)
        d_size = d_h.size
    if d_size not in (1, k) and k != 1:
        raise ValueError(f"depth: length {d_size} does not match {k} texels")
    if k == 0 or d_size == 0:
        raise ValueError("texel: no receivers given (empty array)")
    n = max(k, d_size)
    if depth_dr is None:
        depth_dr = A.to_float(np.broadcast_to(d_h, (n,)), Float)
    elif d_size == 1 and n > 1:
        depth_dr = dr.repeat(depth_dr, n)
    if tex_dev is not None:
        tex_d = A.to_uint32(dr.detach(tex_dev))
        return Lookup(texel=tex_d + dr.zeros(UInt32, n) if k == 1 and n > 1 else tex_d, depth=depth_dr)

    if coords is None:
        if np.any(tex_h != np.round(tex_h)) or np.any(tex_h < 0) or np.any(tex_h >= rep.n_texels):
            raise ValueError(f"texel: indices must be integers in [0, {rep.n_texels})")
        tex_h = np.broadcast_to(tex_h, (n,)) if tex_h.size == 1 else tex_h
        if filter == "point":
            return Lookup(texel=A.to_uint32(tex_h.astype(np.uint32)), depth=depth_dr)
        if width is None or height is None:
            raise ValueError(f"width: filter {filter!r} needs the shadow map's width= and height=")
        ti = tex_h.astype(np.int64)
        coords = np.stack([ti % width + 0.5, ti // width + 0.5], axis=1)
    if width * height != rep.n_texels:
        raise ValueError(f"width: width*height = {width * height} does not match {rep.n_texels} texels")
    if coords.shape[0] == 1 and n > 1:
        coords = np.broadcast_to(coords, (n, 2))
    return Lookup(coords=np.asarray(coords, np.float64), depth=depth_dr, width=width, height=height, radius=radius)

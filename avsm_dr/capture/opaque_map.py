"""Opaque content in a separate depth map, composed with the volumetric representation.

``capture(scene, opaque="separate")`` keeps opaque blockers out of the volumetric
segments: they go into a per-texel depth map ``z_o`` (the nearest opaque segment's
start, the depth at which the inline segment of :mod:`.opaque` begins; +inf where no
blocker is hit) and the volumetric segments are cut at ``z_o`` (a segment straddling it
keeps its part in front, with the optical depth scaled by that part's share, which is
the exact curve's own linear ramp).  A lookup multiplies, per filter tap::

    T(texel, z) = T_volume(texel, z) * [z < z_o(texel)]

(:class:`~avsm_dr.representations.opaque_composite.OpaqueComposite`, with the papers this
follows).  ``opaque="inline"`` (default) keeps blockers as
short segments with T -> 0 inside the one representation.
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from .. import _arrays as A
from ..representations.base import Representation
from ..representations.opaque_composite import OpaqueComposite

OPAQUE_MODES = ("inline", "separate")


def depth_map(texel: np.ndarray, z0: np.ndarray, n_texels: int) -> np.ndarray:
    """(n_texels,) float64: the smallest ``z0`` of each texel's opaque segments, +inf where none."""
    out = np.full(int(n_texels), np.inf)
    if np.size(texel):
        np.minimum.at(out, np.asarray(texel, np.int64), np.asarray(z0, np.float64))
    return out


def clip_pieces(pieces, depth: np.ndarray, Float) -> list:
    """Volumetric ``(texel, z0, z1, tau, *extra)`` pieces cut at the depth map: segments starting
    at or behind ``depth[texel]`` are dropped, those straddling it end there with
    ``tau * (depth - z0) / (z1 - z0)``.  ``tau`` keeps its AD graph (gathered, scaled); the
    ``extra`` per-segment arrays (NumPy or Dr.Jit, e.g. draw keys) keep the kept segments'."""
    out = []
    for tex, z0, z1, tau, *extra in pieces:
        tex = np.asarray(tex, np.int64)
        z0h, z1h = A.host(z0, "z0"), A.host(z1, "z1")
        zo = depth[tex]
        keep = np.nonzero(z0h < zo)[0]
        if keep.size == 0:
            continue
        cut = z1h[keep] > zo[keep]
        frac = np.where(cut, (zo[keep] - z0h[keep]) / np.where(cut, z1h[keep] - z0h[keep], 1.0), 1.0)
        kept = A.to_uint32(keep.astype(np.uint32))
        t = dr.gather(Float, A.to_float(tau, Float), kept)
        more = tuple(x[keep] if isinstance(x, np.ndarray) else dr.gather(type(x), x, kept) for x in extra)
        out.append((tex[keep], z0h[keep], np.where(cut, zo[keep], z1h[keep]), t * A.to_float(frac, Float)) + more)
    return out


def compose(rep: Representation, depth) -> Representation:
    """``rep`` composed with the opaque depth map ``depth`` (None: ``rep`` itself; an
    already composed representation is returned as is)."""
    if depth is None or isinstance(rep, OpaqueComposite):
        return rep
    return OpaqueComposite(rep, depth)

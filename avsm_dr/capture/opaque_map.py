"""Opaque blockers: short segments that take transmittance to zero, or a separate depth map.

Inline (``capture(..., opaque='inline')``, the default; Salvi et al., "Adaptive Volumetric
Shadow Maps", EGSR 2010, sec. 3: "a short, dense segment that takes the transmittance to
zero at the exit point"): a texel ray first meets the blocker's surface at depth ``t_hit``
(:meth:`avsm_dr.scene.Blocker.first_hit`); the segment is ``[t_hit + b, t_hit + b +
thickness]`` with optical depth ``OPAQUE_OPTICAL_DEPTH`` (exit transmittance exactly 0).  The
bias ``b`` keeps receivers lying on the lit surface lit (no "shadow acne"): a receiver
anywhere in the texel's footprint lies on the surface up to ``w tan(theta)`` deeper than the
texel's ray hit (w the footprint width, theta the angle between ray and surface normal), so ::

    b = bias + slope * w * (min(tan(theta), 10) + 0.5)

with ``slope`` = 2 texels by default (also covers bilinear lookups of neighbours); the
``+ 0.5`` covers the change of slope across curved surfaces.  Grazing surfaces and the points
of a box's side face within a texel of an edge can still self-shadow.

Separate (``opaque='separate'``): blockers go into a per-texel depth map ``z_o`` (the depth
where the inline segment would begin; +inf where no blocker is hit) and the volumetric
segments are cut at ``z_o`` (a segment straddling it keeps its part in front, its optical
depth scaled by that part's share).  A lookup multiplies, per filter tap::

    T(texel, z) = T_volume(texel, z) * [z < z_o(texel)]

(:class:`~avsm_dr.representations.opaque_composite.OpaqueComposite`, with the papers this follows).
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from .. import _arrays as A
from ..representations.base import Representation
from ..representations.opaque_composite import OpaqueComposite

OPAQUE_MODES = ("inline", "separate")


def capture_opaque(camera, blockers, bias: float, thickness: float, slope: float = 2.0):
    """(texel, z0, z1) float64 NumPy for every (texel, blocker) hit (tau is OPAQUE_OPTICAL_DEPTH)
    and the (S,) int64 index of each segment's blocker in the list."""
    def hit(item, o, d):                    # one blocker per chunk (chunk = 1 box)
        t, m, cos = blockers[item[0]].first_hit(o, d)
        return t, cos, m
    lo, hi = (np.array([b.bounds()[k] for b in blockers], np.float64).reshape(-1, 3) for k in (0, 1))
    bid, tex, t, cos = camera.footprint_hits(lo, hi, hit, 2)
    tan = np.sqrt(np.maximum(1 - cos * cos, 0)) / np.maximum(cos, 0.1)
    z0 = t + bias + slope * camera.texel_width(tex, t) * (tan + 0.5)
    return tex, z0, z0 + thickness, bid


def depth_map(texel: np.ndarray, z0: np.ndarray, n_texels: int) -> np.ndarray:
    """(n_texels,) float64: the smallest ``z0`` of each texel's opaque segments, +inf where none."""
    out = np.full(int(n_texels), np.inf)
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

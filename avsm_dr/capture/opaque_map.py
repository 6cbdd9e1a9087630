"""Opaque content in a separate depth map, composed with the volumetric representation.

``capture(scene, opaque="separate")`` keeps opaque blockers out of the volumetric
segments: they go into a per-texel depth map ``z_o`` (the nearest opaque segment's
start, the depth at which the inline segment of :mod:`.opaque` begins; +inf where no
blocker is hit) and the volumetric segments are cut at ``z_o`` (a segment straddling it
keeps its part in front, with the optical depth scaled by that part's share, which is
the exact curve's own linear ramp).  A lookup multiplies, per filter tap::

    T(texel, z) = T_volume(texel, z) * [z < z_o(texel)]

(:class:`OpaqueComposite`).  This is how volumetric shadow maps are used with opaque
geometry: Jansen and Bavoil, "Fourier Opacity Mapping", I3D 2010, sec. 4 (an opaque
shadow map next to the opacity map), and Peters and Klein, "Moment Shadow Mapping",
I3D 2015; the opaque step then never passes through a compressed form (no ringing of
Fourier series or moments at the step).  ``opaque="inline"`` (default) keeps blockers as
short segments with T -> 0 inside the one representation.
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from .. import _arrays as A
from ..representations.base import Representation

OPAQUE_MODES = ("inline", "separate")


def depth_map(texel: np.ndarray, z0: np.ndarray, n_texels: int) -> np.ndarray:
    """(n_texels,) float64: the smallest ``z0`` of each texel's opaque segments, +inf where none."""
    out = np.full(int(n_texels), np.inf)
    if np.size(texel):
        np.minimum.at(out, np.asarray(texel, np.int64), np.asarray(z0, np.float64))
    return out


def clip_pieces(pieces, depth: np.ndarray, Float) -> list:
    """Volumetric ``(texel, z0, z1, tau)`` pieces cut at the depth map: segments starting at
    or behind ``depth[texel]`` are dropped, those straddling it end there with
    ``tau * (depth - z0) / (z1 - z0)``.  ``tau`` keeps its AD graph (gathered, scaled)."""
    out = []
    for tex, z0, z1, tau in pieces:
        tex = np.asarray(tex, np.int64)
        z0h, z1h = A.host(z0, "z0"), A.host(z1, "z1")
        zo = depth[tex]
        keep = np.nonzero(z0h < zo)[0]
        if keep.size == 0:
            continue
        cut = z1h[keep] > zo[keep]
        frac = np.where(cut, (zo[keep] - z0h[keep]) / np.where(cut, z1h[keep] - z0h[keep], 1.0), 1.0)
        t = dr.gather(Float, A.to_float(tau, Float), A.to_uint32(keep.astype(np.uint32)))
        out.append((tex[keep], z0h[keep], np.where(cut, zo[keep], z1h[keep]), t * A.to_float(frac, Float)))
    return out


class OpaqueComposite(Representation):
    """A volumetric representation composed with an opaque depth map (module docstring):
    ``T = T_volume(texel, z) * [z < z_o(texel)]`` per lookup tap, so every filter of
    :meth:`~avsm_dr.representations.base.Representation.eval` applies the depth test per
    texel (percentage-closer) before weighting.

    volume: a built representation; depth: (n_texels,) opaque depths (+inf: none).
    Storage: the volume's bytes plus one depth per texel in the segments' dtype.
    Traits (monotone, differentiable, unity_in_front) are the volume's; gradients flow
    to the volume's segments, not to the opaque depths.
    """

    kind = "opaque_composite"

    def __init__(self, volume: Representation, depth):
        if not isinstance(volume, Representation):
            raise ValueError(f"volume: expected a built representation, got {type(volume).__name__}")
        d = np.asarray(depth, np.float64).ravel()
        if d.size != volume.n_texels or np.any(np.isnan(d)):
            raise ValueError(f"depth: expected {volume.n_texels} depths (no NaN), got {d.size}")
        super().__init__(volume.segments)
        self.volume = volume
        big = float(np.finfo(volume.segments.dtype).max)
        self.depth = A.to_float(np.minimum(d, big), volume.Float)   # +inf stored as the largest finite

    @property
    def monotone(self) -> bool:
        return self.volume.monotone

    @property
    def differentiable(self) -> bool:
        return self.volume.differentiable

    @property
    def unity_in_front(self) -> bool:
        return self.volume.unity_in_front

    @property
    def nbytes_per_texel(self) -> float:
        return self.volume.nbytes_per_texel + self.segments.itemsize

    def _eval_texels(self, texel, depth):
        T = self.volume._eval_texels(texel, depth)
        zo = dr.gather(type(self.depth), self.depth, texel)
        return dr.select(depth < zo, T, 0.0)


def compose(rep: Representation, depth) -> Representation:
    """``rep`` composed with the opaque depth map ``depth`` (None: ``rep`` itself; an
    already composed representation is returned as is)."""
    if depth is None or isinstance(rep, OpaqueComposite):
        return rep
    return OpaqueComposite(rep, depth)

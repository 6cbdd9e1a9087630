"""A volumetric representation composed with an opaque depth map.

``capture(scene, opaque="separate")`` (:mod:`avsm_dr.capture.opaque_map`) keeps opaque
blockers out of the volumetric segments, in a per-texel depth map ``z_o`` (+inf where no
blocker is hit).  A lookup multiplies, per filter tap::

    T(texel, z) = T_volume(texel, z) * [z < z_o(texel)]

as volumetric shadow maps are used with opaque geometry (Jansen and Bavoil, "Fourier Opacity
Mapping", I3D 2010, sec. 4; Peters and Klein, "Moment Shadow Mapping", I3D 2015): the opaque
step never passes through a compressed form.
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from .. import _arrays as A
from .base import Representation


class OpaqueComposite(Representation):
    """The module docstring's composite, per lookup tap: every filter applies the depth test
    per texel (percentage-closer).  volume: a built representation; depth: (n_texels,) opaque
    depths (+inf: none).  Storage: the volume's bytes plus one depth per texel in the segments'
    dtype.  Traits are the volume's; gradients flow to the volume's segments, not to the depths.
    """

    kind = "opaque_composite"

    def __init__(self, volume: Representation, depth):
        # its own signature (a built volume, not segments): checked here, then the template
        if not isinstance(volume, Representation):
            raise ValueError(f"volume: expected a built representation, got {type(volume).__name__}")
        d = np.asarray(depth, np.float64).ravel()
        if d.size != volume.n_texels or np.any(np.isnan(d)):
            raise ValueError(f"depth: expected {volume.n_texels} depths (no NaN), got {d.size}")
        self.volume, self.depth = volume, d
        super().__init__(volume.segments)

    def _build(self):
        big = float(np.finfo(self.segments.dtype).max)
        self.depth = A.to_float(np.minimum(self.depth, big), self.Float)   # +inf stored as the largest finite

    monotone, differentiable, unity_in_front = (property(lambda self, n=n: getattr(self.volume, n))
                                                for n in ("monotone", "differentiable", "unity_in_front"))

    @property
    def nbytes_per_texel(self) -> float:
        return self.volume.nbytes_per_texel + self.segments.itemsize

    def _eval_texels(self, texel, depth):
        T = self.volume._eval_texels(texel, depth)
        return dr.select(depth < dr.gather(type(self.depth), self.depth, texel), T, 0.0)

"""Opaque blockers as short segments that take transmittance to zero (Salvi et al.,
"Adaptive Volumetric Shadow Maps", EGSR 2010, sec. 3:
"a short, dense segment that takes the transmittance to zero at the exit point").

A texel ray first meets the blocker's surface at depth ``t_hit``; the segment is
``[t_hit + b, t_hit + b + thickness]`` with optical depth ``OPAQUE_OPTICAL_DEPTH``
(exit transmittance exactly 0); behind it everything is black.  The bias ``b`` keeps
receivers lying on the lit surface lit (no "shadow acne"): a receiver anywhere in the
texel's footprint lies on the surface up to ``w tan(theta)`` deeper than the texel's
ray hit (w the footprint width, theta the angle between ray and surface normal), so ::

    b = bias + slope * w * (min(tan(theta), 10) + 0.5)

with ``slope`` = 2 texels by default (also covers bilinear lookups of neighbours); the
``+ 0.5`` covers the change of slope across curved surfaces (spheres).  Measured: no
self-shadowing of surface points whose cos(theta) > 0.5 with point or bilinear lookups at
64^2..256^2 (tests/test_capture.py); grazing surfaces and the points of a box's side
face within a texel of an edge can still self-shadow (their texel may see another face).

Each blocker type computes its own first hit (:meth:`avsm_dr.scene.Blocker.first_hit`).
"""
from __future__ import annotations

import numpy as np


def capture_opaque(camera, blockers, bias: float, thickness: float, slope: float = 2.0, ids: bool = False):
    """(texel, z0, z1) float64 NumPy for every (texel, blocker) hit; tau is OPAQUE_OPTICAL_DEPTH;
    with ``ids`` also the (S,) int64 index of each segment's blocker in the list."""
    tex, z0, bid = [], [], []
    for i, b in enumerate(blockers):
        lo, hi = b.bounds()
        for _, texel, o, d in camera.footprint_rays(lo[None], hi[None]):
            t, hit, cos = b.first_hit(o, d)
            texel, t, cos = texel[hit], t[hit], cos[hit]
            tan = np.sqrt(np.maximum(1 - cos * cos, 0)) / np.maximum(cos, 0.1)
            tex.append(texel)
            z0.append(t + bias + slope * camera.texel_width(texel, t) * (tan + 0.5))
            bid.append(np.full(texel.size, i, np.int64))
    if not tex:
        return (np.zeros(0, np.int64), np.zeros(0), np.zeros(0)) + ((np.zeros(0, np.int64),) if ids else ())
    tex, z0 = np.concatenate(tex), np.concatenate(z0)
    return (tex, z0, z0 + thickness) + ((np.concatenate(bid),) if ids else ())

"""Spherical particles as light-aligned segments (Salvi et al., "Adaptive Volumetric Shadow
Maps", EGSR 2010, sec. 3: "a segment representing the ray's traversal through the particle").

A texel ray ``o + t d`` (``|d| = 1``) meets the sphere (c, r) where its distance to the
centre ``b = |(c - o) - ((c - o) . d) d|`` is below r; the segment is the exact chord ::

    z0, z1 = (c - o) . d -+ sqrt(r^2 - b^2),      tau = sigma * (z1 - z0)

clipped to t >= 0 (a perspective light inside a particle sees the chord from itself).
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from .. import _arrays as A
from ..geometry import ray_sphere

#: Particles whose footprint rectangles are computed at once (bounds host memory).
CHUNK = 4096


def capture_particles(camera, particles, Float):
    """Segments of all particles: (texel (S,) int64, z0, z1 (S,) float64 NumPy, tau Dr.Jit ``Float``,
    the (S,) int64 index of each segment's particle in the list).  tau = density * chord; a
    Dr.Jit ``particles.density`` is gathered (gradients flow to the per-particle densities)."""
    c, r, s = particles.validate()
    lo, hi = c - r[:, None], c + r[:, None]
    pid, tex, z0, z1 = camera.footprint_hits(lo, hi, lambda i, o, d: ray_sphere(o, d, c[i], r[i], t_min=0.0),
                                             2, CHUNK, "particles")
    length = A.to_float(z1 - z0, Float)
    if A.is_drjit(particles.density):
        dens = dr.gather(Float, A.to_float(particles.density, Float), A.to_uint32(pid))
    else:
        dens = A.to_float(s[pid], Float)
    return tex, z0, z1, dens * length, pid


def draw_ranks(camera, particles, submission: str) -> np.ndarray:
    """(P,) int64 draw position of every particle: its list index (``'list'``), or its rank
    back to front (``'back_to_front'``: by the light-space depth of its centre,
    ``camera.project``, farthest first, ties in list order; the sort of alpha blending)."""
    c, _, _ = particles.validate()
    if submission == "list":
        return np.arange(c.shape[0], dtype=np.int64)
    return np.argsort(np.argsort(-camera.project(c)[1], kind="stable"))     # the inverse permutation

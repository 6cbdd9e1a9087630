"""Spherical particles as light-aligned segments (Salvi et al., "Adaptive Volumetric Shadow
Maps", EGSR 2010, sec. 3: "a segment representing the ray's traversal through the particle").

A texel ray ``o + t d`` (|d| = 1) meets the sphere (c, r) where its distance to the
centre ``b = |(c - o) - ((c - o) . d) d|`` is below r; the segment is the exact chord

    z0, z1 = (c - o) . d -+ sqrt(r^2 - b^2),      tau = sigma * (z1 - z0)

clipped to t >= 0 (a perspective light inside a particle sees the chord from itself).
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import validation as V

#: Particles whose footprint rectangles are computed at once (bounds host memory; the
#: (particle, texel) pairs are then enumerated in chunks of ``camera.MAX_PAIRS``).
CHUNK = 4096
#: Most (item, texel) candidate pairs one capture enumerates (each becomes at most one
#: segment, ~40 bytes on the host while sorting): 2^27.
MAX_CANDIDATES = 1 << 27


def validate(particles):
    """Host copies (centers (P, 3), radii (P,), density (P,)) after checks; ValueError names the field.

    At least one particle (an empty cloud is ``particles=None``).
    """
    c = V.array(particles.centers, "particles.centers")
    r = V.array(particles.radii, "particles.radii").reshape(-1)
    s = V.array(particles.density, "particles.density").reshape(-1)
    if c.ndim != 2 or c.shape[1] != 3:
        raise ValueError(f"particles.centers: expected shape (P, 3), got {c.shape}")
    P = c.shape[0]
    if P == 0:
        raise ValueError("particles.centers: no particles (P = 0); leave Scene.particles = None "
                         "for a scene without particles")
    for name, a in (("particles.radii", r), ("particles.density", s)):
        if a.size != P:
            raise ValueError(f"{name}: expected {P} values (one per particle), got {a.size}")
    if np.any(r <= 0):
        raise ValueError("particles.radii: radii must be > 0")
    if np.any(s < 0):
        raise ValueError("particles.density: negative density")
    return c, r, s


def check_candidates(camera, bmin, bmax, name: str, limit: int) -> None:
    """ValueError naming ``name`` when the boxes' footprints hold more than ``limit``
    (item, texel) pairs (counted chunk by chunk, without enumerating them)."""
    total = 0
    for start in range(0, bmin.shape[0], CHUNK):
        total += camera.footprint_pairs(bmin[start:start + CHUNK], bmax[start:start + CHUNK])
    if total > limit:
        raise ValueError(f"{name}: the footprints cover {total:.3g} (item, texel) pairs, more than the "
                         f"{limit:.3g} one capture handles; use fewer or smaller items, or a lower "
                         f"resolution")


def chords(o, d, c, r):
    """(t0, t1, hit) of rays (o, d) (K, 3) with spheres (c (K, 3), r (K,)), float64, t >= 0."""
    oc = c - o
    b = np.einsum("ij,ij->i", oc, d)
    perp = oc - b[:, None] * d
    h2 = r * r - np.einsum("ij,ij->i", perp, perp)
    hit = h2 > 0
    s = np.sqrt(np.where(hit, h2, 0.0))
    t0 = np.maximum(b - s, 0.0)
    t1 = b + s
    return t0, t1, hit & (t1 > t0)


def capture_particles(camera, particles, Float):
    """Segments of all particles: (texel (S,) int64, z0, z1 (S,) float64 NumPy, tau Dr.Jit ``Float``).

    tau = density * chord; when ``particles.density`` is a Dr.Jit array it is gathered
    (gradients flow to the per-particle densities).
    """
    c, r, s = validate(particles)
    lo, hi = c - r[:, None], c + r[:, None]
    check_candidates(camera, lo, hi, "particles", MAX_CANDIDATES)
    tex, z0, z1, pid = [], [], [], []
    for start in range(0, c.shape[0], CHUNK):
        sl = slice(start, start + CHUNK)
        for item, texel in camera.footprint_chunks(lo[sl], hi[sl]):
            item = item + start
            o, d = camera.rays(texel)
            t0, t1, hit = chords(o, d, c[item], r[item])
            tex.append(texel[hit])
            z0.append(t0[hit])
            z1.append(t1[hit])
            pid.append(item[hit])
    if not tex:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0), Float()
    tex, z0, z1, pid = (np.concatenate(a) for a in (tex, z0, z1, pid))
    length = A.to_float(z1 - z0, Float)
    if A.is_drjit(particles.density):
        dens = dr.gather(Float, A.to_float(particles.density, Float), A.to_uint32(pid))
    else:
        dens = A.to_float(s[pid], Float)
    return tex, z0, z1, dens * length

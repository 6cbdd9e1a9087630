"""Spherical particles as light-aligned segments (seed 000 sec. 3: "a segment representing
the ray's traversal through the particle").

A texel ray ``o + t d`` (|d| = 1) meets the sphere (c, r) where its distance to the
centre ``b = |(c - o) - ((c - o) . d) d|`` is below r; the segment is the exact chord

    z0, z1 = (c - o) . d -+ sqrt(r^2 - b^2),      tau = sigma * (z1 - z0)

clipped to t >= 0 (a perspective light inside a particle sees the chord from itself).
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from .. import _arrays as A

#: Particles whose footprints are enumerated at once (bounds host memory).
CHUNK = 4096


def validate(particles):
    """Host copies (centers (P, 3), radii (P,), density (P,)) after checks; ValueError names the field."""
    c = A.host(particles.centers, "particles.centers")
    r = A.host(particles.radii, "particles.radii").reshape(-1)
    s = A.host(particles.density, "particles.density").reshape(-1)
    if c.ndim != 2 or c.shape[1] != 3:
        raise ValueError(f"particles.centers: expected shape (P, 3), got {c.shape}")
    P = c.shape[0]
    for name, a in (("particles.radii", r), ("particles.density", s)):
        if a.size != P:
            raise ValueError(f"{name}: expected {P} values (one per particle), got {a.size}")
    for name, a in (("particles.centers", c), ("particles.radii", r), ("particles.density", s)):
        A.check_finite(a, name)
    if np.any(r <= 0):
        raise ValueError("particles.radii: radii must be > 0")
    if np.any(s < 0):
        raise ValueError("particles.density: negative density")
    return c, r, s


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
    tex, z0, z1, pid = [], [], [], []
    for start in range(0, c.shape[0], CHUNK):
        sl = slice(start, start + CHUNK)
        item, texel = camera.footprint(c[sl] - r[sl, None], c[sl] + r[sl, None])
        if texel.size == 0:
            continue
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

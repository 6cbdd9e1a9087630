"""Opaque blockers as short segments that take transmittance to zero (Salvi et al.,
"Adaptive Volumetric Shadow Maps", EGSR 2010, sec. 3:
"a short, dense segment that takes the transmittance to zero at the exit point").

A texel ray first meets the blocker's surface at depth ``t_hit``; the segment is
``[t_hit + b, t_hit + b + thickness]`` with optical depth ``OPAQUE_OPTICAL_DEPTH``
(exit transmittance exactly 0); behind it everything is black.  The bias ``b`` keeps
receivers lying on the lit surface lit (no "shadow acne"): a receiver anywhere in the
texel's footprint lies on the surface up to ``w tan(theta)`` deeper than the texel's
ray hit (w the footprint width, theta the angle between ray and surface normal), so

    b = bias + slope * w * (min(tan(theta), 10) + 0.5)

with ``slope`` = 2 texels by default (also covers bilinear lookups of neighbours); the
``+ 0.5`` covers the change of slope across curved surfaces (spheres).  Measured: no
self-shadowing of surface points whose cos(theta) > 0.5 with point or bilinear lookups at
64^2..256^2 (tests/test_capture.py); grazing surfaces and the points of a box's side
face within a texel of an edge can still self-shadow (their texel may see another face).

OpaqueSphere: first root of |o + t d - c| = r.  OpaqueBox: slab entry.
OpaquePlane: the square ``|(p - point) . u| <= extent``, ``|(p - point) . v| <= extent``
with (u, v, normal) = :func:`~avsm_dr.geometry.orthonormal_basis` (normal),
blocking from both sides.
"""
from __future__ import annotations

import numpy as np

from ..geometry import orthonormal_basis, ray_box, ray_sphere
from ..scene import OpaqueBox, OpaqueSphere


def bounds(b) -> tuple[np.ndarray, np.ndarray]:
    """World AABB of a validated blocker."""
    if isinstance(b, OpaqueSphere):
        return b.center - b.radius, b.center + b.radius
    if isinstance(b, OpaqueBox):
        return b.min, b.max
    u, v, _ = orthonormal_basis(b.normal)
    half = b.extent * (np.abs(u) + np.abs(v))
    return b.point - half, b.point + half


def contains(b, p) -> bool:
    """True when the point p lies inside a solid blocker (planes contain nothing)."""
    if isinstance(b, OpaqueSphere):
        return bool(np.linalg.norm(p - b.center) < b.radius)
    if isinstance(b, OpaqueBox):
        return bool(np.all((p > b.min) & (p < b.max)))
    return False


def first_hit(b, o, d):
    """(t_hit, hit, cos) of rays (o, d) (K, 3) with a validated blocker, t_hit >= 0;
    cos = |d . n| with n the surface normal at the hit."""
    if isinstance(b, OpaqueSphere):
        c = np.broadcast_to(b.center, o.shape)
        t0, _, hit = ray_sphere(o, d, c, np.full(o.shape[0], b.radius), t_min=0.0)
        n = (o + t0[:, None] * d - c) / b.radius
        return t0, hit, np.abs(np.einsum("ij,ij->i", n, d))
    if isinstance(b, OpaqueBox):
        t0, _, hit = ray_box(o, d, b.min, b.max, t_min=0.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            ta = (b.min - o) / d
            tb = (b.max - o) / d
        entry = np.where(np.isnan(ta), -np.inf, np.minimum(ta, tb))
        axis = np.argmax(entry, axis=1)                  # the face the ray enters through
        return t0, hit, np.abs(d[np.arange(d.shape[0]), axis])
    u, v, n = orthonormal_basis(b.normal)
    dn = d @ n
    ok = np.abs(dn) > 1e-12
    t = np.where(ok, ((b.point - o) @ n) / np.where(ok, dn, 1.0), -1.0)
    q = o + t[:, None] * d - b.point
    hit = ok & (t >= 0) & (np.abs(q @ u) <= b.extent) & (np.abs(q @ v) <= b.extent)
    return t, hit, np.abs(dn)


def capture_opaque(camera, blockers, bias: float, thickness: float, slope: float = 2.0, ids: bool = False):
    """(texel, z0, z1) float64 NumPy for every (texel, blocker) hit; tau is OPAQUE_OPTICAL_DEPTH;
    with ``ids`` also the (S,) int64 index of each segment's blocker in the list."""
    tex, z0, bid = [], [], []
    for i, b in enumerate(blockers):
        lo, hi = bounds(b)
        for _, texel in camera.footprint_chunks(lo[None], hi[None]):
            o, d = camera.rays(texel)
            t, hit, cos = first_hit(b, o, d)
            texel, t, cos = texel[hit], t[hit], cos[hit]
            tan = np.sqrt(np.maximum(1 - cos * cos, 0)) / np.maximum(cos, 0.1)
            tex.append(texel)
            z0.append(t + bias + slope * camera.texel_width(texel, t) * (tan + 0.5))
            bid.append(np.full(texel.size, i, np.int64))
    if not tex:
        return (np.zeros(0, np.int64), np.zeros(0), np.zeros(0)) + ((np.zeros(0, np.int64),) if ids else ())
    tex, z0 = np.concatenate(tex), np.concatenate(z0)
    return (tex, z0, z0 + thickness) + ((np.concatenate(bid),) if ids else ())

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
with (u, v, normal) = :func:`~avsm_dr.capture.camera.orthonormal_basis` (normal),
blocking from both sides.
"""
from __future__ import annotations

import numpy as np

from .. import validation as V
from ..scene import OpaqueBox, OpaquePlane, OpaqueSphere
from .camera import orthonormal_basis
from .grid import clip_rays
from .particles import chords


def validate(blockers) -> list:
    """Check every blocker; ValueError names ``blockers[i].field``."""
    if not isinstance(blockers, (list, tuple)):
        raise ValueError(f"blockers: expected a list, got {type(blockers).__name__}")
    out = []
    for i, b in enumerate(blockers):
        name = f"blockers[{i}]"
        if isinstance(b, OpaqueSphere):
            out.append(OpaqueSphere(V.vec3(b.center, f"{name}.center"),
                                    V.real(b.radius, f"{name}.radius", 0.0, open_min=True)))
        elif isinstance(b, OpaqueBox):
            lo, hi = V.vec3(b.min, f"{name}.min"), V.vec3(b.max, f"{name}.max")
            if np.any(hi <= lo):
                raise ValueError(f"{name}.max: zero-size box (max must exceed min on every axis)")
            out.append(OpaqueBox(lo, hi))
        elif isinstance(b, OpaquePlane):
            out.append(OpaquePlane(V.vec3(b.point, f"{name}.point"), V.unit_vector(b.normal, f"{name}.normal"),
                                   V.real(b.extent, f"{name}.extent", 0.0, open_min=True)))
        else:
            raise ValueError(f"{name}: expected OpaqueSphere, OpaqueBox or OpaquePlane, got {type(b).__name__}")
    return out


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
        t0, _, hit = chords(o, d, c, np.full(o.shape[0], b.radius))
        n = (o + t0[:, None] * d - c) / b.radius
        return t0, hit, np.abs(np.einsum("ij,ij->i", n, d))
    if isinstance(b, OpaqueBox):
        t0, _, hit = clip_rays(o, d, b.min, b.max)
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


def capture_opaque(camera, blockers, bias: float, thickness: float, slope: float = 2.0):
    """(texel, z0, z1) float64 NumPy for every (texel, blocker) hit; tau is OPAQUE_OPTICAL_DEPTH."""
    tex, z0 = [], []
    for b in blockers:
        lo, hi = bounds(b)
        for _, texel in camera.footprint_chunks(lo[None], hi[None]):
            o, d = camera.rays(texel)
            t, hit, cos = first_hit(b, o, d)
            texel, t, cos = texel[hit], t[hit], cos[hit]
            tan = np.sqrt(np.maximum(1 - cos * cos, 0)) / np.maximum(cos, 0.1)
            tex.append(texel)
            z0.append(t + bias + slope * camera.texel_width(texel, t) * (tan + 0.5))
    if not tex:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    tex, z0 = np.concatenate(tex), np.concatenate(z0)
    return tex, z0, z0 + thickness

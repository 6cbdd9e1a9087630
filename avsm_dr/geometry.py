"""Ray geometry shared by capture, ground truth, shading, area lights and the integrator.

One home for ray-box, ray-sphere, ray-capsule, the package's orthonormal frame, box corners and the box check.
Convention: ``f`` works on NumPy float64 host arrays, ``f_dr`` is the same formula in
Dr.Jit (any float type: ``Float``/``Float64`` lanes, Mitsuba's ``Float``).  In float64
:func:`ray_box_dr` equals :func:`ray_box` bit for bit (the same operations in the same
order); :func:`ray_sphere_dr` equals :func:`ray_sphere` up to rounding (``dr.dot`` fuses
multiply-adds, NumPy's ``einsum`` does not).

Rays are ``o + t d``; a hit interval is ``[t_near, t_far]`` clipped below at ``t_min``
(default ``-inf``: the whole line), and ``hit = t_far > t_near`` (a chord of positive length).
Missed rays' ``t`` values are not meaningful; read them through ``hit``.
"""
from __future__ import annotations

import math

import drjit as dr
import numpy as np

from . import validation as V


def check_bbox(bbox, name: str = "bbox", flat: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) float64 (3,) corners of a finite box with ``hi > lo`` on every axis (``hi >= lo``
    with ``flat``); ValueError naming ``name`` for anything else (zero-size or inverted boxes)."""
    try:
        lo, hi = (np.asarray(end, np.float64).reshape(3) for end in bbox)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected (min_xyz, max_xyz), got {bbox!r}") from None
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError(f"{name}: contains NaN or inf")
    if np.any(hi < lo) or (not flat and np.any(hi == lo)):
        raise ValueError(f"{name}: zero-size or inverted box {lo.tolist()} .. {hi.tolist()}")
    return lo, hi


def box_corners(bmin, bmax) -> np.ndarray:
    """(N, 8, 3) corners of N axis-aligned boxes [bmin, bmax] ((N, 3) or (3,) each)."""
    bmin, bmax = (np.asarray(end, np.float64).reshape(-1, 3) for end in (bmin, bmax))
    sel = np.array([[(c >> a) & 1 for a in range(3)] for c in range(8)], dtype=bool)  # (8, 3)
    return np.where(sel[None], bmax[:, None, :], bmin[:, None, :])


def ray_box(o, d, lo, hi, t_min: float = -math.inf):
    """Slab test (Kay & Kajiya, "Ray tracing complex scenes", SIGGRAPH 1986):
    ``(t_near, t_far, hit)`` (K,) of rays o, d (K, 3) with the box [lo, hi] ((3,) each).

    Per axis a: ``t_a = (lo_a - o_a) / d_a``, ``t'_a = (hi_a - o_a) / d_a``;
    ``t_near = max(t_min, max_a min(t_a, t'_a))``, ``t_far = min_a max(t_a, t'_a)``.
    A ray parallel to a slab (``d_a = 0``) is inside it for all t when ``lo_a <= o_a <= hi_a``
    (the closed slab) and misses the box otherwise (``t_near = inf``, ``t_far = -inf``)."""
    o, d = np.asarray(o, np.float64), np.asarray(d, np.float64)
    lo, hi = (np.asarray(end, np.float64).reshape(3) for end in (lo, hi))
    t0 = np.full(o.shape[0], float(t_min))
    t1 = np.full(o.shape[0], np.inf)
    for a in range(3):
        oa, da = np.ascontiguousarray(o[:, a]), np.ascontiguousarray(d[:, a])
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / da
            ta = (lo[a] - oa) * inv
            tb = (hi[a] - oa) * inv
        near, far = np.minimum(ta, tb), np.maximum(ta, tb)
        par = da == 0
        if par.any():
            inside = (oa >= lo[a]) & (oa <= hi[a])
            near = np.where(par, np.where(inside, -np.inf, np.inf), near)
            far = np.where(par, np.where(inside, np.inf, -np.inf), far)
        np.maximum(t0, near, out=t0)
        np.minimum(t1, far, out=t1)
    return t0, t1, t1 > t0


def ray_box_dr(o, d, lo, hi, t_min: float = -math.inf):
    """:func:`ray_box` in Dr.Jit: o, d Dr.Jit 3-vectors (or lists of three arrays) of one float
    type; lo, hi anything indexable by 0..2 (host arrays, Python floats, width-1 or opaque
    Dr.Jit values: the caller chooses what enters the kernel as a literal) -> (t_near, t_far, hit)."""
    t0, t1 = t_min, math.inf
    for a in range(3):
        lo_a, hi_a = _component(lo, a), _component(hi, a)
        inv = 1.0 / d[a]
        ta, tb = (lo_a - o[a]) * inv, (hi_a - o[a]) * inv
        par = d[a] == 0
        inside = (o[a] >= lo_a) & (o[a] <= hi_a)
        near = dr.select(par, dr.select(inside, -math.inf, math.inf), dr.minimum(ta, tb))
        far = dr.select(par, dr.select(inside, math.inf, -math.inf), dr.maximum(ta, tb))
        t0 = dr.maximum(t0, near)
        t1 = dr.minimum(t1, far)
    return t0, t1, t1 > t0


def _component(v, a):
    """``v[a]``, a NumPy scalar as a Python float (NumPy would take a Dr.Jit operand over)."""
    x = v[a]
    return float(x) if isinstance(x, np.generic) else x


def ray_sphere(o, d, c, r, t_min: float = -math.inf):
    """``(t_near, t_far, hit)`` (K,) of rays o, d (K, 3) (|d| = 1) with spheres c ((3,) or
    (K, 3)), r (scalar or (K,)).

    With ``b = (c - o) . d`` and the perpendicular ``p = (c - o) - b d`` (Haines et al.,
    "Precision improvements for ray/sphere intersection", Ray Tracing Gems 2019, ch. 7:
    no cancellation in ``|c - o|^2 - b^2``): ``h^2 = r^2 - |p|^2``, ``s = sqrt(h^2)``,
    ``t_near = max(b - s, t_min)``, ``t_far = b + s``, ``hit = (h^2 > 0) & (t_far > t_near)``."""
    oc = c - o
    b = np.einsum("ij,ij->i", oc, d)
    perp = oc - b[:, None] * d
    h2 = r * r - np.einsum("ij,ij->i", perp, perp)
    hit = h2 > 0
    s = np.sqrt(np.where(hit, h2, 0.0))
    t0 = np.maximum(b - s, t_min)
    t1 = b + s
    return t0, t1, hit & (t1 > t0)


def ray_sphere_dr(o, d, c, r, t_min: float = -math.inf):
    """:func:`ray_sphere` in Dr.Jit: o, d, c Dr.Jit 3-vectors of one float type, r a number
    or array -> (t_near, t_far, hit), the same formula."""
    oc = c - o
    b = dr.dot(oc, d)
    perp = oc - b * d
    h2 = r * r - dr.dot(perp, perp)
    hit = h2 > 0
    s = dr.sqrt(dr.select(hit, h2, 0.0))
    t0 = dr.maximum(b - s, t_min)
    t1 = b + s
    return t0, t1, hit & (t1 > t0)


def ray_capsule(o, d, pa, pb, r, t_min: float = -math.inf):
    """``(t_near, t_far, hit)`` (K,) of unit rays o, d (K, 3) with capsules (segments pa-pb
    (K, 3), radius r): the hull of the chords through the finite cylinder and the two end
    spheres (:func:`ray_sphere`), a capsule being convex.  Cylinder, with ``b = pb - pa``:
    ``|q|^2 |b|^2 - (q . b)^2 = r^2 |b|^2`` for ``q = o - pa + t d``, kept where
    ``0 <= q . b <= |b|^2``; rays parallel to the axis are left to the end spheres.  float64."""
    ba = pb - pa
    oa = o - pa
    L2 = np.einsum("ij,ij->i", ba, ba)
    bd = np.einsum("ij,ij->i", ba, d)
    boa = np.einsum("ij,ij->i", ba, oa)
    od = np.einsum("ij,ij->i", oa, d)
    oo = np.einsum("ij,ij->i", oa, oa)
    t_in = np.full(o.shape[0], np.inf)
    t_out = np.full(o.shape[0], -np.inf)
    a = L2 - bd * bd
    b = L2 * od - boa * bd
    c = L2 * oo - boa * boa - r * r * L2
    disc = b * b - a * c
    cyl = (a > 1e-12 * np.maximum(L2, 1e-300)) & (disc > 0)     # parallel rays: the end spheres cover it
    sq = np.sqrt(np.where(cyl, disc, 0.0))
    sa = np.where(cyl, a, 1.0)
    ta, tb = (-b - sq) / sa, (-b + sq) / sa
    with np.errstate(divide="ignore", invalid="ignore"):
        s0 = (0.0 - boa) / bd
        s1 = (L2 - boa) / bd
    lo_s = np.where(bd != 0, np.minimum(s0, s1), np.where((boa >= 0) & (boa <= L2), -np.inf, np.inf))
    hi_s = np.where(bd != 0, np.maximum(s0, s1), np.where((boa >= 0) & (boa <= L2), np.inf, -np.inf))
    ca, cb = np.maximum(ta, lo_s), np.minimum(tb, hi_s)
    cyl &= cb > ca
    t_in = np.where(cyl, np.minimum(t_in, ca), t_in)
    t_out = np.where(cyl, np.maximum(t_out, cb), t_out)
    for p in (pa, pb):                                          # end spheres
        t0, t1, hs = ray_sphere(o, d, p, r)
        t_in = np.where(hs, np.minimum(t_in, t0), t_in)
        t_out = np.where(hs, np.maximum(t_out, t1), t_out)
    t_in = np.maximum(t_in, t_min)
    return t_in, t_out, t_out > t_in


def orthonormal_basis(w) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, v, w): right-handed orthonormal frame whose third axis is ``w`` (normalised).

    u = normalize(up x w) with up = +y unless w is within ~8 degrees of +-y (then +x);
    v = w x u.  Deterministic; the one frame of the package: every light camera, the
    squares of :class:`~avsm_dr.scene.OpaquePlane` and the receiver plane (ground truth,
    shading), the inverse problem's receiver grid."""
    w = V.unit_vector(w, "w")
    up = np.array([0.0, 1.0, 0.0]) if abs(w[1]) < 0.99 else np.array([1.0, 0.0, 0.0])
    u = np.cross(up, w)
    u /= np.linalg.norm(u)
    v = np.cross(w, u)
    return u, v, w

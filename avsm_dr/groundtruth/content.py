"""Light paths and the analytic part of the ground truth: particles, hair, opaque blockers.

Paths: :func:`light_paths` (a spot's cone does not limit transmittance; shading applies it).
Particles: exact chords (uniform extinction per sphere; overlapping spheres add).  Hair: the
strand model of :mod:`avsm_dr.capture.hair` stated analytically: a strand is a chain of capsules
(radius ``r`` around each polyline segment), a *crossing* a maximal interval of the path inside
one strand's capsules, absorbing ``tau_c = -ln(1 - opacity)`` spread uniformly over it (partial
when ``a < L < b``); cost O(receivers x capsules).  Opaque blockers: ``T = 0`` when the open
path ``(0, L - eps)`` meets one, ``eps = 1e-6 * scene scale`` (a receiver on a blocker's lit
surface stays lit).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from .. import validation as V
from ..geometry import ray_box
from ..scene import Scene, check_light, validate_blockers
from .media import check_grid

#: Upper bound on NumPy (receiver, particle) pair tests per chunk (host memory).
MAX_CHUNK = 1 << 22
#: Relative surface epsilon (times the scene scale) for blocker tests.
EPS_REL = 1e-6


# ===================================================================== validation
def check_scene(scene) -> dict:
    """Validated host copies of the scene's content; ValueError names the field.

    Returns dict(grid=(g, lo, hi) | None, particles=(c, r, s) | None,
    hair=(strands, radius, opacity) | None, blockers=[...], boxes=[(lo, hi), ...]) with
    ``boxes`` the world AABBs of every piece (each content type's ``bounds()``)."""
    if not isinstance(scene, Scene):
        raise ValueError(f"scene: expected avsm_dr.scene.Scene, got {type(scene).__name__}")
    check_light(scene.light, "scene.light")
    out: dict[str, Any] = {
        "particles": None if scene.particles is None else scene.particles.validate(),
        "hair": None if scene.hair is None else scene.hair.validate(),
        "grid": None if scene.density is None else check_grid(scene.density, scene.bbox),
        "blockers": validate_blockers(scene.blockers or [])}
    out["boxes"] = [] if out["grid"] is None else [out["grid"][1:]]
    out["boxes"] += [b.bounds() for b in (scene.particles, scene.hair, *out["blockers"]) if b is not None]
    if not out["boxes"]:
        raise ValueError("scene: has no density grid, particles, hair or opaque blockers")
    return out


# ======================================================================= geometry
def content_sphere(content) -> tuple[np.ndarray, float]:
    """(centre, radius) of a sphere enclosing every piece of (checked) content."""
    lo = np.min([b[0] for b in content["boxes"]], axis=0)
    hi = np.max([b[1] for b in content["boxes"]], axis=0)
    return 0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo))


def light_paths(scene: Scene, points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Light-side origins o (K, 3), unit directions d (K, 3) towards the points, lengths L (K,):
    ``scene.light.paths`` (:class:`~avsm_dr.scene.Light`) with the content's bounding sphere."""
    return checked_paths(scene, points)[2:]


def checked_paths(scene: Scene, points):
    """(content of :func:`check_scene`, points (K, 3) float64, and their :func:`light_paths` o, d, L)."""
    content = check_scene(scene)
    p = V.points(points)
    return (content, p, *scene.light.paths(p, *content_sphere(content)))


def to_light(light, p):
    """(K, 3) unit directions from points ``p`` (K, 3) towards the light (a new C-contiguous
    array: NumPy's products then take the same path for every light)."""
    return np.ascontiguousarray(light.directions_to(p))


def scene_scale(content, scene, p) -> float:
    """Largest coordinate magnitude of the content, the light and the points (>= 1)."""
    c, R = content_sphere(content)
    m = max(float(np.abs(p).max()), float(np.abs(c).max()) + R)
    pos = getattr(scene.light, "position", None)
    if pos is not None:
        m = max(m, float(np.abs(pos).max()))
    return max(m, 1.0)


# ======================================================================= blockers
def blocked(scene: Scene, points) -> np.ndarray:
    """(K,) True where an opaque blocker lies between the light and the point."""
    return blocked_paths(scene, *checked_paths(scene, points))


def blocked_paths(scene, content, p, o, d, L):
    """(K,) True where a blocker meets the open path (0, L - eps) of rays o + t d towards the
    points p, eps = :data:`EPS_REL` x :func:`scene_scale`."""
    out = np.zeros(o.shape[0], bool)
    far = L - EPS_REL * scene_scale(content, scene, p)
    for b in content["blockers"]:
        out |= b.blocks(o, d, far)
    return out


# ====================================================================== particles
def _sphere_chords(o, d, c, r):
    """(b, h2) (K, P) of unit rays o, d (K, 3) and spheres c (P, 3), r: the chord is
    ``b -+ sqrt(h2)`` where ``h2 > 0`` (``b = (c - o) . d``, ``h2 = r^2 - |c - o|^2 + b^2``)."""
    oc = c[None, :, :] - o[:, None, :]                             # (K, P, 3)
    b = np.einsum("kpj,kj->kp", oc, d)
    return b, r * r - (np.einsum("kpj,kpj->kp", oc, oc) - b * b)


def particles_tau(particles, o, d, L):
    """(K,) optical depth of the particles along [0, L] (exact chords)."""
    c, r, s = particles
    K = o.shape[0]
    tau = np.zeros(K)
    chunk = max(1, MAX_CHUNK // max(K, 1))
    for a in range(0, c.shape[0], chunk):
        b, h2 = _sphere_chords(o, d, c[a:a + chunk], r[None, a:a + chunk])
        h = np.sqrt(np.maximum(h2, 0.0))
        chord = np.clip(np.minimum(b + h, L[:, None]) - np.maximum(b - h, 0.0), 0.0, None)
        tau += np.where(h2 > 0, chord, 0.0) @ s[a:a + chunk]
    return tau


# =========================================================================== hair
def _capsule_intervals(o, d, A0, A1, r):
    """Entry/exit (t0, t1) (K, C) of rays (K) with capsules A0-A1 (C) of radius r; NaN = miss.

    A capsule is convex, so the path meets it in one interval: the hull of its
    chords through the two end spheres and through the finite cylinder."""
    t0 = np.full((o.shape[0], A0.shape[0]), np.inf)
    t1 = np.full_like(t0, -np.inf)
    for c in (A0, A1):                                             # end spheres
        b, h2 = _sphere_chords(o, d, c, r)
        h = np.sqrt(np.maximum(h2, 0.0))
        t0 = np.where(h2 > 0, np.minimum(t0, b - h), t0)
        t1 = np.where(h2 > 0, np.maximum(t1, b + h), t1)
    ax = A1 - A0                                                   # cylinder
    ln = np.linalg.norm(ax, axis=1)
    a = ax / np.where(ln > 0, ln, 1.0)[:, None]
    w = o[:, None] - A0[None]                                      # (K, C, 3)
    da = d @ a.T                                                   # (K, C)
    wa = np.einsum("kcj,cj->kc", w, a)
    dp = d[:, None] - da[..., None] * a[None]
    wp = w - wa[..., None] * a[None]
    qa = np.einsum("kcj,kcj->kc", dp, dp)
    qb = np.einsum("kcj,kcj->kc", wp, dp)
    qc = np.einsum("kcj,kcj->kc", wp, wp) - r * r
    disc = qb * qb - qa * qc
    ok = (qa > 1e-12) & (disc > 0) & (ln[None] > 0)
    sq = np.sqrt(np.maximum(disc, 0.0))
    qs = np.where(ok, qa, 1.0)
    c0, c1 = (-qb - sq) / qs, (-qb + sq) / qs
    # keep the part whose axial coordinate wa + t da lies in [0, ln]
    with np.errstate(divide="ignore", invalid="ignore"):
        s0 = (0 - wa) / da
        s1 = (ln[None] - wa) / da
    par = da == 0
    lo_s = np.where(par, np.where((wa >= 0) & (wa <= ln[None]), -np.inf, np.inf), np.minimum(s0, s1))
    hi_s = np.where(par, np.where((wa >= 0) & (wa <= ln[None]), np.inf, -np.inf), np.maximum(s0, s1))
    c0, c1 = np.maximum(c0, lo_s), np.minimum(c1, hi_s)
    ok &= c0 < c1
    t0 = np.where(ok, np.minimum(t0, c0), t0)
    t1 = np.where(ok, np.maximum(t1, c1), t1)
    miss = ~(t0 < t1)
    t0[miss] = np.nan
    t1[miss] = np.nan
    return t0, t1


def hair_tau(hair, o, d, L):
    """(K,) optical depth of hair crossings along [0, L] (see the module docstring)."""
    st, r, alpha = hair
    K = o.shape[0]
    tau = np.zeros(K)
    if alpha <= 0:
        return tau
    tau_c = -math.log(1.0 - alpha) if alpha < 1 else 1e4
    S = st.shape[0]
    lo = st.min(axis=1) - r                                         # strand boxes for culling
    hi = st.max(axis=1) + r
    for s in range(S):
        tb0, tb1, _ = ray_box(o, d, lo[s], hi[s])
        cand = np.nonzero((tb0 <= tb1) & (tb1 >= 0) & (tb0 <= L))[0]
        if cand.size == 0:
            continue
        t0, t1 = _capsule_intervals(o[cand], d[cand], st[s, :-1], st[s, 1:], r)
        key = np.where(np.isnan(t0), np.inf, t0)
        order = np.argsort(key, axis=1)
        a = np.take_along_axis(t0, order, 1)
        b = np.take_along_axis(t1, order, 1)
        # merge overlapping passages: a new crossing starts where entry > max exit so far
        bm = np.fmax.accumulate(np.where(np.isnan(b), -np.inf, b), axis=1)
        prev = np.concatenate([np.full((cand.size, 1), -np.inf), bm[:, :-1]], axis=1)
        start = ~np.isnan(a) & (a > prev)
        comp = np.cumsum(start, axis=1) - 1                          # crossing id per passage
        ncomp = int(start.sum(axis=1).max()) if start.any() else 0
        for k in range(ncomp):
            m = (comp == k) & ~np.isnan(a)
            ca = np.where(m, a, np.inf).min(axis=1)
            cb = np.where(m, b, -np.inf).max(axis=1)
            Lc = L[cand]
            ca0 = np.maximum(ca, 0.0)
            length = cb - ca0
            frac = np.where(length > 0, np.clip((Lc - ca0) / np.where(length > 0, length, 1.0), 0, 1),
                            (Lc >= ca0).astype(float))
            frac = np.where(np.isfinite(ca) & (cb > 0), frac, 0.0)
            tau[cand] += tau_c * frac
    return tau

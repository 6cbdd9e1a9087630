"""Independent ground truth for scene transmittance and images, with Mitsuba 3.

The same density grid the capture marches becomes a Mitsuba ``heterogeneous``
medium whose ``sigma_t`` is a ``gridvolume`` (``mi.VolumeGrid`` of the (z, y, x)
float32 array, ``to_world`` mapping the unit cube onto ``scene.bbox``,
``filter_type='trilinear'``, ``scale = 1``).  :func:`sample_density` is the
NumPy statement of that convention (cell-centred, trilinear, clamped to the edge
inside the box, 0 outside); the test suite checks it against Mitsuba's lookups.

Transmittance from the light to a receiver ``x`` along the light path
``r(s) = o + s d``, ``0 <= s <= L`` (``o`` on the light side, ``|d| = 1``)::

    T(x) = exp(-int_0^L sigma_t(r(s)) ds)                       density grid
         * prod_p exp(-sigma_p * |chord_p cap [0, L]|)            particles
         * prod_c f_c                                              hair crossings
         * [no opaque blocker meets (0, L)]                        blockers

Grid term, ``method='ratio_tracking'`` (Novak et al. 2014, "Residual ratio
tracking"): tentative collisions ``s_i`` are drawn by Mitsuba's
``Medium.sample_interaction`` with the constant majorant ``mu = f * max(sigma_t)``
and weighted ``T_hat = prod_i (1 - sigma_t(s_i) / mu)``; ``E[T_hat] = T`` exactly
(unbiased), and the standard error is the sample standard deviation over
``spp`` independent paths divided by ``sqrt(spp)``.  Mitsuba 3.9.1 uses exactly
``max(sigma_t)`` as majorant (no safety factor), so inside uniform regions the
weights would be 0 or 1 (delta tracking, variance ``T (1 - T)``).  We trace in
the ray parameter ``u = f s`` (direction ``d / f``), which makes Mitsuba's
free-flight sampling use ``f * max`` per world unit, and weight with
``1 - sigma_t / (f * max)``; ``majorant_factor = f = 2`` by default
(variance ``T^2 (exp(tau / f) - 1)`` in a homogeneous medium).

Grid term, ``method='raymarch'``: deterministic midpoint rule in float64 with
step ``h`` (default one eighth of the smallest voxel side).  The trilinear field
is a cubic polynomial along the ray inside each lattice cell, so the error in
optical depth is at most ``L h^2 max|sigma''| / 24`` plus ``h^2 |jump sigma'| / 8``
per lattice plane crossed (O(h^2)); ``stderr`` is returned as zeros.

Paths: a point or spot light at ``P`` gives ``o = P``, ``L = |x - P|`` (the spot
cone does not limit transmittance; shading applies it).  A directional light
travelling along ``w`` gives ``o = x - L w`` with ``o`` outside every piece of
content (light side), so the path crosses the whole volume in front of ``x``.

Particles (``scene.particles``): exact analytic chords (uniform extinction in each
sphere; overlapping spheres add).  Hair (``scene.hair``): the strand model of
:mod:`avsm_dr.capture.hair` stated analytically: each strand is a chain of
capsules (radius ``r`` around each polyline segment), one *crossing* is a
maximal interval of the path inside the union of one strand's capsules, and a
crossing ``[a, b]`` absorbs ``tau_c = -ln(1 - opacity)`` spread uniformly over it
(partial when ``a < L < b``).  Cost O(receivers x capsules).
Opaque blockers: ``T = 0`` when the open path ``(0, L - eps)`` passes through the
blocker, ``eps = 1e-6 * scene scale``: a receiver lying on a blocker's lit
surface stays lit, one on the far side is dark.

The Mitsuba variant is chosen inside each call (``llvm_ad_rgb``, or
``cuda_ad_rgb`` when :func:`avsm_dr.backend.get_backend` is ``'cuda'``), never
at import time.
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from . import _arrays as A
from . import backend
from .capture.grid import check_bbox
from .capture.particles import validate as validate_particles
from .scene import (DirectionalLight, OpaqueBox, OpaquePlane, OpaqueSphere, PointLight,
                    Scene, SpotLight)

METHODS = ("ratio_tracking", "raymarch")

#: Upper bound on Dr.Jit lanes (receivers x spp) of one ratio-tracking launch.
MAX_LANES = 1 << 22
#: Upper bound on NumPy samples / pair tests per chunk (host memory).
MAX_CHUNK = 1 << 22
#: Relative surface epsilon (times the scene scale) for blocker tests.
EPS_REL = 1e-6


# =========================================================================== Mitsuba
def mitsuba():
    """The ``mitsuba`` module with this package's variant set.

    ``cuda_ad_rgb`` when the Dr.Jit backend is CUDA, else ``llvm_ad_rgb``; the
    variant is changed only when it differs (Mitsuba and Dr.Jit share the process).
    """
    import mitsuba as mi
    want = "cuda_ad_rgb" if backend.get_backend() == "cuda" else "llvm_ad_rgb"
    if mi.variant() != want:
        mi.set_variant(want)
    return mi


def _grid_to_world(mi, lo, hi):
    """ScalarTransform4f mapping the unit cube onto the box [lo, hi]."""
    return (mi.ScalarTransform4f().translate([float(v) for v in lo])
            @ mi.ScalarTransform4f().scale([float(v) for v in hi - lo]))


def mitsuba_volume(density, bbox):
    """The ``gridvolume`` for ``density`` (nz, ny, nx) over ``bbox`` (trilinear).

    Mitsuba clamps lookups to the edge even outside the box; the medium built by
    :func:`mitsuba_medium` is only ever evaluated inside it.
    """
    mi = mitsuba()
    grid, lo, hi = _check_grid(density, bbox)
    return mi.load_dict({
        "type": "gridvolume",
        "grid": mi.VolumeGrid(np.ascontiguousarray(grid[..., None], dtype=np.float32)),
        "to_world": _grid_to_world(mi, lo, hi),
        "filter_type": "trilinear",
    })


def _medium_dict(mi, grid, lo, hi, albedo: float) -> dict:
    return {
        "type": "heterogeneous",
        "sigma_t": {
            "type": "gridvolume",
            "grid": mi.VolumeGrid(np.ascontiguousarray(grid[..., None], dtype=np.float32)),
            "to_world": _grid_to_world(mi, lo, hi),
            "filter_type": "trilinear",
        },
        "albedo": float(albedo),
        "scale": 1.0,
    }


def mitsuba_medium(scene: Scene, albedo: float = 0.0):
    """Mitsuba ``heterogeneous`` medium of ``scene.density`` (sigma_t = density, scale 1)."""
    mi = mitsuba()
    grid, lo, hi = _check_grid(scene.density, scene.bbox)
    return mi.load_dict(_medium_dict(mi, grid, lo, hi, albedo))


# ===================================================================== validation
def _check_grid(density, bbox):
    """(grid float32 (nz, ny, nx), lo (3,), hi (3,)) after checks."""
    if density is None:
        raise ValueError("density: the scene has no density grid")
    g = A.host(density, "density", np.float64)
    if g.ndim != 3 or min(g.shape) < 1:
        raise ValueError(f"density: expected a (nz, ny, nx) array, got shape {g.shape}")
    A.check_finite(g, "density")
    if np.any(g < 0):
        raise ValueError("density: negative density")
    if bbox is None:
        raise ValueError("bbox: a density grid needs bbox = (min_xyz, max_xyz)")
    lo, hi = check_bbox(bbox)
    return g.astype(np.float32), lo, hi


def check_points(points, name: str = "points") -> np.ndarray:
    """(K, 3) finite float64 copy of ``points`` (K >= 1)."""
    p = A.host(points, name, np.float64)
    if p.ndim == 1 and p.size == 3:
        p = p.reshape(1, 3)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (K, 3), got {p.shape}")
    if p.shape[0] == 0:
        raise ValueError(f"{name}: no points given (empty array)")
    A.check_finite(p, name)
    return p


def _particles(scene):
    """Validated particle arrays of the scene, or None (the capture's own checks)."""
    return None if scene.particles is None else validate_particles(scene.particles)


def _hair(scene):
    if scene.hair is None:
        return None
    H = scene.hair
    st = A.host(H.strands, "hair.strands")
    if st.ndim != 3 or st.shape[2] != 3 or st.shape[1] < 2:
        raise ValueError(f"hair.strands: expected shape (S, V >= 2, 3), got {st.shape}")
    A.check_finite(st, "hair.strands")
    if not (np.isfinite(H.radius) and H.radius > 0):
        raise ValueError(f"hair.radius: must be a finite number > 0, got {H.radius!r}")
    if not (0 <= H.opacity <= 1):
        raise ValueError(f"hair.opacity: must lie in [0, 1], got {H.opacity!r}")
    return st, float(H.radius), float(H.opacity)


def _check_scene(scene) -> dict:
    """Validated host copies of the scene's content; ValueError names the field."""
    if not isinstance(scene, Scene):
        raise ValueError(f"scene: expected avsm_dr.scene.Scene, got {type(scene).__name__}")
    if not isinstance(scene.light, (DirectionalLight, SpotLight, PointLight)):
        raise ValueError(f"scene.light: expected DirectionalLight, SpotLight or PointLight, "
                         f"got {type(scene.light).__name__}")
    out: dict[str, Any] = {"grid": None, "particles": _particles(scene), "hair": _hair(scene)}
    if scene.density is not None:
        out["grid"] = _check_grid(scene.density, scene.bbox)
    blockers = scene.blockers or []
    for i, b in enumerate(blockers):
        if not isinstance(b, (OpaqueSphere, OpaqueBox, OpaquePlane)):
            raise ValueError(f"blockers[{i}]: expected OpaqueSphere, OpaqueBox or OpaquePlane, "
                             f"got {type(b).__name__}")
    out["blockers"] = list(blockers)
    if out["grid"] is None and out["particles"] is None and out["hair"] is None and not blockers:
        raise ValueError("scene: has no density grid, particles, hair or opaque blockers")
    return out


# ======================================================================= geometry
def plane_basis(normal) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, v, n): the frame orienting square planes (OpaquePlane, receiver plane).

    u = normalize(up x n), up = +y unless |n_y| >= 0.99 (then +x), v = n x u; the
    same convention as :func:`avsm_dr.capture.camera.orthonormal_basis`.
    """
    n = np.asarray(normal, np.float64).reshape(3)
    n = n / np.linalg.norm(n)
    up = np.array([0.0, 1.0, 0.0]) if abs(n[1]) < 0.99 else np.array([1.0, 0.0, 0.0])
    u = np.cross(up, n)
    u /= np.linalg.norm(u)
    return u, np.cross(n, u), n


def _content_sphere(content) -> tuple[np.ndarray, float]:
    """(centre, radius) of a sphere enclosing every piece of content."""
    lo, hi = [], []
    if content["grid"] is not None:
        lo.append(content["grid"][1]); hi.append(content["grid"][2])
    if content["particles"] is not None:
        c, r, _ = content["particles"]
        lo.append((c - r[:, None]).min(0)); hi.append((c + r[:, None]).max(0))
    if content["hair"] is not None:
        st, rad, _ = content["hair"]
        pts = st.reshape(-1, 3)
        lo.append(pts.min(0) - rad); hi.append(pts.max(0) + rad)
    for b in content["blockers"]:
        if isinstance(b, OpaqueSphere):
            c = np.asarray(b.center, np.float64); lo.append(c - b.radius); hi.append(c + b.radius)
        elif isinstance(b, OpaqueBox):
            lo.append(np.asarray(b.min, np.float64)); hi.append(np.asarray(b.max, np.float64))
        else:
            c = np.asarray(b.point, np.float64)
            e = float(b.extent) * math.sqrt(2.0)
            lo.append(c - e); hi.append(c + e)
    lo, hi = np.min(lo, axis=0), np.max(hi, axis=0)
    return 0.5 * (lo + hi), 0.5 * float(np.linalg.norm(hi - lo))


def light_paths(scene: Scene, points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Light-side origins o (K, 3), unit directions d (K, 3) towards the points, lengths L (K,).

    Point/spot: o = light position.  Directional (travelling along w): o = x - L w
    with L the distance from x back to the plane, orthogonal to w, that touches the
    light side of the content's bounding sphere (L = 0 when x is beyond it).
    """
    content = _check_scene(scene)
    return _light_paths(scene, check_points(points), content)


def _light_paths(scene, p, content):
    light = scene.light
    if isinstance(light, DirectionalLight):
        w = light.direction / np.linalg.norm(light.direction)
        c, R = _content_sphere(content)
        L = np.maximum((p - c) @ w + R, 0.0) * (1 + 1e-9) + 1e-9 * (1 + R)
        d = np.broadcast_to(w, p.shape).copy()
        o = p - L[:, None] * d
    else:
        o = np.broadcast_to(light.position, p.shape).astype(np.float64)
        v = p - o
        L = np.linalg.norm(v, axis=1)
        d = np.where(L[:, None] > 0, v / np.where(L > 0, L, 1.0)[:, None], np.array([0.0, 0.0, 1.0]))
    return o, d, L


def _scene_scale(content, scene, p) -> float:
    c, R = _content_sphere(content)
    m = max(float(np.abs(p).max()), float(np.abs(c).max()) + R)
    pos = getattr(scene.light, "position", None)
    if pos is not None:
        m = max(m, float(np.abs(pos).max()))
    return max(m, 1.0)


def ray_box(o, d, lo, hi):
    """Slab test: (t_near, t_far) of rays o + t d with the box [lo, hi]; t_near > t_far = miss."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (lo - o) * inv
        t2 = (hi - o) * inv
    tmin = np.minimum(t1, t2)
    tmax = np.maximum(t1, t2)
    par = d == 0                                    # parallel to a slab: inside it or miss
    inside = (o >= lo) & (o <= hi)
    tmin = np.where(par, np.where(inside, -np.inf, np.inf), tmin)
    tmax = np.where(par, np.where(inside, np.inf, -np.inf), tmax)
    return tmin.max(axis=1), tmax.min(axis=1)


def ray_sphere(o, d, c, r):
    """(t_near, t_far, hit) of rays (unit d) with spheres c (K or 1, 3), r (K or 1,)."""
    oc = c - o
    b = np.einsum("ij,ij->i", oc, d) if oc.ndim == 2 else oc @ d
    perp = oc - b[..., None] * d
    h2 = r * r - np.einsum("...j,...j->...", perp, perp)
    hit = h2 > 0
    s = np.sqrt(np.where(hit, h2, 0.0))
    return b - s, b + s, hit


def blocked(scene: Scene, points) -> np.ndarray:
    """(K,) True where an opaque blocker lies between the light and the point."""
    content = _check_scene(scene)
    p = check_points(points)
    o, d, L = _light_paths(scene, p, content)
    return _blocked(content["blockers"], o, d, L, EPS_REL * _scene_scale(content, scene, p))


def _blocked(blockers, o, d, L, eps):
    out = np.zeros(o.shape[0], bool)
    far = L - eps
    for b in blockers:
        if isinstance(b, OpaqueSphere):
            t0, t1, hit = ray_sphere(o, d, np.asarray(b.center, np.float64), float(b.radius))
            out |= hit & (np.maximum(t0, 0.0) < np.minimum(t1, far))
        elif isinstance(b, OpaqueBox):
            t0, t1 = ray_box(o, d, np.asarray(b.min, np.float64), np.asarray(b.max, np.float64))
            out |= (t0 <= t1) & (np.maximum(t0, 0.0) < np.minimum(t1, far))
        elif isinstance(b, OpaquePlane):
            u, v, n = plane_basis(b.normal)
            c = np.asarray(b.point, np.float64)
            den = d @ n
            ok = den != 0
            t = np.where(ok, ((c - o) @ n) / np.where(ok, den, 1.0), -1.0)
            q = o + t[:, None] * d - c
            inside = (np.abs(q @ u) <= b.extent) & (np.abs(q @ v) <= b.extent)
            out |= ok & inside & (t > 0) & (t < far)
    return out


def _particles_tau(particles, o, d, L):
    """(K,) optical depth of the particles along [0, L] (exact chords)."""
    c, r, s = particles
    K = o.shape[0]
    tau = np.zeros(K)
    chunk = max(1, MAX_CHUNK // max(K, 1))
    for a in range(0, c.shape[0], chunk):
        cc, rr, ss = c[a:a + chunk], r[a:a + chunk], s[a:a + chunk]
        oc = cc[None, :, :] - o[:, None, :]                        # (K, P, 3)
        b = np.einsum("kpj,kj->kp", oc, d)
        h2 = rr[None] ** 2 - (np.einsum("kpj,kpj->kp", oc, oc) - b * b)
        h = np.sqrt(np.maximum(h2, 0.0))
        chord = np.clip(np.minimum(b + h, L[:, None]) - np.maximum(b - h, 0.0), 0.0, None)
        tau += np.where(h2 > 0, chord, 0.0) @ ss
    return tau


def _capsule_intervals(o, d, A0, A1, r):
    """Entry/exit (t0, t1) (K, C) of rays (K) with capsules A0-A1 (C) of radius r; NaN = miss.

    A capsule is convex, so the path meets it in one interval: the hull of its
    chords through the two end spheres and through the finite cylinder.
    """
    t0 = np.full((o.shape[0], A0.shape[0]), np.inf)
    t1 = np.full_like(t0, -np.inf)
    for c in (A0, A1):                                             # end spheres
        oc = c[None] - o[:, None]
        b = np.einsum("kcj,kj->kc", oc, d)
        h2 = r * r - (np.einsum("kcj,kcj->kc", oc, oc) - b * b)
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


def _hair_tau(hair, o, d, L):
    """(K,) optical depth of hair crossings along [0, L] (see the module docstring)."""
    st, r, alpha = hair
    K = o.shape[0]
    tau = np.zeros(K)
    if alpha <= 0:
        return tau
    tau_c = -math.log(1.0 - alpha) if alpha < 1 else 1e4
    S, V, _ = st.shape
    lo = st.min(axis=1) - r                                         # strand boxes for culling
    hi = st.max(axis=1) + r
    for s in range(S):
        tb0, tb1 = ray_box(o, d, lo[s], hi[s])
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
            has = np.isfinite(ca)
            Lc = L[cand]
            ca0 = np.maximum(ca, 0.0)
            length = cb - ca0
            frac = np.where(length > 0, np.clip((Lc - ca0) / np.where(length > 0, length, 1.0), 0, 1),
                            (Lc >= ca0).astype(float))
            frac = np.where(has & (cb > 0), frac, 0.0)
            tau[cand] += tau_c * frac
    return tau


# ===================================================================== density
def sample_density(density, bbox, points) -> np.ndarray:
    """sigma_t at world ``points`` (K, 3): (K,) float64.

    Voxel (k, j, i) sits at ``lo + ((i, j, k) + 0.5) * (hi - lo) / (nx, ny, nz)``;
    trilinear in between, clamped to the edge inside the box, 0 outside it
    (the Mitsuba ``gridvolume`` convention, see :mod:`avsm_dr.scene`).
    """
    g, lo, hi = _check_grid(density, bbox)
    p = check_points(points)
    return _sample(g.astype(np.float64), lo, hi, p)


def _sample(g, lo, hi, p):
    nz, ny, nx = g.shape
    n = np.array([nx, ny, nz], np.float64)
    u = (p - lo) / (hi - lo) * n - 0.5
    inside = np.all((p >= lo) & (p <= hi), axis=1)
    u = np.clip(u, 0.0, n - 1)
    i0 = np.minimum(np.floor(u).astype(np.int64), np.maximum(n.astype(np.int64) - 2, 0))
    f = u - i0
    i1 = np.minimum(i0 + 1, n.astype(np.int64) - 1)
    out = np.zeros(p.shape[0])
    for cz in (0, 1):
        kz = i1[:, 2] if cz else i0[:, 2]
        wz = f[:, 2] if cz else 1 - f[:, 2]
        for cy in (0, 1):
            ky = i1[:, 1] if cy else i0[:, 1]
            wy = f[:, 1] if cy else 1 - f[:, 1]
            for cx in (0, 1):
                kx = i1[:, 0] if cx else i0[:, 0]
                wx = f[:, 0] if cx else 1 - f[:, 0]
                out += wz * wy * wx * g[kz, ky, kx]
    return np.where(inside, out, 0.0)


def raymarch_optical_depth(density, bbox, o, d, L, step: float | None = None) -> np.ndarray:
    """Midpoint-rule optical depth of the grid along rays o + t d, t in [0, L] (float64).

    Each ray is clipped to the box and split into ``ceil(length / step)`` equal
    pieces (<= step); default step = min voxel side / 8.  Error: see module docstring.
    """
    g, lo, hi = _check_grid(density, bbox)
    o = np.asarray(o, np.float64).reshape(-1, 3)
    d = np.asarray(d, np.float64).reshape(-1, 3)
    L = np.asarray(L, np.float64).reshape(-1)
    if step is None:
        step = float(np.min((hi - lo) / np.array(g.shape[::-1]))) / 8
    if not (np.isfinite(step) and step > 0):
        raise ValueError(f"step: must be a finite number > 0, got {step!r}")
    return _raymarch(g.astype(np.float64), lo, hi, o, d, L, step)


def _raymarch(g, lo, hi, o, d, L, step):
    t0, t1 = ray_box(o, d, lo, hi)
    t0 = np.maximum(t0, 0.0)
    t1 = np.minimum(t1, L)
    length = np.where(t1 > t0, t1 - t0, 0.0)
    n = np.ceil(length / step).astype(np.int64)
    h = np.where(n > 0, length / np.maximum(n, 1), 0.0)
    tau = np.zeros(o.shape[0])
    idx = np.nonzero(n)[0]
    start = 0
    while start < idx.size:                                        # chunks of <= MAX_CHUNK samples
        csum = np.cumsum(n[idx[start:]])
        stop = start + max(1, int(np.searchsorted(csum, MAX_CHUNK, side="right")))
        rays = idx[start:stop]
        cnt = n[rays]
        rid = np.repeat(np.arange(rays.size), cnt)
        j = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        t = t0[rays][rid] + (j + 0.5) * h[rays][rid]
        pts = o[rays][rid] + t[:, None] * d[rays][rid]
        sig = _sample(g, lo, hi, pts)
        tau[rays] = np.bincount(rid, weights=sig, minlength=rays.size) * h[rays]
        start = stop
    return tau


# ================================================================ ratio tracking
def _ratio_tracking(grid, lo, hi, o, d, L, spp: int, seed: int, f: float):
    """Per-receiver mean and standard error of the ratio-tracking estimator (float64)."""
    mi = mitsuba()
    import drjit as dr
    K = o.shape[0]
    mean = np.ones(K)
    se = np.zeros(K)
    if float(grid.max()) == 0.0:
        return mean, se
    t0, t1 = ray_box(o, d, lo, hi)
    todo = np.nonzero((t0 <= t1) & (t1 > 0) & (t0 < L) & (L > 0))[0]
    if todo.size == 0:
        return mean, se
    medium = mi.load_dict(_medium_dict(mi, grid, lo, hi, 0.0))
    Float, UInt32 = mi.Float, mi.UInt32
    chunk = max(1, MAX_LANES // spp)
    seed_a, seed_b = (UInt32(int(v)) for v in mi.sample_tea_32(seed & 0xFFFFFFFF, 0x5EED))
    for a in range(0, todo.size, chunk):
        rec = todo[a:a + chunk]
        n = rec.size * spp
        lane = dr.arange(UInt32, n)
        rid = lane // spp
        # Start where the path enters the box (float32 precision is then local to the box).
        s0 = np.maximum(t0[rec], 0.0)
        org = o[rec] + s0[:, None] * d[rec]
        rem = (np.minimum(L[rec], t1[rec]) - s0) * f                  # remaining parameter length
        g = [dr.gather(Float, Float(org[:, i].astype(np.float32)), rid) for i in range(3)]
        dv = [dr.gather(Float, Float((d[rec, i] / f).astype(np.float32)), rid) for i in range(3)]
        D = mi.Vector3f(*dv)
        maxt = dr.gather(Float, Float(rem.astype(np.float32)), rid)
        # PCG32 state and stream hashed (TEA) from (receiver index, sample index, seed),
        # as Mitsuba's independent sampler does: independent of chunking and of `todo`.
        r_id = dr.gather(UInt32, UInt32(rec.astype(np.uint32)), rid)
        s_id = lane - rid * spp
        # (seed() directly: the PCG32 constructor would add arange(n), i.e. the lane index)
        rng = mi.PCG32(n)
        rng.seed(mi.sample_tea_64(r_id, s_id ^ seed_a), mi.sample_tea_64(s_id, r_id ^ seed_b))
        Tr = dr.ones(Float, n)
        active = dr.full(mi.Bool, True, n)
        ch = UInt32(0)

        def cond(p, maxt, Tr, active, rng):
            return active

        def body(p, maxt, Tr, active, rng):
            ray = mi.Ray3f(p, D)
            ray.maxt = maxt
            mei = medium.sample_interaction(ray, rng.next_float32(), ch, active)
            hit = active & mei.is_valid()
            w = 1.0 - mei.sigma_t.x / (f * mei.combined_extinction.x)
            Tr = dr.select(hit, Tr * w, Tr)
            p = dr.select(hit, mei.p, p)
            maxt = dr.select(hit, maxt - mei.t, maxt)
            return p, maxt, Tr, hit & (Tr > 0), rng

        _, _, Tr, _, _ = dr.while_loop((mi.Point3f(*g), maxt, Tr, active, rng), cond, body,
                                       label="ratio_tracking")
        samples = np.asarray(Tr.numpy(), np.float64).reshape(rec.size, spp)
        mean[rec] = samples.mean(axis=1)
        se[rec] = samples.std(axis=1, ddof=1) / math.sqrt(spp) if spp > 1 else np.inf
    return mean, se


# ====================================================================== public
def transmittance(scene: Scene, points, spp: int = 256, seed: int = 0, method: str = "ratio_tracking",
                  step: float | None = None, majorant_factor: float = 2.0):
    """Transmittance from ``scene.light`` to each point: ``(mean, stderr)``, (K,) float64 NumPy.

    points: (K, 3) world positions.  spp: independent ratio-tracking paths per point
    (>= 1; ``stderr`` is inf for spp = 1).  seed: RNG seed (results are independent
    of batching).  method: 'ratio_tracking' (Mitsuba, unbiased) or 'raymarch'
    (deterministic float64 midpoint rule with ``step``; stderr = 0).
    majorant_factor: f >= 1, the tracking majorant is f * max(density).
    Particles, hair and blockers are analytic factors (see the module docstring).
    """
    content = _check_scene(scene)
    p = check_points(points)
    if method not in METHODS:
        raise ValueError(f"method: expected one of {METHODS}, got {method!r}")
    if isinstance(spp, bool) or not isinstance(spp, (int, np.integer)) or spp < 1:
        raise ValueError(f"spp: expected an integer >= 1, got {spp!r}")
    if not (np.isfinite(majorant_factor) and majorant_factor >= 1):
        raise ValueError(f"majorant_factor: must be a finite number >= 1, got {majorant_factor!r}")
    if step is not None and not (np.isfinite(step) and step > 0):
        raise ValueError(f"step: must be a finite number > 0, got {step!r}")
    o, d, L = _light_paths(scene, p, content)
    K = p.shape[0]
    mean, se = np.ones(K), np.zeros(K)
    if content["grid"] is not None:
        grid, lo, hi = content["grid"]
        if method == "raymarch":
            if step is None:
                step = float(np.min((hi - lo) / np.array(grid.shape[::-1]))) / 8
            mean = np.exp(-_raymarch(grid.astype(np.float64), lo, hi, o, d, L, step))
        else:
            mean, se = _ratio_tracking(grid, lo, hi, o, d, L, int(spp), int(seed), float(majorant_factor))
    tau = np.zeros(K)
    if content["particles"] is not None:
        tau += _particles_tau(content["particles"], o, d, L)
    if content["hair"] is not None:
        tau += _hair_tau(content["hair"], o, d, L)
    factor = np.exp(-tau)
    if content["blockers"]:
        eps = EPS_REL * _scene_scale(content, scene, p)
        factor = np.where(_blocked(content["blockers"], o, d, L, eps), 0.0, factor)
    return mean * factor, se * factor


# ============================================================= reference images
def default_camera(scene: Scene, fov: float = 40.0, distance: float | None = None,
                   direction=None) -> dict:
    """A camera looking at the receiver plane's centre from the light's side of the plane.

    The view direction v (from the plane centre to the camera) is ``direction`` if given;
    otherwise the candidate, among v0 = normalize(2 n + l) (n: the plane normal turned
    towards the light, l: unit direction to the light) and 32 directions tilted 25..60
    degrees from n, whose view of the plane is least hidden by the smoke: the smallest
    mean opacity 1 - exp(-tau) along 25 view rays to the plane (ray-marched), plus
    0.05 per radian away from v0 (prefer frontal views).  The distance frames the square
    with a 15 % margin (``distance`` overrides); a camera inside the volume's box is
    moved out along v with the fov narrowed to keep the framing.
    Returns dict(origin, target, up, fov) (fov in degrees along x).
    """
    c, n, half = _receiver_plane(scene)
    l = _to_light(scene.light, c[None])[0]
    if n @ l < 0:
        n = -n
    u, w, _ = plane_basis(n)
    grid = None
    if scene.density is not None and scene.bbox is not None:
        grid = _check_grid(scene.density, scene.bbox)

    def place(v):
        dist = distance
        f = float(fov)
        if dist is None:
            dist = 1.15 * half / math.tan(math.radians(f) / 2) + half * abs(v @ n - 1)
            if grid is not None:
                t0, t1 = ray_box(c[None], v[None], grid[1], grid[2])
                if t0[0] <= t1[0] and t0[0] <= dist <= t1[0]:
                    dist = float(t1[0]) + 0.1 * half
                    f = min(f, 2 * math.degrees(math.atan(1.15 * half / dist)))
        return c + dist * v, f

    v0 = 2 * n + l
    v0 /= np.linalg.norm(v0)
    if direction is not None:
        cands = [np.asarray(direction, np.float64).reshape(3) / np.linalg.norm(direction)]
    elif grid is None:
        cands = [v0]
    else:
        cands = [v0] + [math.cos(a) * n + math.sin(a) * (math.cos(p) * u + math.sin(p) * w)
                        for a in np.radians([25.0, 40.0, 50.0, 60.0])
                        for p in np.radians(np.arange(0.0, 360.0, 45.0))]
    best = None
    if len(cands) > 1:
        g, lo, hi = grid
        a, b = np.meshgrid(np.linspace(-0.8, 0.8, 5), np.linspace(-0.8, 0.8, 5))
        targets = c + half * (a.reshape(-1, 1) * u + b.reshape(-1, 1) * w)
        step = float(np.min((hi - lo) / np.array(g.shape[::-1]))) / 2
        for v in cands:
            origin, f = place(v)
            dv = targets - origin
            L = np.linalg.norm(dv, axis=1)
            tau = _raymarch(g.astype(np.float64), lo, hi, np.broadcast_to(origin, dv.shape),
                            dv / L[:, None], L, step)
            score = float(np.mean(1 - np.exp(-tau))) + 0.05 * math.acos(np.clip(v @ v0, -1, 1))
            if best is None or score < best[0] - 1e-12:
                best = (score, v)
        v = best[1]
    else:
        v = cands[0]
    origin, f = place(v)
    up = w if abs(w @ v) < 0.9 else u
    return {"origin": origin, "target": c, "up": up, "fov": float(f)}


def _receiver_plane(scene):
    if scene.receiver_plane is None:
        raise ValueError("scene: has no receiver_plane = (point, normal, half_size)")
    try:
        c, n, half = scene.receiver_plane
        c = np.asarray(c, np.float64).reshape(3)
        n = np.asarray(n, np.float64).reshape(3)
        half = float(half)
    except (TypeError, ValueError):
        raise ValueError(f"scene.receiver_plane: expected (point, normal, half_size), "
                         f"got {scene.receiver_plane!r}") from None
    if not (np.all(np.isfinite(c)) and np.all(np.isfinite(n)) and np.linalg.norm(n) > 0):
        raise ValueError("scene.receiver_plane: point and normal must be finite, normal non-zero")
    if not (np.isfinite(half) and half > 0):
        raise ValueError(f"scene.receiver_plane: half_size must be > 0, got {half}")
    return c, n / np.linalg.norm(n), half


#: Offset of the receiver plane towards the camera (times max(1, half size)) in both
#: renderers, so that a plane lying on a blocker's face (a table top) is seen, not the face.
PLANE_OFFSET = 1e-5


def receiver_plane_for(scene: Scene, camera: dict) -> tuple[np.ndarray, np.ndarray, float]:
    """(centre, normal facing the camera, half size) of the receiver plane as both renderers
    draw it: moved ``PLANE_OFFSET * max(1, half)`` towards the camera."""
    c, n, half = _receiver_plane(scene)
    if (camera["origin"] - c) @ n < 0:
        n = -n
    return c + PLANE_OFFSET * max(1.0, half) * n, n, half


def _to_light(light, p):
    """(K, 3) unit directions from points towards the light."""
    if isinstance(light, DirectionalLight):
        return np.broadcast_to(-light.direction, p.shape).copy()
    v = light.position - p
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300)


def check_camera(scene, camera) -> dict:
    """Validated camera dict (origin, target, up, fov); the default view when ``camera`` is None."""
    cam = default_camera(scene) if camera is None else dict(camera)
    for key in ("origin", "target", "up"):
        if key not in cam:
            raise ValueError(f"camera: missing {key!r} (expected origin, target, up, fov)")
        cam[key] = np.asarray(cam[key], np.float64).reshape(3)
        if not np.all(np.isfinite(cam[key])):
            raise ValueError(f"camera: {key} must be finite")
    cam["fov"] = float(cam.get("fov", 40.0))
    if not (0 < cam["fov"] < 180):
        raise ValueError(f"camera: fov must lie in (0, 180), got {cam['fov']}")
    fwd = cam["target"] - cam["origin"]
    if np.linalg.norm(fwd) == 0 or np.linalg.norm(np.cross(fwd, cam["up"])) == 0:
        raise ValueError("camera: origin == target or up parallel to the view direction")
    if scene.density is not None and scene.bbox is not None:
        lo, hi = np.asarray(scene.bbox[0], float), np.asarray(scene.bbox[1], float)
        if np.all(cam["origin"] >= lo) and np.all(cam["origin"] <= hi):
            raise ValueError("camera: origin lies inside the volume's box (unsupported)")
    return cam


def _sensor_dict(mi, cam, width, height, spp):
    return {
        "type": "perspective",
        "fov": cam["fov"],
        "fov_axis": "x",
        "to_world": mi.ScalarTransform4f().look_at(origin=cam["origin"].tolist(),
                                                   target=cam["target"].tolist(),
                                                   up=cam["up"].tolist()),
        "film": {"type": "hdrfilm", "width": int(width), "height": int(height),
                 "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        "sampler": {"type": "independent", "sample_count": int(spp)},
    }


def camera_rays(scene: Scene, width: int, height: int, camera=None, supersample: int = 1):
    """Origins and unit directions (H*W*s*s, 3) of the camera rays (Mitsuba's own sensor),
    ``s x s`` stratified positions per pixel, ordered (row, column, sub-row, sub-column)."""
    mi = mitsuba()
    _check_size(width, height)
    cam = check_camera(scene, camera)
    sensor = mi.load_dict(_sensor_dict(mi, cam, width, height, 1))
    s = int(supersample)
    if s < 1:
        raise ValueError(f"supersample: expected an integer >= 1, got {supersample!r}")
    y, x, sy, sx = np.meshgrid(np.arange(height), np.arange(width), np.arange(s), np.arange(s),
                               indexing="ij")
    u = ((x + (sx + 0.5) / s) / width).ravel()
    v = ((y + (sy + 0.5) / s) / height).ravel()
    ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(mi.Float(u.astype(np.float32)), mi.Float(v.astype(np.float32))),
                               mi.Point2f(0.5, 0.5))
    o = np.stack([np.asarray(ray.o[i].numpy(), np.float64) for i in range(3)], axis=1)
    d = np.stack([np.asarray(ray.d[i].numpy(), np.float64) for i in range(3)], axis=1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o, d


def _check_size(width, height):
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise ValueError(f"{name}: expected an integer >= 1, got {v!r}")


def _emitter_dict(mi, light):
    if isinstance(light, DirectionalLight):
        return {"type": "directional", "direction": light.direction.tolist(),
                "irradiance": {"type": "rgb", "value": [float(light.irradiance)] * 3}}
    if isinstance(light, SpotLight):
        pos = light.position
        up = plane_basis(light.direction)[1]
        return {"type": "spot", "cutoff_angle": light.fov / 2, "beam_width": spot_beam_width(light),
                "intensity": {"type": "rgb", "value": [float(light.intensity)] * 3},
                "to_world": mi.ScalarTransform4f().look_at(origin=pos.tolist(),
                                                           target=(pos + light.direction).tolist(),
                                                           up=up.tolist())}
    return {"type": "point", "position": light.position.tolist(),
            "intensity": {"type": "rgb", "value": [float(light.intensity)] * 3}}


def spot_beam_width(light: SpotLight) -> float:
    """Full-intensity half angle (degrees) of a spot: 3/4 of the cutoff fov / 2 (Mitsuba's default)."""
    return 0.75 * light.fov / 2


def _rect_to_world(mi, c, n, half):
    u, v, n = plane_basis(n)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = u * half, v * half, n, c
    return mi.ScalarTransform4f(m)


def render_reference(scene: Scene, width: int = 128, height: int = 128, spp: int = 64,
                     camera: dict | None = None, albedo: float = 0.0, reflectance: float = 1.0,
                     max_depth: int = 2, seed: int = 0) -> np.ndarray:
    """Mitsuba ``volpath`` image (height, width) float64 of the volume and the receiver plane.

    Receiver plane: a two-sided diffuse square (``reflectance``) of ``scene.receiver_plane``
    oriented by :func:`plane_basis`; volume: the heterogeneous medium of ``scene.density``
    with single-scattering ``albedo`` (0 = purely absorbing) inside a null-BSDF cube on
    ``scene.bbox``; blockers: black (reflectance 0) spheres, cubes and rectangles, so they
    cast shadows but reflect nothing.  Light: 'directional' / 'spot' / 'point' with the
    scene light's irradiance / intensity.  Camera: :func:`default_camera` unless given
    (dict origin, target, up, fov).  Box pixel filter; ``max_depth = 2`` is direct
    lighting (single scattering in the medium when albedo > 0).  Returns the red channel
    (all channels are equal: everything is grey).  Particles and hair are not rendered
    (ValueError).
    """
    mi = mitsuba()
    content = _check_scene(scene)
    _check_size(width, height)
    if isinstance(spp, bool) or not isinstance(spp, (int, np.integer)) or spp < 1:
        raise ValueError(f"spp: expected an integer >= 1, got {spp!r}")
    if content["particles"] is not None or content["hair"] is not None:
        raise ValueError("scene: render_reference renders density grids and opaque blockers only "
                         "(particles / hair have no Mitsuba counterpart here)")
    if not (0 <= albedo <= 1):
        raise ValueError(f"albedo: must lie in [0, 1], got {albedo!r}")
    cam = check_camera(scene, camera)
    c, n, half = receiver_plane_for(scene, cam)
    black = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}}
    d: dict[str, Any] = {
        "type": "scene",
        "integrator": {"type": "volpath", "max_depth": int(max_depth)},
        "sensor": _sensor_dict(mi, cam, width, height, spp),
        "light": _emitter_dict(mi, scene.light),
        "plane": {"type": "rectangle", "to_world": _rect_to_world(mi, c, n, half),
                  "bsdf": {"type": "twosided", "bsdf": {
                      "type": "diffuse", "reflectance": {"type": "rgb", "value": [float(reflectance)] * 3}}}},
    }
    if content["grid"] is not None:
        grid, lo, hi = content["grid"]
        d["volume"] = {
            "type": "cube",
            "to_world": (mi.ScalarTransform4f().translate(((lo + hi) / 2).tolist())
                         @ mi.ScalarTransform4f().scale(((hi - lo) / 2).tolist())),
            "bsdf": {"type": "null"},
            "interior": _medium_dict(mi, grid, lo, hi, albedo),
        }
    for i, b in enumerate(content["blockers"]):
        if isinstance(b, OpaqueSphere):
            d[f"blocker{i}"] = {"type": "sphere", "center": np.asarray(b.center, float).tolist(),
                                "radius": float(b.radius), "bsdf": black}
        elif isinstance(b, OpaqueBox):
            lo_b, hi_b = np.asarray(b.min, float), np.asarray(b.max, float)
            d[f"blocker{i}"] = {"type": "cube", "bsdf": black, "to_world": (
                mi.ScalarTransform4f().translate(((lo_b + hi_b) / 2).tolist())
                @ mi.ScalarTransform4f().scale(((hi_b - lo_b) / 2).tolist()))}
        else:
            d[f"blocker{i}"] = {"type": "rectangle", "bsdf": {"type": "twosided", "bsdf": black},
                                "to_world": _rect_to_world(mi, np.asarray(b.point, float), b.normal,
                                                           float(b.extent))}
    img = mi.render(mi.load_dict(d), spp=int(spp), seed=int(seed))
    return np.asarray(img, np.float64)[..., 0]

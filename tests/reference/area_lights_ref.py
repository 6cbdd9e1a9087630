"""Slow, obvious float64 NumPy references for avsm_dr.area_lights (never imported by the package).

Scenes are read from the package's dataclasses (plain data); every computation here is
written independently: pixel rays, ray/primitive intersection, VPL placement, the
Riemann sum, the per-VPL light grid voxelization, the scan and the boundary mask.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import integrate


# ----------------------------------------------------------------------------- camera
def camera_rays(cam) -> np.ndarray:
    """(H*W, 3) unit directions through pixel centres, row-major from the top row."""
    f = cam.target - cam.origin
    f = f / np.linalg.norm(f)
    r = np.cross(f, cam.up)
    r = r / np.linalg.norm(r)
    u = np.cross(r, f)
    tx = math.tan(math.radians(cam.fov) / 2)
    ty = tx * cam.height / cam.width
    out = np.empty((cam.height, cam.width, 3))
    for j in range(cam.height):
        for i in range(cam.width):
            x = (2 * (i + 0.5) / cam.width - 1) * tx
            y = (1 - 2 * (j + 0.5) / cam.height) * ty
            v = f + x * r + y * u
            out[j, i] = v / np.linalg.norm(v)
    return out.reshape(-1, 3)


def vpl_positions(light, K: int) -> np.ndarray:
    """Cell centres of a sqrt(K) x sqrt(K) grid on the quad (K must be a square)."""
    m = int(round(math.sqrt(K)))
    assert m * m == K
    pts = []
    for a in range(m):
        for b in range(m):
            pts.append(light.center + ((a + 0.5) / m - 0.5) * light.edge_u + ((b + 0.5) / m - 0.5) * light.edge_v)
    return np.array(pts)


# ----------------------------------------------------------------------- intersection
def hit_sphere(o, d, c, r):
    """Per ray: (t0, t1) or (inf, -inf) when missed; d unit."""
    oc = o - c
    b = np.sum(oc * d, -1)
    disc = b * b - (np.sum(oc * oc, -1) - r * r)
    sq = np.sqrt(np.maximum(disc, 0))
    miss = disc <= 0
    return np.where(miss, np.inf, -b - sq), np.where(miss, -np.inf, -b + sq)


def hit_box(o, d, lo, hi):
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (lo - o) / d
        b = (hi - o) / d
    t0 = np.max(np.minimum(a, b), -1)
    t1 = np.min(np.maximum(a, b), -1)
    miss = ~(t1 > t0)
    return np.where(miss, np.inf, t0), np.where(miss, -np.inf, t1)


def hit_occluder(o, d, occ):
    if hasattr(occ, "radius"):
        return hit_sphere(o, d, occ.center, occ.radius)
    return hit_box(o, d, occ.min, occ.max)


def closest_hit(scene, o, d):
    """(t_end, kind, normal, albedo) with kind 0 exit, 1 diffuse, 2 light front, 3 light back."""
    n = d.shape[0]
    lo, hi = scene.bounds
    _, t_end = hit_box(np.broadcast_to(o, d.shape), d, lo, hi)
    kind = np.zeros(n, int)
    nrm = np.tile([0.0, 1.0, 0.0], (n, 1))
    alb = np.zeros(n)
    with np.errstate(divide="ignore"):
        tf = np.where(d[:, 1] < 0, (lo[1] - o[1]) / d[:, 1], np.inf)
    m = tf <= t_end + 1e-9
    t_end, kind, alb = np.where(m, tf, t_end), np.where(m, 1, kind), np.where(m, scene.floor_albedo, alb)
    for occ in scene.occluders:
        t0, _ = hit_occluder(o, d, occ)
        m = (t0 > 0) & (t0 < t_end)
        x = o + t0[:, None] * d
        if hasattr(occ, "radius"):
            nn = (x - occ.center) / occ.radius
        else:
            c, h = (occ.min + occ.max) / 2, (occ.max - occ.min) / 2
            q = (x - c) / h
            ax = np.argmax(np.abs(q), 1)
            nn = np.zeros_like(q)
            nn[np.arange(n), ax] = np.sign(q[np.arange(n), ax])
        t_end = np.where(m, t0, t_end)
        kind = np.where(m, 1, kind)
        alb = np.where(m, occ.albedo, alb)
        nrm = np.where(m[:, None], nn, nrm)
    L = scene.light
    ln = L.normal
    den = d @ ln
    with np.errstate(divide="ignore", invalid="ignore"):
        tl = ((L.center - o) @ ln) / den
    x = o + tl[:, None] * d - L.center
    A = np.stack([L.edge_u, L.edge_v], 1)
    ab = np.linalg.lstsq(A, x.T, rcond=None)[0].T
    m = (den != 0) & (tl > 0) & (tl < t_end) & np.all(np.abs(ab) <= 0.5, 1)
    t_end = np.where(m, tl, t_end)
    kind = np.where(m, np.where(den < 0, 2, 3), kind)
    return t_end, kind, nrm, alb


def occluded(scene, x, p, eps):
    v = p - x
    r = np.linalg.norm(v, axis=-1)
    d = v / r[:, None]
    out = np.zeros(len(x), bool)
    for occ in scene.occluders:
        t0, t1 = hit_occluder(x, d, occ)
        out |= (t1 > eps) & (t0 < r - eps) & (t1 > t0)
    return out


# ----------------------------------------------------------------------------- render
def phase(cos, g):
    return (1 - g * g) / (4 * math.pi * (1 + g * g - 2 * g * cos) ** 1.5)


def render_exact(scene, K: int, steps: int, eps: float) -> np.ndarray:
    """Naive full-resolution single scattering: K VPLs, midpoint Riemann sum, exact
    shadow rays (offset eps along the normal at surfaces)."""
    cam, med, L = scene.camera, scene.medium, scene.light
    d = camera_rays(cam)
    o = cam.origin
    t_end, kind, nrm, alb = closest_hit(scene, o, d)
    P = vpl_positions(L, K)
    I = L.radiance * L.area / K
    n = L.normal
    img = np.where(kind == 2, L.radiance * np.exp(-med.sigma_t * t_end), 0.0)
    dt = t_end / steps
    for p in P:
        for j in range(steps):
            t = (j + 0.5) * dt
            x = o + t[:, None] * d
            v = x - p
            r = np.linalg.norm(v, axis=1)
            w = v / r[:, None]
            f = med.sigma_s * phase(-np.sum(w * d, 1), med.g) * I * np.maximum(w @ n, 0) / r ** 2 \
                * np.exp(-med.sigma_t * (t + r))
            vis = ~occluded(scene, x, p, eps)
            img += vis * f * dt
        xs = o + t_end[:, None] * d
        v = xs - p
        r = np.linalg.norm(v, axis=1)
        w = v / r[:, None]
        cs = np.maximum(-np.sum(nrm * w, 1), 0)
        lit = (kind == 1) & (cs > 0) & (w @ n > 0)
        vis = ~occluded(scene, xs + eps * nrm, p, eps)
        img += np.where(lit & vis, alb / math.pi * I * np.maximum(w @ n, 0) * cs / r ** 2
                        * np.exp(-med.sigma_t * (t_end + r)), 0)
    return img.reshape(cam.height, cam.width)


def point_light_quadrature(scene) -> np.ndarray:
    """K = 1, no occluders: the VPL at the quad centre with intensity L_e A max(0, n.w);
    the airlight integral by adaptive quadrature (scipy.integrate.quad, epsrel 1e-10)
    plus the exact floor term."""
    cam, med, L = scene.camera, scene.medium, scene.light
    assert not scene.occluders
    d = camera_rays(cam)
    o = cam.origin
    t_end, kind, nrm, alb = closest_hit(scene, o, d)
    p, n, I = L.center, L.normal, L.radiance * L.area
    out = np.zeros(len(d))
    for i in range(len(d)):
        def f(t):
            x = o + t * d[i]
            v = x - p
            r = np.linalg.norm(v)
            w = v / r
            return med.sigma_s * phase(-w @ d[i], med.g) * I * max(w @ n, 0) / r ** 2 * math.exp(-med.sigma_t * (t + r))
        val, _ = integrate.quad(f, 0, t_end[i], epsabs=0, epsrel=1e-10, limit=200)
        out[i] = val
        if kind[i] == 1:
            v = o + t_end[i] * d[i] - p
            r = np.linalg.norm(v)
            w = v / r
            cs = max(-nrm[i] @ w, 0)
            out[i] += alb[i] / math.pi * I * max(w @ n, 0) * cs / r ** 2 * math.exp(-med.sigma_t * (t_end[i] + r))
        elif kind[i] == 2:
            out[i] += L.radiance * math.exp(-med.sigma_t * t_end[i])
    return out.reshape(cam.height, cam.width)


# ------------------------------------------------------------------------ light grid
def scan_exclusive(occ: np.ndarray) -> np.ndarray:
    """S[..., b] = any(occ[..., :b]) along the last axis."""
    c = np.cumsum(occ, axis=-1) > 0
    out = np.zeros_like(occ, dtype=bool)
    out[..., 1:] = c[..., :-1]
    return out


def boundary_mask(S: np.ndarray) -> np.ndarray:
    """S: (K, R_t, R_s, B) bool; True where the 3x3 texel neighbourhood (outside = False)
    at the same bin is not constant."""
    K, Rt, Rs, B = S.shape
    pad = np.zeros((K, Rt + 2, Rs + 2, B), bool)
    pad[:, 1:-1, 1:-1] = S
    any_ = np.zeros_like(S)
    all_ = np.ones_like(S)
    for dy in range(3):
        for dx in range(3):
            nb = pad[:, dy:dy + Rt, dx:dx + Rs]
            any_ |= nb
            all_ &= nb
    return any_ & ~all_


def voxelize_rays(scene, P: np.ndarray, grid) -> np.ndarray:
    """(K, R, R, R) occupancy: entry bin of each occluder along each texel-centre ray."""
    R = grid.R
    eu, ev, n = scene.light.frame()
    occ = np.zeros((len(P), R, R, R), bool)
    dr_bin = (grid.r_far - grid.r_near) / (R - 1)
    for k, p in enumerate(P):
        for j in range(R):
            for i in range(R):
                s = grid.s_min + (i + 0.5) * (grid.s_max - grid.s_min) / R
                t = grid.t_min + (j + 0.5) * (grid.t_max - grid.t_min) / R
                dvec = s * eu + t * ev + n
                dvec /= np.linalg.norm(dvec)
                for o in scene.occluders:
                    t0, _ = hit_occluder(p[None], dvec[None], o)
                    if np.isfinite(t0[0]) and t0[0] > 0:
                        b = int(min(max((t0[0] - grid.r_near) / dr_bin, 0), R - 2))
                        occ[k, j, i, b] = True
    return occ


def unpack_bits(words: np.ndarray, n_rays: int, R: int) -> np.ndarray:
    """(n_rays * W,) uint32 words -> (n_rays, R) bool, bit b & 31 of word b >> 5."""
    W = (R + 31) // 32
    w = words.astype(np.uint64).reshape(n_rays, W)
    b = np.arange(R)
    return ((w[:, b // 32] >> (b % 32).astype(np.uint64)) & np.uint64(1)).astype(bool)


def pack_bits(bits: np.ndarray) -> np.ndarray:
    """(n_rays, R) bool -> (n_rays * W,) uint32."""
    n, R = bits.shape
    W = (R + 31) // 32
    out = np.zeros((n, W), np.uint64)
    for b in range(R):
        out[:, b // 32] |= bits[:, b].astype(np.uint64) << np.uint64(b % 32)
    return out.astype(np.uint32).ravel()

"""Slow float64 NumPy references for capture (never imported by the package).

* ``sigma_ref``: trilinear density of a cell-centred (z, y, x) grid, clamped to the
  edge inside the box, 0 outside (Mitsuba ``gridvolume`` convention).
* ``optical_depth_ref``: integral of sigma along a ray from ``t_a`` to each depth, by
  the composite midpoint rule with ``n`` sub-steps per unit length.
* ``chord_ref``: ray-sphere chord by solving the quadratic directly.
"""
from __future__ import annotations

import numpy as np


def sigma_ref(density, bbox, points):
    """sigma at points (K, 3), float64."""
    d = np.asarray(density, np.float64)
    nz, ny, nx = d.shape
    lo, hi = (np.asarray(b, np.float64) for b in bbox)
    p = np.asarray(points, np.float64)
    out = np.zeros(p.shape[0])
    n = np.array([nx, ny, nz], np.float64)
    for k in range(p.shape[0]):
        q = p[k]
        if np.any(q < lo) or np.any(q > hi):
            continue
        u = (q - lo) / (hi - lo) * n - 0.5          # continuous voxel index (x, y, z)
        base = np.floor(u)
        f = u - base
        val = 0.0
        for corner in range(8):
            off = np.array([(corner >> a) & 1 for a in range(3)])
            idx = np.clip(base.astype(int) + off, 0, n.astype(int) - 1)
            w = np.prod(np.where(off == 1, f, 1 - f))
            val += w * d[idx[2], idx[1], idx[0]]
        out[k] = val
    return out


def optical_depth_ref(density, bbox, origin, direction, t_a, depths, per_unit=4000):
    """Optical depth from t_a to each of ``depths`` along origin + t * direction (|direction| = 1).

    The midpoint grid spans only the ray's part inside the box, so the jump of sigma
    at the box faces (edge value inside, 0 outside) costs no accuracy.
    """
    depths = np.atleast_1d(np.asarray(depths, np.float64))
    o = np.asarray(origin, np.float64)
    d = np.asarray(direction, np.float64)
    lo, hi = (np.asarray(b, np.float64) for b in bbox)
    t_in, t_out = -np.inf, np.inf
    for a in range(3):                                  # slab test, one axis at a time
        if d[a] == 0:
            if not lo[a] <= o[a] <= hi[a]:
                return np.zeros_like(depths)
            continue
        ta, tb = sorted(((lo[a] - o[a]) / d[a], (hi[a] - o[a]) / d[a]))
        t_in, t_out = max(t_in, ta), min(t_out, tb)
    t_in = max(t_in, t_a)
    t_b = min(depths.max(), t_out)
    if t_b <= t_in:
        return np.zeros_like(depths)
    n = max(int(np.ceil((t_b - t_in) * per_unit)), 1)
    edges = np.linspace(t_in, t_b, n + 1)
    mids = 0.5 * (edges[:-1] + edges[1:])
    s = _sigma_vec(density, bbox, o + mids[:, None] * d) * np.diff(edges)
    cum = np.concatenate([[0.0], np.cumsum(s)])
    return np.interp(depths, edges, cum, left=0.0, right=cum[-1])


def _sigma_vec(density, bbox, points):
    """Vectorised twin of sigma_ref (checked against it in the tests)."""
    d = np.asarray(density, np.float64)
    nz, ny, nx = d.shape
    lo, hi = (np.asarray(b, np.float64) for b in bbox)
    n = np.array([nx, ny, nz], np.float64)
    p = np.asarray(points, np.float64)
    inside = np.all((p >= lo) & (p <= hi), axis=1)
    u = (p - lo) / (hi - lo) * n - 0.5
    base = np.floor(u).astype(int)
    f = u - base
    val = np.zeros(p.shape[0])
    for corner in range(8):
        off = np.array([(corner >> a) & 1 for a in range(3)])
        idx = np.clip(base + off, 0, n.astype(int) - 1)
        w = np.prod(np.where(off == 1, f, 1 - f), axis=1)
        val += w * d[idx[:, 2], idx[:, 1], idx[:, 0]]
    return np.where(inside, val, 0.0)


def chord_ref(o, d, c, r):
    """(t0, t1) of the line o + t d (|d| = 1) through the sphere (c, r), or None."""
    oc = np.asarray(o, np.float64) - np.asarray(c, np.float64)
    b = 2 * np.dot(oc, d)
    cc = np.dot(oc, oc) - r * r
    disc = b * b - 4 * cc
    if disc <= 0:
        return None
    s = np.sqrt(disc)
    return (-b - s) / 2, (-b + s) / 2

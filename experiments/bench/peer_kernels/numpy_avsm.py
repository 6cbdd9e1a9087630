"""AVSM and exact lookup vectorised over texels with NumPy: the baseline a careful
researcher would write without a JIT.  Same algorithm and conventions as
:mod:`avsm_dr.representations.avsm` (one NumPy row per texel, one Python-level step per
segment slot), so it doubles as an independent float64 check of the kernel.
"""
from __future__ import annotations

import numpy as np


def _curve(D, V, x):
    """Right-continuous linear interpolation of each row's node list at x (L,)."""
    L, N = D.shape
    val = np.ones(L)
    for k in range(N):
        if k + 1 < N:
            dd = D[:, k + 1] - D[:, k]
            safe = np.where(dd > 0, dd, 1.0)
            inner = V[:, k] + (x - D[:, k]) * (V[:, k + 1] - V[:, k]) / safe
            v = np.where(D[:, k + 1] > x, inner, V[:, k])
        else:
            v = V[:, k]
        val = np.where(D[:, k] <= x, v, val)
    return val


def _remove_smallest(D, V):
    d0, d1, d2 = D[:, :-2], D[:, 1:-1], D[:, 2:]
    t0, t1, t2 = V[:, :-2], V[:, 1:-1], V[:, 2:]
    m = np.abs((d2 - d0) * (t2 - t1) - (d2 - d1) * (t2 - t0))
    # ties: the deepest interior node
    idx = m.shape[1] - 1 - np.argmin(m[:, ::-1], axis=1) + 1
    keep = np.arange(D.shape[1])[None, :] != idx[:, None]
    L = D.shape[0]
    return D[keep].reshape(L, -1), V[keep].reshape(L, -1)


def build(offsets, z0, z1, tau, nodes: int, far: float):
    """(T, N) node depths and values; float64; unsorted insertion in the given order."""
    offsets = np.asarray(offsets, np.int64)
    counts = np.diff(offsets)
    T, N = counts.size, int(nodes)
    D = np.full((T, N), float(far))
    V = np.ones((T, N))
    used = np.zeros(T, np.int64)
    z0, z1, ts_all = np.asarray(z0, float), np.asarray(z1, float), np.exp(-np.asarray(tau, float))
    for step in range(int(counts.max()) if T else 0):
        lanes = np.nonzero(counts > step)[0]
        s = offsets[lanes] + step
        a, b, ts = z0[s], z1[s], ts_all[s]
        d, v, u = D[lanes], V[lanes], used[lanes]
        ta = _curve(d, v, a)
        tb = _curve(d, v, b) * ts
        real = np.arange(N)[None, :] < u[:, None]
        length = b - a
        safe = np.where(length > 0, length, 1.0)
        ramp = 1 + (ts - 1)[:, None] * ((d - a[:, None]) * (1.0 / safe)[:, None])
        inner = np.where(d > a[:, None], np.where(d >= b[:, None], ts[:, None], ramp), 1.0)
        factor = np.where(real, inner, ts[:, None])
        sv = v * factor
        e = np.sum(real & (d <= a[:, None]), axis=1)
        x = np.sum(real & (d <= b[:, None]), axis=1) + 1
        j = np.arange(N + 2)[None, :]
        shift = (e[:, None] < j).astype(np.int64) + (x[:, None] < j)
        src = np.clip(j - shift, 0, N - 1)
        nd = np.take_along_axis(d, src, axis=1)
        nv = np.take_along_axis(sv, src, axis=1)
        nd = np.where(x[:, None] == j, b[:, None], nd)
        nv = np.where(x[:, None] == j, tb[:, None], nv)
        nd = np.where(e[:, None] == j, a[:, None], nd)
        nv = np.where(e[:, None] == j, ta[:, None], nv)
        room = u + 2 <= N
        out_d, out_v = nd[:, :N].copy(), nv[:, :N].copy()
        full = np.nonzero(~room)[0]
        if full.size:
            cd, cv = _remove_smallest(nd[full], nv[full])
            cd, cv = _remove_smallest(cd, cv)
            out_d[full], out_v[full] = cd, cv
        skip = ta == 0
        D[lanes] = np.where(skip[:, None], d, out_d)
        V[lanes] = np.where(skip[:, None], v, out_v)
        used[lanes] = np.where(skip | ~room, u, u + 2)
    return D, V


def lookup(D, V, texel, depth):
    """Linear-interpolated AVSM lookup for receivers (texel, depth)."""
    return _curve(D[texel], V[texel], np.asarray(depth, float))

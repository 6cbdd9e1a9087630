"""AVSM in plain Python/NumPy, one texel at a time, written from Salvi et
al. 2010, "Adaptive Volumetric Shadow Maps", secs. 3-4.

Mirrors the conventions documented in avsm_dr/representations/avsm.py: nodes cleared
to (far, 1) and flagged 'clear'; clear nodes sort after inserted nodes of equal depth
and always take a segment's full transmittance; over N nodes, remove the interior node
with the smallest area metric (ties: the deepest); a segment entering where T = 0 is
skipped; with sorted input the texel stops there.
"""
from __future__ import annotations

import numpy as np


def curve(nodes, x):
    """Right-continuous, linearly interpolated value of [(d, t, clear), ...] at x."""
    val = 1.0
    for k, (dk, tk, _) in enumerate(nodes):
        if dk <= x:
            if k + 1 < len(nodes) and nodes[k + 1][0] > x:
                d1, t1, _ = nodes[k + 1]
                val = tk + (x - dk) * (t1 - tk) / (d1 - dk)
            else:
                val = tk
    return val


def insert(nodes, a, b, ts):
    ta = curve(nodes, a)
    tb = curve(nodes, b) * ts
    out = []
    for dk, tk, clear in nodes:
        if clear:
            f = ts
        elif dk <= a:
            f = 1.0
        elif dk >= b:
            f = ts
        else:
            f = 1.0 + (ts - 1.0) * ((dk - a) * (1.0 / (b - a)))
        out.append((dk, tk * f, clear))
    real = [n for n in out if not n[2]]
    clear = [n for n in out if n[2]]
    e = sum(1 for n in real if n[0] <= a)
    real.insert(e, (a, ta, False))
    x = sum(1 for n in real[:e] + real[e + 1:] if n[0] <= b) + 1
    real.insert(x, (b, tb, False))
    return real + clear


def metric(nodes, i):
    (d0, t0, _), (d1, t1, _), (d2, t2, _) = nodes[i - 1], nodes[i], nodes[i + 1]
    return abs((d2 - d0) * (t2 - t1) - (d2 - d1) * (t2 - t0))


def compress(nodes, n):
    """Back to n nodes.  With two or more clear nodes the texel still has room: drop two
    clear nodes (identical copies at far).  Otherwise remove by the area metric."""
    nodes = list(nodes)
    clear = [i for i, p in enumerate(nodes) if p[2]]
    if len(clear) >= len(nodes) - n:
        for i in sorted(clear)[::-1][: len(nodes) - n]:
            del nodes[i]
        return nodes
    while len(nodes) > n:
        ms = [metric(nodes, i) for i in range(1, len(nodes) - 1)]
        best = min(ms)
        idx = max(i for i, m in enumerate(ms) if m == best) + 1
        del nodes[idx]
    return nodes


def build_texel(z0, z1, tau, n, far, sort=False):
    """Nodes (depths, values) of one texel: arrays of length n."""
    order = np.lexsort((z1, z0)) if sort else np.arange(len(z0))
    nodes = [(far, 1.0, True)] * n
    for s in order:
        a, b, ts = float(z0[s]), float(z1[s]), float(np.exp(-tau[s]))
        if curve(nodes, a) == 0.0:
            if sort:
                break
            continue
        nodes = compress(insert(nodes, a, b, ts), n)
    return np.array([p[0] for p in nodes]), np.array([p[1] for p in nodes])



#: Metrics within this of the smallest count as tied in :func:`texel_outcomes` (float64
#: rounding of an area that is 0 in exact arithmetic, e.g. collinear nodes, is ~1e-18).
TIE = 1e-14


def _compress_all(nodes, n, tie, by_metric=False):
    """Every layout :func:`compress` could give when metrics within ``tie`` of the
    smallest are treated as equal (which of them goes is then decided by rounding).
    Like :func:`compress`, the choice between dropping clear nodes and removing by the
    metric is made once per insertion (``by_metric``: already removing by the metric), not
    again after each removal."""
    clear = [i for i, p in enumerate(nodes) if p[2]]
    if len(nodes) <= n:
        return [list(nodes)]
    if not by_metric and len(clear) >= len(nodes) - n:
        return [compress(nodes, n)]
    ms = [metric(nodes, i) for i in range(1, len(nodes) - 1)]
    best = min(ms)
    out = []
    for i, m in enumerate(ms):
        if m <= best + tie:
            out += _compress_all(nodes[:i + 1] + nodes[i + 2:], n, tie, by_metric=True)
    return out


def texel_outcomes(z0, z1, tau, n, far, sort=False, tie=TIE, cap=512):
    """Every (depths, values) :func:`build_texel` can give when removal metrics within
    ``tie`` of each other are ties broken by rounding: collinear nodes have area 0, and
    whichever of them float64 rounding removes, the following insertions see different
    nodes (of the same curve) and may end in different curves.  At most ``cap`` layouts."""
    order = np.lexsort((z1, z0)) if sort else np.arange(len(z0))
    states = [([(far, 1.0, True)] * n, False)]
    for s in order:
        a, b, ts = float(z0[s]), float(z1[s]), float(np.exp(-tau[s]))
        nxt, seen = [], set()
        for nodes, done in states:
            if done or curve(nodes, a) == 0.0:
                cand = [(nodes, done or sort)]
            else:
                cand = [(c, False) for c in _compress_all(insert(nodes, a, b, ts), n, tie)]
            for c in cand:
                key = (tuple(c[0]), c[1])
                if key not in seen:
                    seen.add(key)
                    nxt.append(c)
        states = nxt[:cap]
    return [(np.array([p[0] for p in nodes]), np.array([p[1] for p in nodes])) for nodes, _ in states]


def build(offsets, z0, z1, tau, n, far, sort=False):
    """(T, n) node depths and values for all texels."""
    T = len(offsets) - 1
    D = np.full((T, n), far, dtype=np.float64)
    V = np.ones((T, n))
    for k in range(T):
        s = slice(offsets[k], offsets[k + 1])
        if offsets[k + 1] > offsets[k]:
            D[k], V[k] = build_texel(z0[s], z1[s], tau[s], n, far, sort)
    return D, V


def sample(depths, values, x, mode="linear"):
    """Sample one texel's node list at depth x."""
    val = 1.0
    n = len(depths)
    for k in range(n):
        if depths[k] <= x:
            if k + 1 < n and depths[k + 1] > x:
                w = (x - depths[k]) / (depths[k + 1] - depths[k])
                w = min(max(w, 0.0), 1.0)
                tl, tr = values[k], values[k + 1]
                if mode == "exp" and tl > 0 and tr > 0:
                    val = tl * np.exp(w * (np.log(tr) - np.log(tl)))
                else:
                    val = tl + w * (tr - tl)
            else:
                val = values[k]
    return val

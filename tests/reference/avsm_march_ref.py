"""Engine-style AVSM of one texel in plain float64 Python (checks avsm_march.py):
march over the exact curve's points, a node where T leaves the last node's exponential
extrapolation by more than max(abs_error, rel_error T), AVSM's smallest-area removal
when full, float16 depths relative to the texel's range, binary-search-free lookup."""
from __future__ import annotations

import math

import numpy as np

from . import offline_ref


def slope_after(z0, z1, tau, d, nxt):
    """d tau / dz on (d, nxt): the densities of the positive-length segments covering it
    (0 behind the last depth, ``nxt`` None)."""
    if nxt is None:
        return 0.0
    mid = 0.5 * (d + nxt)
    return sum(t / (b - a) for a, b, t in zip(z0, z1, tau) if b > a and a <= mid < b)


def points(z0, z1, tau):
    """[(depth, T, slope)] in march order."""
    pts = offline_ref.points(z0, z1, tau)
    depths = sorted(set(p[0] for p in pts))
    out = []
    for d, t, _ in pts:
        later = [x for x in depths if x > d]
        out.append((d, t, slope_after(z0, z1, tau, d, later[0] if later else None)))
    return out


def _area(nodes, i):
    (d0, t0), (d1, t1), (d2, t2) = (n[:2] for n in nodes[i - 1:i + 2])
    return abs((d2 - d0) * (t2 - t1) - (d2 - d1) * (t2 - t0))


def _append(nodes, node, cap):
    nodes.append(node)
    if len(nodes) > cap:
        best, idx = math.inf, None
        for i in range(1, len(nodes) - 1):
            m = _area(nodes, i)
            if m <= best:
                best, idx = m, i
        nodes.pop(idx)


def build(z0, z1, tau, cap, abs_error, rel_error):
    """Nodes [(depth, T)] of the texel (empty list for no segments)."""
    if len(z0) == 0:
        return []
    pts = points(z0, z1, tau)
    nodes = [pts[0]]
    last = pts[0]
    prev, prev_is_node = pts[0], True
    for p in pts[1:]:
        x, t, _ = p

        def departs(n):
            return abs(t - n[1] * math.exp(-n[2] * (x - n[0]))) > max(abs_error, rel_error * t)

        add = False
        if departs(last):
            if not prev_is_node:
                _append(nodes, prev, cap)
                last = prev
            add = departs(last)
            if add:
                _append(nodes, p, cap)
                last = p
        prev, prev_is_node = p, add
    if not prev_is_node:
        _append(nodes, prev, cap)
    return [n[:2] for n in nodes]


def quantise(nodes):
    """(lo, hi, [(dequantised depth, T)]): depths as float16 fractions of [lo, hi]."""
    lo, hi = nodes[0][0], nodes[-1][0]
    span = hi - lo
    out = []
    for d, t in nodes:
        q = float(np.float16((d - lo) / span)) if span > 0 else 0.0
        out.append((lo + q * span, t))
    return lo, hi, out


def lookup(nodes, x, interp="exp"):
    """T at x of dequantised nodes: 1 in front, last value behind, AVSM interpolation."""
    if not nodes:
        return 1.0
    return offline_ref.node_curve(nodes, x, interp)

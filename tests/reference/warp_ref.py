"""Monotone piecewise-linear depth warp in plain float64 NumPy, one segment at a time,
written from the definition in avsm_dr/warp.py's docstring (softmax increments over K
uniform knot intervals of [near, far], linear extension beyond), independently of it."""
from __future__ import annotations

import math

import numpy as np


def knot_values(theta) -> np.ndarray:
    """(K + 1,) w at the knots: 0, cumulative softmax(theta) .. 1."""
    e = np.exp(np.asarray(theta, np.float64) - np.max(theta))
    d = e / e.sum()
    return np.r_[0.0, np.cumsum(d)]


def warp(z, near, far, theta) -> np.ndarray:
    """w(z): linear interpolation of the knot values, the end slopes extended outside."""
    v = knot_values(theta)
    K = len(v) - 1
    h = (far - near) / K
    out = []
    for x in np.atleast_1d(np.asarray(z, np.float64)):
        k = min(max(int(math.floor((x - near) / h)), 0), K - 1)
        out.append(v[k] + (v[k + 1] - v[k]) * (x - (near + k * h)) / h)
    return np.array(out)


def warp_segments(case, near, far, theta) -> dict:
    """Each segment split at the knots strictly inside it, pieces warped, optical depth
    shared by length (a zero-length segment stays one step)."""
    K = len(theta)
    h = (far - near) / K
    knots = near + h * np.arange(K + 1)
    off, z0, z1, tau = case["offsets"], case["z0"], case["z1"], case["optical_depth"]
    out = {"offsets": [0], "z0": [], "z1": [], "optical_depth": []}
    for t in range(len(off) - 1):
        for i in range(off[t], off[t + 1]):
            a, b = float(z0[i]), float(z1[i])
            cuts = [a] + [float(c) for c in knots if a < c < b] + [b]
            if b == a:
                cuts = [a, a]
            for p, q in zip(cuts[:-1], cuts[1:]):
                out["z0"].append(warp(p, near, far, theta)[0])
                out["z1"].append(warp(q, near, far, theta)[0])
                out["optical_depth"].append(tau[i] if b == a else tau[i] * (q - p) / (b - a))
        out["offsets"].append(len(out["z0"]))
    return {k: np.asarray(v, np.int64 if k == "offsets" else np.float64) for k, v in out.items()}


def exact(case, texel, depth) -> np.ndarray:
    """T of uniform-density segments; a zero-length segment is a step at z0 (a receiver at
    exactly z0 is behind it)."""
    off, z0, z1, tau = case["offsets"], case["z0"], case["z1"], case["optical_depth"]
    out = []
    for t, x in zip(np.atleast_1d(texel), np.atleast_1d(depth)):
        D = 0.0
        for i in range(off[t], off[t + 1]):
            if z1[i] > z0[i]:
                D += tau[i] * min(max((x - z0[i]) / (z1[i] - z0[i]), 0.0), 1.0)
            elif x >= z0[i]:
                D += tau[i]
        out.append(math.exp(-D))
    return np.array(out)

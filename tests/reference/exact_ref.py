"""Exact transmittance in float64 NumPy, one receiver at a time (checks the Dr.Jit kernel)."""
from __future__ import annotations

import numpy as np


def transmittance(z0, z1, tau, depth):
    """prod_i exp(-tau_i f_i(depth)) over one texel's segments."""
    total = 0.0
    for a, b, t in zip(z0, z1, tau):
        if depth >= b:
            f = 1.0
        elif depth <= a:
            f = 0.0
        else:
            f = (depth - a) / (b - a)
        total += t * f
    return float(np.exp(-total))


def evaluate(offsets, z0, z1, tau, texels, depths):
    out = np.empty(len(texels))
    for k, (tx, d) in enumerate(zip(texels, depths)):
        s = slice(offsets[tx], offsets[tx + 1])
        out[k] = transmittance(z0[s], z1[s], tau[s], d)
    return out

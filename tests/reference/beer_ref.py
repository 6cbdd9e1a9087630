"""Beer shadow map of one texel in plain float64 Python (checks beer.py): front depth,
mean extinction = total optical depth / (last exit - first entry), max optical depth."""
from __future__ import annotations

import math


def transmittance(z0, z1, tau, depth, variant="cloud"):
    """T at ``depth`` of the texel's Beer shadow map (1 for an empty texel)."""
    if len(z0) == 0:
        return 1.0
    a, b, total = min(z0), max(z1), float(sum(tau))
    if variant == "cloud":
        if b > a:
            sigma = total / (b - a)
            return math.exp(-min(total, sigma * max(0.0, depth - a)))
        return math.exp(-total) if depth >= a else 1.0
    # two nodes (a, 1), (b, exp(-total)), linear in between
    tb = math.exp(-total)
    if depth < a:
        return 1.0
    if depth >= b:
        return tb
    return 1.0 + (depth - a) / (b - a) * (tb - 1.0)

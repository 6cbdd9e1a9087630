"""Shadow-map reconstruction filters shared by every representation.

A filter turns receiver positions into taps ``(texel index, weight)`` over a
``width x height`` shadow map (row-major, texel ``y * width + x``); the filtered
transmittance is ``sum_j w_j T_j(depth)`` with ``sum_j w_j = 1``.  Positions are
either integer texel indices (taken at the texel centre) or continuous (K, 2)
coordinates ``(x, y)`` in texel units, texel ``(i, j)`` covering ``[i, i+1) x [j, j+1)``.
Out-of-map taps clamp to the edge.

* ``point``    nearest texel.
* ``bilinear`` the 2x2 texels around the position, weights (1-fx)(1-fy) ... (seed 000 sec. 3.3).
* ``box``      the (2r+1)^2 texels around the nearest one, equal weights, r = ceil(radius).
* ``gaussian`` the same support, weights exp(-|p - c|^2 / (2 sigma^2)), sigma = radius / 2.
"""
from __future__ import annotations

import math

import drjit as dr

FILTERS = ("point", "bilinear", "box", "gaussian")


def taps(x, y, width: int, height: int, filter: str, radius: float, Float, UInt32, Int32):
    """List of (texel UInt32, weight Float) for continuous coordinates (x, y)."""
    def clamp_index(ix, iy):
        ix = dr.clip(ix, 0, width - 1)
        iy = dr.clip(iy, 0, height - 1)
        return UInt32(iy) * width + UInt32(ix)

    if filter == "point":
        return [(clamp_index(Int32(dr.floor(x)), Int32(dr.floor(y))), Float(1))]
    if filter == "bilinear":
        fx, fy = x - 0.5, y - 0.5
        x0, y0 = dr.floor(fx), dr.floor(fy)
        wx, wy = fx - x0, fy - y0
        ix, iy = Int32(x0), Int32(y0)
        return [
            (clamp_index(ix, iy), (1 - wx) * (1 - wy)),
            (clamp_index(ix + 1, iy), wx * (1 - wy)),
            (clamp_index(ix, iy + 1), (1 - wx) * wy),
            (clamp_index(ix + 1, iy + 1), wx * wy),
        ]
    r = int(math.ceil(radius))
    cx, cy = dr.floor(x), dr.floor(y)
    out = []
    sigma = max(radius, 1e-6) / 2.0
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            if filter == "box":
                w = Float(1.0 / (2 * r + 1) ** 2)
            else:
                px, py = cx + dx + 0.5 - x, cy + dy + 0.5 - y
                w = dr.exp(-(px * px + py * py) / (2 * sigma * sigma))
            out.append((clamp_index(Int32(cx) + dx, Int32(cy) + dy), w))
    if filter == "gaussian":
        total = sum((w for _, w in out), Float(0))
        out = [(t, w / total) for t, w in out]
    return out

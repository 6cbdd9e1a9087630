"""Shadow-map reconstruction filters shared by every representation.

A filter turns receiver positions into taps ``(texel index, weight)`` over a
``width x height`` shadow map (row-major, texel ``y * width + x``); the filtered
transmittance is ``sum_j w_j T_j(depth) / sum_j w_j``.  Positions are either integer
texel indices (taken at the texel centre) or continuous (K, 2) coordinates ``(x, y)`` in
texel units, texel ``(i, j)`` covering ``[i, i+1) x [j, j+1)``.  Out-of-map taps clamp
to the edge.

* ``point``    nearest texel.
* ``bilinear`` the 2x2 texels around the position, weights (1-fx)(1-fy) ... (Salvi et al.,
  "Adaptive Volumetric Shadow Maps", 2010, sec. 3.3).
* ``box``      the (2r+1)^2 texels around the one holding the position, equal weights,
  r = ceil(radius).
* ``gaussian`` the same support, weights exp(-(|p - c|^2 - |p - c_0|^2) / (2 sigma^2)),
  sigma = radius / 2, c_0 the centre of the texel holding p (weight 1, so the sum never
  underflows to 0 however small the radius: a tiny radius becomes the point filter).

Coordinates are split on the device in float64 (:func:`split_on_device`) into an integer
texel (clamped to the map) and the offset inside it, so texel selection is exact on any map
and coordinates far outside it (>= 2^31) clamp to the edge.  ``radius``: finite, ``> 0`` and at most
``max(width, height)``.
"""
from __future__ import annotations

import math

import drjit as dr
import numpy as np

from . import _arrays as A
from . import backend
from . import validation as V

FILTERS = ("point", "bilinear", "box", "gaussian")
#: (receiver, tap) lanes evaluated per batch (bounds the temporary memory: ~50 bytes/lane).
LANES_PER_BATCH = 1 << 22
#: Largest gaussian ``1 / (2 sigma^2)`` used: finite in float32 also times a squared
#: distance of the support (<= 2 (r + 1)^2 for r <= 1: below 1e8).
GAUSSIAN_INV2S2_MAX = 1e30
#: Coordinates below the smallest normal float64 count as 0 on every device.
TINY = float(np.finfo(np.float64).tiny)


def check_radius(radius, width: int | None = None, height: int | None = None) -> float:
    """``radius``: a finite real number > 0 (not bool / str), at most max(width, height)."""
    r = V.real(radius, "radius", 0, open_min=True)
    if width is not None and height is not None and r > max(width, height):
        raise ValueError(f"radius: expected <= max(width, height) = {max(width, height)} (a larger "
                         f"kernel only re-weights the clamped edge texels), got {radius!r}")
    return r


def split_on_device(coords: np.ndarray, width: int, height: int, shift: float = 0.0, margin: int = 0):
    """(ix, iy, fx, fy) of (K, 2) float64 host coordinates minus ``shift``, on the device: the integer
    texel (Int32, ``floor``, clamped to [-margin - 1, size + margin] so that every tap of a support
    ``margin`` clamps as before) and the offset inside it (Float64 in [0, 1)); subnormal coordinates
    count as 0 (LLVM's worker threads flush them, CUDA does not)."""
    t = backend.types()
    out = []
    for c, size in ((0, width), (1, height)):
        x = t.Float64(A.aligned(np.ascontiguousarray(coords[:, c]))) - shift
        x = dr.select(dr.abs(x) < TINY, 0.0, x)
        f = dr.floor(x)
        out += [t.Int32(dr.clip(f, -margin - 1, size + margin)), x - f]
    return out[0], out[2], out[1], out[3]


def _taps(coords: np.ndarray, width: int, height: int, filter: str):
    """(texel UInt32, weight Float64) of the point filter's one tap (weight None) or the bilinear
    filter's four, weights ``(1-fx)(1-fy), fx (1-fy), (1-fx) fy, fx fy``; texels clamped to the map."""
    UInt32, bilinear = backend.types().UInt32, filter == "bilinear"
    ix, iy, fx, fy = split_on_device(coords, width, height, 0.5 if bilinear else 0.0, int(bilinear))
    for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1))[:4 if bilinear else 1]:
        tex = UInt32(dr.clip(iy + dy, 0, height - 1)) * width + UInt32(dr.clip(ix + dx, 0, width - 1))
        yield tex, ((fx if dx else 1 - fx) * (fy if dy else 1 - fy) if bilinear else None)


def bilinear_taps(coords: np.ndarray, width: int, height: int):
    """(tex, weights): host copies of the bilinear filter's taps at (K, 2) coordinates, (4, K) int64
    texels and float64 weights (:func:`_taps`)."""
    taps = list(_taps(coords, width, height, "bilinear"))
    return np.stack([t.numpy() for t, _ in taps]).astype(np.int64), np.stack([w.numpy() for _, w in taps])


def filtered_eval(eval_texels, coords: np.ndarray, depth, width: int, height: int, filter: str,
                  radius: float, Float, UInt32, Int32):
    """Filtered transmittance of K receivers (module docstring).

    eval_texels(texel UInt32, depth Float) -> Float: the representation's kernel;
    coords: (K, 2) float64 host coordinates; depth: Float (K,) (AD graph kept)."""
    k = coords.shape[0]
    if filter == "point":
        return eval_texels(next(_taps(coords, width, height, filter))[0], depth)
    if filter == "bilinear":
        total = Float(0)
        for tex, w in _taps(coords, width, height, filter):
            total = total + Float(w) * eval_texels(tex, depth)
        return total

    # box / gaussian: K x m lanes, lane = receiver * m + tap (receiver-major, block sums)
    r = int(math.ceil(radius))
    side = 2 * r + 1
    m = side * side
    ix_d, iy_d, fx, fy = split_on_device(coords, width, height, margin=r)
    fx_d, fy_d = Float(fx), Float(fy)
    # 1 / (2 sigma^2), capped where it would overflow float32 (radius < ~1e-19): an inf
    # times the own texel's exponent 0 made every weight NaN; at the cap the other taps'
    # weights are 0 and ties 1, the limit of the formula (the point filter).
    inv2s2 = min(1.0 / (2.0 * (radius / 2.0) ** 2), GAUSSIAN_INV2S2_MAX)
    num, den = dr.zeros(Float, k), dr.zeros(Float, k)
    per = max(1, min(m, LANES_PER_BATCH // max(k, 1)))     # taps per batch
    for j0 in range(0, m, per):
        mt = min(per, m - j0)
        lane = dr.arange(UInt32, k * mt)
        rec = lane // mt
        j = dr.opaque(UInt32, j0) + lane % mt                # tap index in [0, m)
        dx = Int32(j % side) - r
        dy = Int32(j // side) - r
        tx = dr.clip(dr.gather(Int32, ix_d, rec) + dx, 0, width - 1)
        ty = dr.clip(dr.gather(Int32, iy_d, rec) + dy, 0, height - 1)
        tex = UInt32(ty) * width + UInt32(tx)
        if filter == "box":
            w = dr.full(Float, 1.0, k * mt)
        else:
            ox, oy = dr.gather(Float, fx_d, rec), dr.gather(Float, fy_d, rec)
            px, py = Float(dx) + 0.5 - ox, Float(dy) + 0.5 - oy    # tap centre - position
            qx, qy = 0.5 - ox, 0.5 - oy                               # own centre - position
            w = dr.exp(-((px * px + py * py) - (qx * qx + qy * qy)) * inv2s2)
        T = eval_texels(tex, dr.gather(Float, depth, rec))
        num = num + dr.block_sum(w * T, mt)
        den = den + dr.block_sum(w, mt)
        if mt < m:
            dr.eval(num, den)                                # one batch per kernel
    return num / den

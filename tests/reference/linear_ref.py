"""Linear representations (FOM, OSM, any basis) in plain float64 NumPy loops, one
texel and one segment at a time, written from Jansen and Bavoil 2010,
"Fourier Opacity Mapping", eqs. 1-3 and secs. 5 / 5.1.

Conventions mirrored from avsm_dr/representations/basis.py (documented there):
u = (z - near) / span, span = max(far - near, r max(|near|, |far|) + tiny) (r = 1e-6 in float32,
1e-14 in float64; tiny: the dtype's smallest normal number); the part of a
segment in front of near is a delta at u = 0, the part behind far is dropped; a
zero-length segment is a delta at its depth; receivers clamp to u in [0, 1].
Projections are computed independently of the kernels: closed-form antiderivative
differences (Fourier in 80-bit long double, slices) or 64-point Gauss-Legendre quadrature
(short Fourier segments, any basis).
"""
from __future__ import annotations

import math

import numpy as np

#: Span floor per storage dtype: MIN_SPAN_REL[dtype] max(|lo|, |hi|) + MIN_SPAN_ABS[dtype].
MIN_SPAN_REL = {"float32": 1e-6, "float64": 1e-14}
MIN_SPAN_ABS = {"float32": float(np.finfo(np.float32).tiny), "float64": float(np.finfo(np.float64).tiny)}
LD = np.longdouble                      # 80-bit on x86: the Fourier difference quotients
PI_LD = np.arccos(LD(-1))               # lose digits for short segments (eps / du)
GL_X, GL_W = np.polynomial.legendre.leggauss(64)


# ----------------------------------------------------------------- ranges
def ranges(case, near=None, far=None, depth_range="global"):
    """(near, span) per texel as float64 arrays (the floor of ``case['dtype']``, default
    float32)."""
    off, z0, z1 = case["offsets"], case["z0"], case["z1"]
    T = len(off) - 1
    lo = np.zeros(T)
    hi = np.ones(T)
    if depth_range == "texel":
        for t in range(T):
            if off[t + 1] > off[t]:
                lo[t] = min(z0[off[t]:off[t + 1]])
                hi[t] = max(z1[off[t]:off[t + 1]])
    else:
        if near is None:
            near = min(z0) if len(z0) else 0.0
        if far is None:
            far = max(z1) if len(z1) else 1.0
        lo[:], hi[:] = near, far
    dt = case.get("dtype", "float32")
    span = np.maximum(hi - lo, MIN_SPAN_REL[dt] * np.maximum(abs(lo), abs(hi)) + MIN_SPAN_ABS[dt])
    return lo, span


def split(z0, z1, tau, near, span):
    """Clip one segment to u in [0, 1]: (c0, c1, tau inside, tau in front of near)."""
    u0, u1 = (z0 - near) / span, (z1 - near) / span
    if u1 == u0:                        # zero-length: a delta
        if u0 < 0:
            return 0.0, 0.0, 0.0, tau
        if u0 > 1:
            return 1.0, 1.0, 0.0, 0.0
        return u0, u0, tau, 0.0
    c0, c1 = min(max(u0, 0.0), 1.0), min(max(u1, 0.0), 1.0)
    length = u1 - u0
    return c0, c1, tau * (c1 - c0) / length, tau * (min(u1, 0.0) - min(u0, 0.0)) / length


def segments_of(case, t):
    off = case["offsets"]
    for i in range(off[t], off[t + 1]):
        yield case["z0"][i], case["z1"][i], case["tau"][i]


# ---------------------------------------------------------------- Fourier
def fourier_coefficients(case, harmonics, **rng):
    """(T, 2n+1) [a'_0, a'_1, b'_1, ...] from eqs. 1-2 integrated over each segment."""
    near, span = ranges(case, **rng)
    T = len(case["offsets"]) - 1
    out = np.zeros((T, 2 * harmonics + 1))
    for t in range(T):
        for z0, z1, tau in segments_of(case, t):
            c0, c1, tin, tfront = split(z0, z1, tau, near[t], span[t])
            c0, c1, tin = LD(c0), LD(c1), LD(tin)
            out[t, 0] += 2 * tin + 2 * tfront
            for k in range(1, harmonics + 1):
                w = 2 * PI_LD * k
                if c1 - c0 > 1e-2:      # 2 tau / du * int cos(w u) du
                    a = 2 * tin * (np.sin(w * c1) - np.sin(w * c0)) / (w * (c1 - c0))
                    b = 2 * tin * (np.cos(w * c0) - np.cos(w * c1)) / (w * (c1 - c0))
                else:                   # short: 64-point Gauss-Legendre mean (delta: eqs. 5, 6)
                    x = (c0 + c1) / 2 + (c1 - c0) / 2 * GL_X.astype(LD)
                    a = 2 * tin * np.dot(GL_W.astype(LD), np.cos(w * x)) / 2
                    b = 2 * tin * np.dot(GL_W.astype(LD), np.sin(w * x)) / 2
                out[t, 2 * k - 1] += float(a) + 2 * tfront      # cos(0) = 1, sin(0) = 0
                out[t, 2 * k] += float(b)
    return out


def fourier_optical_depth(coeffs, u):
    """Eq. 3 for one texel's coefficients at normalised depths u (clamped to [0, 1])."""
    u = np.clip(np.asarray(u, np.float64), 0, 1)
    n = (len(coeffs) - 1) // 2
    D = coeffs[0] / 2 * u
    for k in range(1, n + 1):
        w = 2 * math.pi * k
        D = D + coeffs[2 * k - 1] * np.sin(w * u) / w + coeffs[2 * k] * (1 - np.cos(w * u)) / w
    return D


# ----------------------------------------------------------------- slices
def slice_coefficients(case, slices, **rng):
    """(T, n) optical depth inside each of n uniform slices (sec. 5.1)."""
    near, span = ranges(case, **rng)
    T = len(case["offsets"]) - 1
    out = np.zeros((T, slices))
    for t in range(T):
        for z0, z1, tau in segments_of(case, t):
            c0, c1, tin, tfront = split(z0, z1, tau, near[t], span[t])
            out[t, 0] += tfront
            if c1 > c0:
                for k in range(slices):
                    lo, hi = k / slices, (k + 1) / slices
                    out[t, k] += tin * max(0.0, min(c1, hi) - max(c0, lo)) / (c1 - c0)
            else:
                out[t, min(int(math.floor(c0 * slices)), slices - 1)] += tin
    return out


def slice_optical_depth(coeffs, u):
    u = np.clip(np.asarray(u, np.float64), 0, 1)
    n = len(coeffs)
    return sum(coeffs[k] * np.clip(n * u - k, 0, 1) for k in range(n))


# ------------------------------------------------------------- any basis
def basis_coefficients(case, fs, **rng):
    """(T, K) a_k = int sigma f_k by 64-point Gauss-Legendre per segment; fs: list of
    vectorised float64 callables f_k(u)."""
    near, span = ranges(case, **rng)
    T = len(case["offsets"]) - 1
    out = np.zeros((T, len(fs)))
    for t in range(T):
        for z0, z1, tau in segments_of(case, t):
            c0, c1, tin, tfront = split(z0, z1, tau, near[t], span[t])
            x = 0.5 * (c0 + c1) + 0.5 * (c1 - c0) * GL_X
            for k, f in enumerate(fs):
                out[t, k] += tin * 0.5 * np.dot(GL_W, f(x)) + tfront * f(np.zeros(1))[0]
    return out


def basis_optical_depth(coeffs, fs, u):
    """D(u) = sum_k a_k int_0^u f_k (orthonormal basis), by Gauss-Legendre on [0, u]."""
    u = np.clip(np.atleast_1d(np.asarray(u, np.float64)), 0, 1)
    D = np.zeros(u.size)
    for j, uj in enumerate(u):
        x = 0.5 * uj * (1 + GL_X)
        D[j] = sum(a * 0.5 * uj * np.dot(GL_W, f(x)) for a, f in zip(coeffs, fs))
    return D


def legendre_functions(n):
    """f_k(u) = sqrt(2k+1) P_k(2u - 1), k < n."""
    return [(lambda u, k=k: math.sqrt(2 * k + 1)
             * np.polynomial.legendre.legval(2 * u - 1, [0] * k + [1])) for k in range(n)]


def cosine_functions(n):
    """f_0 = 1, f_k = sqrt(2) cos(pi k u)."""
    return [lambda u: np.ones_like(u)] + [(lambda u, k=k: math.sqrt(2) * np.cos(math.pi * k * u))
                                          for k in range(1, n)]


# ------------------------------------------------------------------ exact
def exact_optical_depth(case, t, depth):
    """Optical depth of texel t in front of each depth (uniform density per segment;
    a receiver at a zero-length segment's depth is behind it)."""
    depth = np.atleast_1d(np.asarray(depth, np.float64))
    D = np.zeros(depth.size)
    for z0, z1, tau in segments_of(case, t):
        for j, d in enumerate(depth):
            if d >= z1:
                D[j] += tau
            elif d > z0:
                D[j] += tau * (d - z0) / (z1 - z0)
    return D


def transmittance(D):
    return np.clip(np.exp(-np.asarray(D)), 0, 1)

"""Fourier opacity maps with Numba ``parallel=True``: the peer a careful researcher would
write for :mod:`avsm_dr.representations.fom` (Jansen and Bavoil, "Fourier Opacity
Mapping", I3D 2010, eqs. 1-6; segments integrated analytically), global depth range
``[near, far]``.

Build: one thread-chunk of texels at a time, each texel summing its segments' coefficients

    a'_0 += 2 tau,   a'_k += 2 tau sinc(pi k du) cos(2 pi k m),   b'_k += 2 tau sinc(pi k du) sin(2 pi k m)

(``m``, ``du``: midpoint and length in ``u = (z - near) / (far - near)``); the harmonics
k = 1..n come from the angle-addition recurrence (4 libm calls per segment instead of 4n).
Segments outside the range are clipped as in :mod:`avsm_dr.representations.basis`
(the part in front of ``near`` is a delta at u = 0, the part behind ``far`` is dropped).
Lookup: ``D(u) = a'_0 u / 2 + sum_k [a'_k sin(2 pi k u) + b'_k (1 - cos(2 pi k u))] / (2 pi k)``,
``T = clamp(exp(-D), 0, 1)`` (eq. 3, sec. 7.3).

Numba is optional (the ``bench`` extra); importing this module never needs it.
"""
from __future__ import annotations

import math
import time

import numpy as np

from avsm_dr.representations.basis import MIN_SPAN_ABS, MIN_SPAN_REL

from ._numba import numba, require as _require_numba

_KERNELS: dict = {}
_COMPILE_S: dict = {}


def available() -> bool:
    """True when Numba can be imported."""
    return numba is not None


def compile_seconds() -> dict:
    """Seconds spent compiling each kernel on its first call (``{'build': s, 'lookup': s}``)."""
    return dict(_COMPILE_S)


def _kernels() -> dict:
    if _KERNELS:
        return _KERNELS
    _require_numba(numba)
    njit, prange = numba.njit, numba.prange
    PI = math.pi

    @njit(parallel=True)
    def build(offsets, z0, z1, tau, n, near, span, coeffs):
        """coeffs (T, 2n+1) in the paper's packing [a'_0, a'_1, b'_1, ..., a'_n, b'_n]."""
        T = offsets.size - 1
        n_chunks = min(T, 64 * numba.get_num_threads())
        for c in prange(n_chunks):
            for tex in range(c * T // n_chunks, (c + 1) * T // n_chunks):
                for k in range(2 * n + 1):
                    coeffs[tex, k] = 0.0
                for s in range(offsets[tex], offsets[tex + 1]):
                    u0 = (z0[s] - near) / span
                    u1 = (z1[s] - near) / span
                    c0 = min(max(u0, 0.0), 1.0)
                    c1 = min(max(u1, 0.0), 1.0)
                    du = u1 - u0
                    if du > 0:
                        inside = (c1 - c0) / du
                        front = (min(u1, 0.0) - min(u0, 0.0)) / du
                    else:
                        inside = 1.0 if 0.0 <= u0 <= 1.0 else 0.0
                        front = 1.0 if u0 < 0.0 else 0.0
                    t_in, t_front = tau[s] * inside, tau[s] * front
                    coeffs[tex, 0] += 2 * t_in + 2 * t_front
                    m, w = 0.5 * (c0 + c1), c1 - c0
                    s1, c1m = math.sin(2 * PI * m), math.cos(2 * PI * m)   # angle 2 pi m
                    h = PI * w                                              # half-width angle
                    sh1, ch1 = math.sin(h), math.cos(h)
                    sk, ck = s1, c1m                                        # sin/cos(2 pi k m)
                    shk, chk = sh1, ch1                                     # sin/cos(pi k w)
                    for k in range(1, n + 1):
                        x = k * h
                        x2 = x * x
                        sinc = shk / x if x > 0.1 else 1 - x2 / 6 + x2 * x2 / 120 - x2 ** 3 / 5040 + x2 ** 4 / 362880
                        amp = 2 * t_in * sinc
                        coeffs[tex, 2 * k - 1] += amp * ck + 2 * t_front
                        coeffs[tex, 2 * k] += amp * sk
                        sk, ck = sk * c1m + ck * s1, ck * c1m - sk * s1
                        shk, chk = shk * ch1 + chk * sh1, chk * ch1 - shk * sh1

    @njit(parallel=True)
    def lookup(coeffs, n, near, span, texel, depth, out):
        for r in prange(texel.size):
            tx = texel[r]
            u = min(max((depth[r] - near) / span, 0.0), 1.0)
            D = coeffs[tx, 0] * 0.5 * u
            s1, c1 = math.sin(PI * u), math.cos(PI * u)       # half angle pi u
            sk, ck = s1, c1
            for k in range(1, n + 1):
                # sin(2x) = 2 sin x cos x, 1 - cos(2x) = 2 sin^2 x  (x = pi k u)
                D += (coeffs[tx, 2 * k - 1] * sk * ck + coeffs[tx, 2 * k] * sk * sk) / (PI * k)
                sk, ck = sk * c1 + ck * s1, ck * c1 - sk * s1
            out[r] = min(max(math.exp(-D), 0.0), 1.0)

    _KERNELS.update(build=build, lookup=lookup)
    return _KERNELS


def span_of(near: float, far: float, dtype: str = "float32") -> float:
    """far - near, floored as in :mod:`avsm_dr.representations.basis` for a map stored in
    ``dtype`` (MIN_SPAN_REL, MIN_SPAN_ABS; the kernels it is timed against are float32)."""
    return max(far - near, MIN_SPAN_REL[dtype] * max(abs(near), abs(far)) + MIN_SPAN_ABS[dtype])


def build(offsets, z0, z1, tau, harmonics: int, near: float, far: float) -> np.ndarray:
    """(T, 2n+1) float64 Fourier coefficients of every texel (see the module docstring).

    offsets: (T+1,) CSR; z0, z1, tau: (S,) segment depths and optical depths;
    harmonics: n >= 1; near < far: the global depth range."""
    K = _kernels()
    n = int(harmonics)
    if n < 1:
        raise ValueError(f"harmonics: expected an integer >= 1, got {harmonics!r}")
    offsets = np.ascontiguousarray(offsets, np.int64)
    coeffs = np.zeros((offsets.size - 1, 2 * n + 1))
    if offsets.size > 1:
        t0 = time.perf_counter()
        K["build"](offsets, np.ascontiguousarray(z0, np.float64), np.ascontiguousarray(z1, np.float64),
                   np.ascontiguousarray(tau, np.float64), n, float(near), span_of(near, far), coeffs)
        _COMPILE_S.setdefault("build", time.perf_counter() - t0)
    return coeffs


def lookup(coeffs, near: float, far: float, texel, depth) -> np.ndarray:
    """T = clamp(exp(-D(u)), 0, 1) at receivers (texel, depth)."""
    K = _kernels()
    coeffs = np.ascontiguousarray(coeffs, np.float64)
    n = (coeffs.shape[1] - 1) // 2
    texel = np.ascontiguousarray(texel, np.int64)
    depth = np.ascontiguousarray(depth, np.float64)
    out = np.empty(texel.size)
    t0 = time.perf_counter()
    K["lookup"](coeffs, n, float(near), span_of(near, far), texel, depth, out)
    _COMPILE_S.setdefault("lookup", time.perf_counter() - t0)
    return out

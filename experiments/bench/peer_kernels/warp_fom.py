"""Fourier opacity maps in NVIDIA Warp: the Warp peer of :mod:`avsm_dr.representations.fom`
(Jansen and Bavoil, "Fourier Opacity Mapping", I3D 2010, eqs. 1-6; segments integrated
analytically), global depth range ``[near, far]``, float64 like :mod:`.numba_fom`.

Build: one Warp thread per texel summing its segments' coefficients

    a'_0 += 2 tau,   a'_k += 2 tau sinc(pi k du) cos(2 pi k m),   b'_k += 2 tau sinc(pi k du) sin(2 pi k m)

with the harmonics from the angle-addition recurrence and the clipping of
:mod:`avsm_dr.representations.basis`, in the expression order of :mod:`.numba_fom`.
Lookup: ``D(u) = a'_0 u / 2 + sum_k [a'_k sin(2 pi k u) + b'_k (1 - cos(2 pi k u))] / (2 pi k)``,
``T = clamp(exp(-D), 0, 1)`` (eq. 3, sec. 7.3).  Warp runs a CPU launch serially on one
thread.

Warp is optional (the ``bench`` extra); importing this module never needs it.
"""
# no ``from __future__ import annotations``: Warp reads the kernels' annotations as types
import math
import time

import numpy as np

from ._warp import int32_array as _int32, require as _require_warp, warp as wp
from .numba_fom import span_of

_KERNELS: dict = {}
_COMPILE_S: dict = {}


def available() -> bool:
    """True when Warp can be imported."""
    return wp is not None


def compile_seconds() -> dict:
    """Seconds spent loading (compiling, or reading from Warp's cache) the kernel module on
    the first call (``{'module': s}``)."""
    return dict(_COMPILE_S)


def _kernels() -> dict:
    if _KERNELS:
        return _KERNELS
    _require_warp(wp, __name__)
    f64 = wp.float64
    Arr1 = wp.array(dtype=wp.float64)
    Arr2 = wp.array2d(dtype=wp.float64)
    PI = wp.constant(wp.float64(math.pi))

    @wp.kernel
    def build(offsets: wp.array(dtype=wp.int32), z0: Arr1, z1: Arr1, tau: Arr1, n: int, near: wp.float64,
              span: wp.float64, coeffs: Arr2):
        """coeffs (T, 2n+1) in the paper's packing [a'_0, a'_1, b'_1, ..., a'_n, b'_n], zeroed."""
        tex = wp.tid()
        zero = f64(0.0)
        one = f64(1.0)
        two = f64(2.0)
        for s in range(offsets[tex], offsets[tex + 1]):
            u0 = (z0[s] - near) / span
            u1 = (z1[s] - near) / span
            c0 = wp.min(wp.max(u0, zero), one)
            c1 = wp.min(wp.max(u1, zero), one)
            du = u1 - u0
            inside = zero
            front = zero
            if du > zero:
                inside = (c1 - c0) / du
                front = (wp.min(u1, zero) - wp.min(u0, zero)) / du
            else:
                if u0 >= zero and u0 <= one:
                    inside = one
                if u0 < zero:
                    front = one
            t_in = tau[s] * inside
            t_front = tau[s] * front
            coeffs[tex, 0] += two * t_in + two * t_front
            m = f64(0.5) * (c0 + c1)
            w = c1 - c0
            s1 = wp.sin(two * PI * m)            # angle 2 pi m
            c1m = wp.cos(two * PI * m)
            h = PI * w                           # half-width angle
            sh1 = wp.sin(h)
            ch1 = wp.cos(h)
            sk = s1                              # sin/cos(2 pi k m)
            ck = c1m
            shk = sh1                            # sin/cos(pi k w)
            chk = ch1
            for k in range(1, n + 1):
                x = f64(k) * h
                x2 = x * x
                sinc = zero
                if x > f64(0.1):
                    sinc = shk / x
                else:
                    sinc = (one - x2 / f64(6.0) + x2 * x2 / f64(120.0) - x2 * x2 * x2 / f64(5040.0)
                            + x2 * x2 * x2 * x2 / f64(362880.0))
                amp = two * t_in * sinc
                coeffs[tex, 2 * k - 1] += amp * ck + two * t_front
                coeffs[tex, 2 * k] += amp * sk
                sk_next = sk * c1m + ck * s1
                ck = ck * c1m - sk * s1
                sk = sk_next
                shk_next = shk * ch1 + chk * sh1
                chk = chk * ch1 - shk * sh1
                shk = shk_next

    @wp.kernel
    def lookup(coeffs: Arr2, n: int, near: wp.float64, span: wp.float64, texel: wp.array(dtype=wp.int32),
               depth: Arr1, out: Arr1):
        r = wp.tid()
        tx = texel[r]
        u = wp.min(wp.max((depth[r] - near) / span, f64(0.0)), f64(1.0))
        D = coeffs[tx, 0] * f64(0.5) * u
        s1 = wp.sin(PI * u)                      # half angle pi u
        c1 = wp.cos(PI * u)
        sk = s1
        ck = c1
        for k in range(1, n + 1):
            # sin(2x) = 2 sin x cos x, 1 - cos(2x) = 2 sin^2 x  (x = pi k u)
            D += (coeffs[tx, 2 * k - 1] * sk * ck + coeffs[tx, 2 * k] * sk * sk) / (PI * f64(k))
            sk_next = sk * c1 + ck * s1
            ck = ck * c1 - sk * s1
            sk = sk_next
        out[r] = wp.min(wp.max(wp.exp(-D), f64(0.0)), f64(1.0))

    t0 = time.perf_counter()
    wp.load_module(build.module, device="cpu")
    _COMPILE_S["module"] = time.perf_counter() - t0
    _KERNELS.update(build=build, lookup=lookup)
    return _KERNELS


def build(offsets, z0, z1, tau, harmonics: int, near: float, far: float) -> np.ndarray:
    """(T, 2n+1) float64 Fourier coefficients of every texel; as :func:`.numba_fom.build`."""
    n = int(harmonics)
    if n < 1:
        raise ValueError(f"harmonics: expected an integer >= 1, got {harmonics!r}")
    K = _kernels()
    offsets = _int32(offsets, "offsets")
    coeffs = np.zeros((offsets.size - 1, 2 * n + 1))
    if offsets.size > 1:
        arr = [wp.array(np.ascontiguousarray(x, np.float64), copy=False, device="cpu") for x in (z0, z1, tau)]
        wp.launch(K["build"], dim=offsets.size - 1, device="cpu",
                  inputs=[wp.array(offsets, copy=False, device="cpu"), *arr, n, float(near), span_of(near, far),
                          wp.array(coeffs, copy=False, device="cpu")])
        wp.synchronize_device("cpu")
    return coeffs


def lookup(coeffs, near: float, far: float, texel, depth) -> np.ndarray:
    """T = clamp(exp(-D(u)), 0, 1) at receivers (texel, depth)."""
    K = _kernels()
    coeffs = np.ascontiguousarray(coeffs, np.float64)
    n = (coeffs.shape[1] - 1) // 2
    texel = _int32(texel, "texel")
    depth = np.ascontiguousarray(depth, np.float64)
    out = np.empty(texel.size)
    if texel.size:
        wp.launch(K["lookup"], dim=texel.size, device="cpu",
                  inputs=[wp.array(coeffs, copy=False, device="cpu"), n, float(near), span_of(near, far),
                          wp.array(texel, copy=False, device="cpu"), wp.array(depth, copy=False, device="cpu"),
                          wp.array(out, copy=False, device="cpu")])
        wp.synchronize_device("cpu")
    return out

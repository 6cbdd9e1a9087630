"""AVSM with Numba ``parallel=True``: what a careful researcher would write instead of
Dr.Jit (scalar code per texel, texels spread over threads with ``prange``).

Same algorithm and conventions as :mod:`avsm_dr.representations.avsm` (Salvi et al.,
"Adaptive Volumetric Shadow Maps", EGSR 2010, sec. 3.1-3.3): N nodes cleared to
``(far, 1)``; a segment ``[a, b]`` with exit transmittance ``ts`` multiplies the inserted nodes by its linear ramp
``R(d) = 1 (d <= a), 1 + (ts - 1)(d - a)/(b - a) (a < d < b), ts (d >= b)`` and the clear
nodes by ``ts``, then adds ``(a, T(a))`` and ``(b, T(b) ts)`` after the inserted nodes of
equal depth; while over N, the interior node of smallest
``|(d[i+1]-d[i-1])(t[i+1]-t[i]) - (d[i+1]-d[i])(t[i+1]-t[i-1])|`` is removed (ties: the
deepest); a segment whose entry lies where T = 0 is not inserted (sorted input: the
rest of the texel is skipped).  Every floating-point expression is written in the
kernel's order, so float64 node depths are bit-identical to the kernel's and values
agree to rounding (``tests/test_peers.py``).

Numba is optional (the ``bench`` extra): importing this module never needs it; the
kernels compile on the first call (:func:`compile_seconds` reports how long that took).
"""
from __future__ import annotations

import time

import numpy as np

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
    """The jitted functions, created on first use (so that importing needs no Numba)."""
    if _KERNELS:
        return _KERNELS
    _require_numba(numba)
    njit, prange = numba.njit, numba.prange

    @njit(inline="always")
    def curve(d, t, n, x):
        """T(x) of the first n nodes: t_l + (x - d_l)(t_r - t_l) / (d_r - d_l) (kernel order)."""
        dl, tl, dr, tr = x, 1.0, x, 1.0
        for k in range(n):
            if d[k] <= x:
                nxt = min(k + 1, n - 1)
                dl, tl, dr, tr = d[k], t[k], d[nxt], t[nxt]
        dd = dr - dl
        return tl + (x - dl) * (tr - tl) / (dd if dd > 0 else 1.0)

    @njit(inline="always")
    def remove_smallest(d, t, n):
        """Remove the interior node of smallest area metric from the first n (ties: deepest)."""
        best = abs((d[2] - d[0]) * (t[2] - t[1]) - (d[2] - d[1]) * (t[2] - t[0]))
        idx = 1
        for i in range(2, n - 1):
            m = abs((d[i + 1] - d[i - 1]) * (t[i + 1] - t[i]) - (d[i + 1] - d[i]) * (t[i + 1] - t[i - 1]))
            if m <= best:
                best = m
                idx = i
        for j in range(idx, n - 1):
            d[j] = d[j + 1]
            t[j] = t[j + 1]

    @njit(parallel=True)
    def build(offsets, z0, z1, ts, N, far, sort, D, V, used_out, stats):
        """Per texel: stream its segments into N nodes.  stats[tex] = (skipped, compressed)."""
        T = offsets.size - 1
        n_chunks = min(T, 64 * numba.get_num_threads())
        for c in prange(n_chunks):
            d = np.empty(N + 2)                 # node depths (N + 2 during an insertion)
            t = np.empty(N + 2)                 # node transmittances
            for tex in range(c * T // n_chunks, (c + 1) * T // n_chunks):
                for k in range(N):
                    d[k] = far
                    t[k] = 1.0
                used = 0                        # inserted nodes kept (clear nodes follow)
                skipped = 0
                compressed = 0
                start, end = offsets[tex], offsets[tex + 1]
                for s in range(start, end):
                    a, b, tsv = z0[s], z1[s], ts[s]
                    ta = curve(d, t, N, a)
                    if ta == 0:                 # behind a fully opaque point
                        skipped += 1
                        if sort:
                            skipped += end - s - 1
                            break
                        continue
                    tb = curve(d, t, N, b) * tsv
                    length = b - a
                    inv_len = 1 / (length if length > 0 else 1.0)
                    e = 0                       # slot of the entry node
                    x = 1                       # slot of the exit node
                    for k in range(N):
                        if k < used:
                            dk = d[k]
                            if dk <= a:
                                e += 1
                            if dk <= b:
                                x += 1
                            if dk > a:
                                if dk >= b:
                                    t[k] = t[k] * tsv
                                else:
                                    t[k] = t[k] * (1 + (tsv - 1) * ((dk - a) * inv_len))
                        else:                   # clear nodes take the full ts
                            t[k] = t[k] * tsv
                    for j in range(N + 1, -1, -1):   # merge in place, from the back
                        if j == x:
                            d[j] = b
                            t[j] = tb
                        elif j == e:
                            d[j] = a
                            t[j] = ta
                        else:
                            sh = (1 if e < j else 0) + (1 if x < j else 0)
                            d[j] = d[j - sh]
                            t[j] = t[j - sh]
                    if used + 2 <= N:           # room: the two last (clear) nodes drop out
                        used += 2
                    else:
                        remove_smallest(d, t, N + 2)
                        remove_smallest(d, t, N + 1)
                        compressed += 1
                for k in range(N):
                    D[tex, k] = d[k]
                    V[tex, k] = t[k]
                used_out[tex] = used
                stats[tex, 0] = skipped
                stats[tex, 1] = compressed

    @njit(parallel=True)
    def lookup(D, V, texel, depth, out):
        """Linear interpolation between the bracketing nodes (kernel's ``interpolate``)."""
        N = D.shape[1]
        for r in prange(texel.size):
            tx, x = texel[r], depth[r]
            dl, tl, dr, tr = x, 1.0, x, 1.0
            for k in range(N):
                if D[tx, k] <= x:
                    nxt = min(k + 1, N - 1)
                    dl, tl, dr, tr = D[tx, k], V[tx, k], D[tx, nxt], V[tx, nxt]
            dd = dr - dl
            w = (x - dl) / (dd if dd > 0 else 1.0)
            w = min(max(w, 0.0), 1.0)
            out[r] = tl + w * (tr - tl)

    _KERNELS.update(build=build, lookup=lookup)
    return _KERNELS


def build(offsets, z0, z1, tau, nodes: int, far: float, sort: bool = False):
    """AVSM nodes of every texel.

    offsets: (T+1,) CSR; z0, z1, tau: (S,) float64 segment entry/exit depths and optical
    depths (a texel's segments inserted in the given order; ``sort=True`` expects them
    sorted by depth and stops a texel behind its first fully opaque point).
    nodes: N >= 2; far: depth of the clear nodes.
    Returns (D, V, used, stats): (T, N) node depths and transmittances (float64), (T,)
    inserted nodes kept, and dict(skipped=, compressed=) totals as in ``AVSM.stats``.
    """
    K = _kernels()
    offsets = np.ascontiguousarray(offsets, np.int64)
    z0 = np.ascontiguousarray(z0, np.float64)
    z1 = np.ascontiguousarray(z1, np.float64)
    ts = np.exp(-np.asarray(tau, np.float64))
    T, N = offsets.size - 1, int(nodes)
    if N < 2:
        raise ValueError(f"nodes: expected an integer >= 2, got {nodes!r}")
    D = np.empty((T, N))
    V = np.empty((T, N))
    used = np.zeros(T, np.int64)
    stats = np.zeros((T, 2), np.int64)
    if T:
        t0 = time.perf_counter()
        K["build"](offsets, z0, z1, ts, N, float(far), bool(sort), D, V, used, stats)
        _COMPILE_S.setdefault("build", time.perf_counter() - t0)
    return D, V, used, {"skipped": int(stats[:, 0].sum()), "compressed": int(stats[:, 1].sum())}


def lookup(D, V, texel, depth) -> np.ndarray:
    """Transmittance at receivers (texel, depth): linear interpolation between nodes."""
    K = _kernels()
    texel = np.ascontiguousarray(texel, np.int64)
    depth = np.ascontiguousarray(depth, np.float64)
    out = np.empty(texel.size)
    t0 = time.perf_counter()
    K["lookup"](np.ascontiguousarray(D), np.ascontiguousarray(V), texel, depth, out)
    _COMPILE_S.setdefault("lookup", time.perf_counter() - t0)
    return out

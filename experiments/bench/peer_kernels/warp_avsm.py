"""AVSM in NVIDIA Warp: the peer a researcher who picks Warp instead of Dr.Jit would write
(one Warp thread per chunk of texels, scalar code per texel, node lists in a per-chunk
scratch array), on Warp's ``cpu`` device.

Same algorithm, conventions and floating-point expression order as
:mod:`.numba_avsm` (Salvi et al., "Adaptive Volumetric Shadow Maps", EGSR 2010,
sec. 3.1-3.3; see that module for the insertion and compression rules), in float64 like
the Numba peer, so node depths equal the kernel's and values agree to rounding
(``tests/test_peers.py``).  Warp runs a CPU launch serially on one thread (its
documented CPU execution model), so on a multi-core machine its wall time carries the
cores it leaves idle; ``bench`` also reports the CPU-time ratio.

Warp is optional (the ``bench`` extra): importing this module never needs it.  The
kernels are compiled on the first call (:func:`compile_seconds`; cached on disk by Warp).
"""
# no ``from __future__ import annotations``: Warp reads the kernels' annotations as types
import time

import numpy as np

from ._warp import int32_array as _int32, require as _require_warp, warp as wp

_KERNELS: dict = {}
_COMPILE_S: dict = {}
#: texel chunks per launch (one Warp thread each, one scratch row each)
CHUNKS = 4096


def available() -> bool:
    """True when Warp can be imported."""
    return wp is not None


def compile_seconds() -> dict:
    """Seconds spent loading (compiling, or reading from Warp's cache) the kernel module on
    the first call (``{'module': s}``): build and lookup share one module."""
    return dict(_COMPILE_S)


def _kernels() -> dict:
    """The Warp kernels, created on first use (so that importing needs no Warp)."""
    if _KERNELS:
        return _KERNELS
    _require_warp(wp, __name__)
    f64 = wp.float64
    Arr1 = wp.array(dtype=wp.float64)
    Arr2 = wp.array2d(dtype=wp.float64)

    @wp.func
    def curve(d: Arr2, t: Arr2, c: int, n: int, x: wp.float64) -> wp.float64:
        """T(x) of the first n nodes of row c: t_l + (x - d_l)(t_r - t_l) / (d_r - d_l)."""
        dl = x
        tl = f64(1.0)
        dr = x
        tr = f64(1.0)
        for k in range(n):
            if d[c, k] <= x:
                nxt = wp.min(k + 1, n - 1)
                dl = d[c, k]
                tl = t[c, k]
                dr = d[c, nxt]
                tr = t[c, nxt]
        dd = dr - dl
        if not (dd > f64(0.0)):
            dd = f64(1.0)
        return tl + (x - dl) * (tr - tl) / dd

    @wp.func
    def remove_smallest(d: Arr2, t: Arr2, c: int, n: int):
        """Remove the interior node of smallest area metric from the first n (ties: deepest)."""
        best = wp.abs((d[c, 2] - d[c, 0]) * (t[c, 2] - t[c, 1]) - (d[c, 2] - d[c, 1]) * (t[c, 2] - t[c, 0]))
        idx = int(1)
        for i in range(2, n - 1):
            m = wp.abs((d[c, i + 1] - d[c, i - 1]) * (t[c, i + 1] - t[c, i])
                       - (d[c, i + 1] - d[c, i]) * (t[c, i + 1] - t[c, i - 1]))
            if m <= best:
                best = m
                idx = i
        for j in range(idx, n - 1):
            d[c, j] = d[c, j + 1]
            t[c, j] = t[c, j + 1]

    @wp.kernel
    def build(offsets: wp.array(dtype=wp.int32), z0: Arr1, z1: Arr1, ts: Arr1, N: int, far: wp.float64,
              sort: int, n_chunks: int, d: Arr2, t: Arr2, D: Arr2, V: Arr2,
              used_out: wp.array(dtype=wp.int32), stats: wp.array2d(dtype=wp.int32)):
        """Thread c: texels [c T / n_chunks, (c + 1) T / n_chunks); d, t: (n_chunks, N + 2) scratch."""
        c = wp.tid()
        T = offsets.shape[0] - 1
        for tex in range(c * T // n_chunks, (c + 1) * T // n_chunks):
            for k in range(N):
                d[c, k] = far
                t[c, k] = f64(1.0)
            used = int(0)
            skipped = int(0)
            compressed = int(0)
            start = offsets[tex]
            end = offsets[tex + 1]
            for s in range(start, end):
                a = z0[s]
                b = z1[s]
                tsv = ts[s]
                ta = curve(d, t, c, N, a)
                if ta == f64(0.0):               # behind a fully opaque point
                    skipped += 1
                    if sort != 0:
                        skipped += end - s - 1
                        break
                    continue
                tb = curve(d, t, c, N, b) * tsv
                length = b - a
                if not (length > f64(0.0)):
                    length = f64(1.0)
                inv_len = f64(1.0) / length
                e = int(0)                        # slot of the entry node
                x = int(1)                        # slot of the exit node
                for k in range(N):
                    if k < used:
                        dk = d[c, k]
                        if dk <= a:
                            e += 1
                        if dk <= b:
                            x += 1
                        if dk > a:
                            if dk >= b:
                                t[c, k] = t[c, k] * tsv
                            else:
                                t[c, k] = t[c, k] * (f64(1.0) + (tsv - f64(1.0)) * ((dk - a) * inv_len))
                    else:                         # clear nodes take the full ts
                        t[c, k] = t[c, k] * tsv
                for jj in range(N + 2):           # merge in place, from the back
                    j = N + 1 - jj
                    if j == x:
                        d[c, j] = b
                        t[c, j] = tb
                    elif j == e:
                        d[c, j] = a
                        t[c, j] = ta
                    else:
                        sh = int(0)
                        if e < j:
                            sh += 1
                        if x < j:
                            sh += 1
                        d[c, j] = d[c, j - sh]
                        t[c, j] = t[c, j - sh]
                if used + 2 <= N:                 # room: the two last (clear) nodes drop out
                    used += 2
                else:
                    remove_smallest(d, t, c, N + 2)
                    remove_smallest(d, t, c, N + 1)
                    compressed += 1
            for k in range(N):
                D[tex, k] = d[c, k]
                V[tex, k] = t[c, k]
            used_out[tex] = used
            stats[tex, 0] = skipped
            stats[tex, 1] = compressed

    @wp.kernel
    def lookup(D: Arr2, V: Arr2, texel: wp.array(dtype=wp.int32), depth: Arr1, out: Arr1):
        """Linear interpolation between the bracketing nodes (kernel's ``interpolate``)."""
        r = wp.tid()
        N = D.shape[1]
        tx = texel[r]
        x = depth[r]
        dl = x
        tl = f64(1.0)
        dr = x
        tr = f64(1.0)
        for k in range(N):
            if D[tx, k] <= x:
                nxt = wp.min(k + 1, N - 1)
                dl = D[tx, k]
                tl = V[tx, k]
                dr = D[tx, nxt]
                tr = V[tx, nxt]
        dd = dr - dl
        if not (dd > f64(0.0)):
            dd = f64(1.0)
        w = wp.min(wp.max((x - dl) / dd, f64(0.0)), f64(1.0))
        out[r] = tl + w * (tr - tl)

    t0 = time.perf_counter()
    wp.load_module(build.module, device="cpu")
    _COMPILE_S["module"] = time.perf_counter() - t0
    _KERNELS.update(build=build, lookup=lookup)
    return _KERNELS


def build(offsets, z0, z1, tau, nodes: int, far: float, sort: bool = False):
    """AVSM nodes of every texel; arguments and results as :func:`.numba_avsm.build`.

    offsets: (T+1,) CSR; z0, z1, tau: (S,) float64 segment entry/exit depths and optical
    depths; nodes: N >= 2; far: depth of the clear nodes.  Returns (D, V, used, stats):
    (T, N) float64 node depths and transmittances, (T,) inserted nodes kept, and
    dict(skipped=, compressed=) totals."""
    T, N = np.asarray(offsets).size - 1, int(nodes)
    if N < 2:
        raise ValueError(f"nodes: expected an integer >= 2, got {nodes!r}")
    K = _kernels()
    offsets = _int32(offsets, "offsets")
    ts = np.exp(-np.asarray(tau, np.float64))
    D = np.empty((T, N))
    V = np.empty((T, N))
    used = np.zeros(T, np.int32)
    stats = np.zeros((T, 2), np.int32)
    if T:
        n_chunks = min(T, CHUNKS)
        scratch_d = wp.empty((n_chunks, N + 2), dtype=wp.float64, device="cpu")
        scratch_t = wp.empty((n_chunks, N + 2), dtype=wp.float64, device="cpu")
        arr = [wp.array(x, copy=False, device="cpu") for x in
               (offsets, np.ascontiguousarray(z0, np.float64), np.ascontiguousarray(z1, np.float64), ts)]
        out = [wp.array(x, copy=False, device="cpu") for x in (D, V, used, stats)]   # views of the NumPy outputs
        wp.launch(K["build"], dim=n_chunks, device="cpu",
                  inputs=[*arr, N, float(far), int(bool(sort)), n_chunks, scratch_d, scratch_t, *out])
        wp.synchronize_device("cpu")
    return D, V, used.astype(np.int64), {"skipped": int(stats[:, 0].sum()), "compressed": int(stats[:, 1].sum())}


def lookup(D, V, texel, depth) -> np.ndarray:
    """Transmittance at receivers (texel, depth): linear interpolation between nodes."""
    K = _kernels()
    texel = _int32(texel, "texel")
    depth = np.ascontiguousarray(depth, np.float64)
    out = np.empty(texel.size)
    if texel.size:
        args = [wp.array(np.ascontiguousarray(x, np.float64), copy=False, device="cpu") for x in (D, V)]
        wp.launch(K["lookup"], dim=texel.size, device="cpu",
                  inputs=[*args, wp.array(texel, copy=False, device="cpu"),
                          wp.array(depth, copy=False, device="cpu"), wp.array(out, copy=False, device="cpu")])
        wp.synchronize_device("cpu")
    return out

"""The exact transmittance curve as points per texel, for the kinds that choose their nodes
from it (``greedy``, ``optimal``, ``avsm_march``), and their helpers (gradients of stored
curve values, texel buckets for padded NumPy work, a per-segments cache, node lists).

Between the texel's sorted unique segment ends ("breakpoints") ``T = exp(-tau)`` is exactly
exponential; a zero-length segment is a step.  Per breakpoint ``z_k`` the points are
``(z_k, T(z_k^-))`` when a step sits there (the *left* point), then ``(z_k, T(z_k))``, with
the slope ``s_k = d tau / dz`` after it: ``T(x) = T_p exp(-s_p (x - z_p))`` up to the next
point.  Breakpoints, optical depths and slopes: :mod:`._dsm_polyline` (float64).
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from .. import backend
from ._dsm_polyline import breakpoints, prefix_optical_depth
from .exact import exact_values


def curve_points(segments) -> dict:
    """Points of every texel's exact curve (host float64 NumPy): dict of ``off`` (T+1,) CSR
    and per point ``z``, ``tau``, ``v`` (``exp(-tau)``), ``slope`` (d tau / dz after it; a
    left point's: its right point's), ``left`` (value just before a step), ``texel``."""
    h = segments.numpy()
    return host_curve_points(h["offsets"], h["z0"], h["z1"], h["optical_depth"])


def host_curve_points(offsets, z0, z1, tau) -> dict:
    """:func:`curve_points` of CSR segments given as host float64 arrays (a texel's points
    depend only on its own segments: any run of whole texels gives the same points)."""
    n_tex = offsets.size - 1
    if z0.size == 0:
        e = np.zeros(0)
        return dict(off=np.zeros(n_tex + 1, np.int64), z=e, tau=e, v=e, slope=e,
                    left=np.zeros(0, bool), texel=np.zeros(0, np.int64))
    bp = breakpoints(offsets, z0, z1, tau)
    tl, tr, slope = (np.asarray(x.numpy(), np.float64) for x in prefix_optical_depth(bp))
    step = bp["jump"] > 0
    per_bp = 1 + step.astype(np.int64)
    first = np.concatenate([[0], np.cumsum(per_bp)])[:-1]      # slot of each breakpoint's first point
    z = np.repeat(bp["z"], per_bp)
    tau = np.repeat(np.where(step, tl, tr), per_bp)            # a step's points: tau_left, tau_right
    tau[first[step] + 1] = tr[step]
    left = np.zeros(z.size, bool)
    left[first[step]] = True
    texel = np.repeat(np.repeat(np.arange(n_tex), np.diff(bp["off"])), per_bp)
    off = np.concatenate([[0], np.cumsum(np.bincount(texel, minlength=n_tex))]).astype(np.int64)
    return dict(off=off, z=z, tau=tau, v=np.exp(-tau), slope=np.repeat(slope, per_bp), left=left, texel=texel)


def attach_exact_gradients(segments, value, texel, z, left):
    """``value + (V - detach(V))`` with ``V`` = :func:`exact_values`: the primal stays
    ``value`` (a Dr.Jit Float), the gradient is that of the exact curve at the fixed
    depths ``z``.  Returns ``value`` unchanged when the segments carry no gradients."""
    if not segments.requires_grad or np.size(z) == 0:
        return value
    v = exact_values(segments, np.asarray(texel), np.asarray(z), np.asarray(left))
    return value + (v - dr.detach(v))


def buckets(off: np.ndarray, max_elems: int = 1 << 22, power: int = 2):
    """Groups of non-empty texels of similar point count K (same power of two), each
    small enough that ``len(group) * Kmax**power <= max_elems``: yields
    ``(texels, Kmax)``."""
    counts = np.diff(off)
    tex = np.flatnonzero(counts > 0)
    if tex.size == 0:
        return
    key = np.ceil(np.log2(np.maximum(counts[tex], 1))).astype(np.int64)
    for b in np.unique(key):
        group = tex[key == b]
        kmax = int(counts[group].max())
        step = max(1, max_elems // max(1, kmax ** power))
        for s in range(0, group.size, step):
            yield group[s:s + step], kmax


def padded(off: np.ndarray, texels: np.ndarray, kmax: int, *arrays):
    """(B, kmax) blocks of per-point ``arrays`` for ``texels``, each row padded with its
    texel's last point; also returns the (B,) point counts."""
    start = off[texels]
    count = off[texels + 1] - start
    idx = start[:, None] + np.minimum(np.arange(kmax)[None, :], count[:, None] - 1)
    return count, [a[idx] for a in arrays]


def points(segments) -> dict:
    """:func:`curve_points`, computed once per segments (:func:`cached`)."""
    return cached(segments, "curve_points", lambda: curve_points(segments))


def cached(segments, key: str, fn):
    """``fn()`` computed once per :class:`~avsm_dr.Segments` (kept in its cache: the
    points and the offline orders depend only on the segments' values)."""
    store = segments._cache
    if key not in store:
        store[key] = fn()
    return store[key]


def fill_slots(sel_tex: np.ndarray, sel_pt: np.ndarray, slot: np.ndarray, N: int, T: int, fill=-1) -> np.ndarray:
    """(N, T) point index (or value: ``sel_pt``'s dtype) of every node slot from the chosen
    points (texel, point, slot; slots 0..count-1 per texel in depth order): slots beyond a
    texel's count repeat its last node (duplicates change no lookup); ``fill`` for empty texels."""
    src = np.full((N, T), fill, np.asarray(sel_pt).dtype)
    src[slot, sel_tex] = sel_pt
    count = np.bincount(sel_tex, minlength=T)
    nz = np.flatnonzero(count > 0)
    last = src[count[nz] - 1, nz]
    for k in range(N):
        more = count[nz] <= k
        src[k, nz[more]] = last[more]
    return src


def exp_stored_values(v, store):
    """Node values as the offline kinds store them for exponential interpolation: 0 where
    ``store`` (np.float32 / np.float64) rounds the value to 0, else at least its smallest
    normal ``tiny``: the lookup never takes the log of a denormal (Dr.Jit's LLVM log is
    inexact there), so the DP's chords are the lookup's exactly."""
    v = np.asarray(v, np.float64)
    return np.where(v.astype(store) == 0, 0.0, np.maximum(v, np.finfo(store).tiny))


def store_nodes(segments, src: np.ndarray, pts: dict, values: np.ndarray | None = None, exp: bool = False):
    """Node lists (N Dr.Jit Floats of length T) from the (N, T) point indices ``src``
    (:func:`fill_slots`): depths ``z[src]``, values ``values`` (default: the exact values
    ``v[src]``, with the exact curve's gradients attached; ``exp``: as
    :func:`exp_stored_values`); empty texels hold (0, 1)."""
    N, T = src.shape
    dt = segments.dtype
    if exp and values is None:
        pts = {**pts, "v": exp_stored_values(pts["v"], dt)}
    Float = segments.Float
    has = src >= 0
    s = np.maximum(src, 0)
    d = np.where(has, pts["z"][s] if pts["z"].size else 0.0, 0.0)
    t = np.where(has, (pts["v"][s] if pts["v"].size else 1.0) if values is None else values, 1.0)
    depths = [Float(d[k].astype(dt)) for k in range(N)]
    if values is not None or not segments.requires_grad or not has.any():
        return depths, [Float(t[k].astype(dt)) for k in range(N)]
    # gradients of the exact curve at each node's fixed depth (one lane per stored node)
    UInt32 = backend.types().UInt32
    flat = np.flatnonzero(has.ravel())
    p = src.ravel()[flat]
    g = attach_exact_gradients(segments, dr.zeros(Float, flat.size), pts["texel"][p], pts["z"][p], pts["left"][p])
    grad = dr.zeros(Float, N * T)
    dr.scatter(grad, g, UInt32(flat.astype(np.uint32)))
    allv = Float(t.ravel().astype(dt)) + grad
    return depths, [dr.gather(Float, allv, dr.arange(UInt32, T) + k * T) for k in range(N)]

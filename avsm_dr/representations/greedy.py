"""Offline greedy: Visvalingam-Whyatt simplification of the exact curve (Visvalingam and
Whyatt 1993, "Line generalisation by repeated elimination of points", The Cartographic
Journal 30(1)) with AVSM's removal metric and tie rule (Salvi et al. 2010, sec. 3.2), run on
the whole exact curve at once (its points, :mod:`._curve`) instead of while streaming: the
smallest-metric interior point is removed and its neighbours' metrics updated until N remain,
the first and last point kept (experiment ``avsm_gap``: streaming vs greed).

The removal order does not depend on N: computed once per segments (cached), ``nodes=N``
keeps the N points removed last.  Host float64: texels up to :data:`HEAP_POINTS` points
vectorised (O(K^2) per texel), larger ones with a heap (O(K log K); identical ranks).  Node
values are the exact curve's (:func:`._curve.store_nodes`), with its gradients at the fixed
node depths; lookup as AVSM's.
"""
from __future__ import annotations

import numpy as np

from . import _curve
from .avsm import INTERPOLATION, NODES, NodeList
from .registry import register
from .schema import Schema


def vw_removal_rank(x: np.ndarray, v: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Visvalingam-Whyatt removal step of every point of a (B, K) padded block of curves
    (rows: points sorted by depth, ``count`` real points each).

    Returns (B, K) int64: the step at which each interior point is removed (0 first);
    the first and last point and padding get ``K``.  Metric: AVSM's area metric with the
    current neighbours (an overflow counts as the largest float, NaN as the smallest, as
    ``np.argmin`` has it); ties: the deepest point (highest index)."""
    B, K = x.shape
    rows = np.arange(B)
    cols = np.arange(K)
    prev = np.broadcast_to(cols - 1, (B, K)).copy()
    nxt = np.broadcast_to(cols + 1, (B, K)).copy()
    rank = np.full((B, K), K, np.int64)
    interior = (cols[None, :] >= 1) & (cols[None, :] < count[:, None] - 1)

    def metric(r, p, i, q):
        # an overflow to inf is clamped to the largest float: inf marks removed points
        a = np.abs((x[r, q] - x[r, p]) * (v[r, q] - v[r, i]) - (x[r, q] - x[r, i]) * (v[r, q] - v[r, p]))
        return np.minimum(a, BIG)

    area = np.full((B, K), np.inf)
    ri, ci = np.nonzero(interior)
    area[ri, ci] = metric(ri, ci - 1, ci, ci + 1)
    n_interior = np.maximum(count - 2, 0)
    for step in range(int(n_interior.max(initial=0))):
        r = rows[n_interior > step]
        # the last minimum: ties go to the deepest node, as in AVSM
        i = K - 1 - np.argmin(area[r, ::-1], axis=1)
        rank[r, i] = step
        area[r, i] = np.inf
        p, q = prev[r, i], nxt[r, i]
        nxt[r, p] = q
        prev[r, q] = p
        for j in (p, q):                       # the neighbours' new areas (interior ones)
            upd = (j >= 1) & (j < count[r] - 1)
            rj, jj = r[upd], j[upd]
            area[rj, jj] = metric(rj, prev[rj, jj], jj, nxt[rj, jj])
    return rank


#: Areas that overflow count as this (the scan marks removed points with inf).
BIG = np.finfo(np.float64).max
#: Texels with more points than this use the heap (:func:`vw_removal_rank_heap`), smaller
#: ones the vectorised O(K^2) scan (faster per texel there).
HEAP_POINTS = 1024


def vw_removal_rank_heap(x, v, n: int) -> np.ndarray:
    """:func:`vw_removal_rank` of one curve of ``n`` points (1-D float64 ``x``, ``v``), in
    O(n log n): a binary heap with lazy deletion, keys ``bits(area) << S | (2^S - 1 -
    index)`` (the IEEE pattern, monotone for areas >= 0; NaN first, overflow :data:`BIG`):
    the scan's order and float64 operations, identical ranks."""
    import heapq
    import struct

    n = int(n)
    x, v = np.asarray(x, np.float64)[:n], np.asarray(v, np.float64)[:n]
    rank = np.full(n, n, np.int64)
    if n < 3:
        return rank
    S = n.bit_length()
    M = (1 << S) - 1
    pack, unpack = struct.Struct("<d").pack, struct.Struct("<q").unpack

    def bits(a):
        return (unpack(pack(a if a < BIG else BIG))[0]) if a == a else -1

    with np.errstate(all="ignore"):            # overflows: inf (clamped) or NaN, as in the scan
        a0 = np.abs((x[2:] - x[:-2]) * (v[2:] - v[1:-1]) - (x[2:] - x[1:-1]) * (v[2:] - v[:-2]))
    b0 = np.where(np.isnan(a0), -1, np.minimum(a0, BIG).view(np.int64))
    cur = [0, *b0.tolist(), 0]                 # current area bits per point
    heap = [(b << S) | (M - i) for i, b in enumerate(cur[1:-1], 1)]
    heapq.heapify(heap)
    xs, vs = x.tolist(), v.tolist()
    prev, nxt = list(range(-1, n - 1)), list(range(1, n + 1))
    removed = [False] * n
    pop, push = heapq.heappop, heapq.heappush
    for step in range(n - 2):
        while True:
            k = pop(heap)
            i = M - (k & M)
            if not removed[i] and k >> S == cur[i]:
                break
        removed[i] = True
        rank[i] = step
        p, q = prev[i], nxt[i]
        nxt[p] = q
        prev[q] = p
        for j in (p, q):                       # the neighbours' new areas (interior ones)
            if 1 <= j < n - 1:
                o, r = prev[j], nxt[j]
                cur[j] = b = bits(abs((xs[r] - xs[o]) * (vs[r] - vs[j]) - (xs[r] - xs[j]) * (vs[r] - vs[o])))
                push(heap, (b << S) | (M - j))
    return rank


def removal_ranks(segments) -> tuple[dict, np.ndarray]:
    """The segments' curve points (:func:`._curve.curve_points`) and the VW removal step
    of each point (first / last point of a texel: its point count), cached."""
    def compute():
        pts = _curve.points(segments)
        off = pts["off"]
        rank = np.zeros(pts["z"].size, np.int64)
        for tex, kmax in _curve.buckets(off, power=1):
            if kmax > HEAP_POINTS:
                for t in tex:
                    s = slice(off[t], off[t + 1])
                    rank[s] = vw_removal_rank_heap(pts["z"][s], pts["v"][s], off[t + 1] - off[t])
                continue
            count, (x, v) = _curve.padded(off, tex, kmax, pts["z"], pts["v"])
            r = vw_removal_rank(x, v, count)
            cols = np.arange(kmax)
            real = cols[None, :] < count[:, None]
            idx = off[tex][:, None] + cols[None, :]
            rank[idx[real]] = np.minimum(r, count[:, None])[real]
        return pts, rank
    return _curve.cached(segments, "vw_removal_rank", compute)


@register("greedy")
class GreedyVW(NodeList):
    """Offline Visvalingam-Whyatt on the exact curve (module docstring): N nodes per texel
    (fewer points: the last repeated), 2 N itemsize; ``node_counts`` (T,) distinct nodes."""

    schema = Schema(
        params=(
            NODES, INTERPOLATION,
        ),
        size="nodes", sweep=(2, 4, 6, 8, 12, 16, 24, 32), quick_sweep=(2, 4, 8, 16),
        examples=({"nodes": 4}, {"nodes": 8, "interpolation": "exp"}),
        headline={"nodes": 8},
        summary="offline Visvalingam-Whyatt on the exact curve (AVSM's metric, whole curve known)",
        paper="Visvalingam & Whyatt 1993", offline=True)

    def _build(self):
        segments = self.segments
        pts, rank = removal_ranks(segments)
        sel = np.flatnonzero(rank >= np.diff(pts["off"])[pts["texel"]] - self.N)     # the N removed last
        tex = pts["texel"][sel]
        node_off = np.concatenate([[0], np.cumsum(np.bincount(tex, minlength=segments.n_texels))])
        self.node_counts = np.diff(node_off)
        src = _curve.fill_slots(tex, sel, np.arange(sel.size) - node_off[tex], self.N, segments.n_texels)
        self.depths, self.values = _curve.store_nodes(segments, src, pts, exp=self.params["interpolation"] == "exp")

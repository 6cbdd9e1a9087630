"""Offline greedy: Visvalingam-Whyatt simplification of the exact curve (Visvalingam and
Whyatt 1993, "Line generalisation by repeated elimination of points", The Cartographic
Journal 30(1)), with AVSM's removal metric and tie rule.

AVSM (Salvi et al. 2010, sec. 3.2) removes, while a texel holds more than N nodes, the
interior node of smallest area metric ``|(d[i+1]-d[i-1])(t[i+1]-t[i]) - (d[i+1]-d[i])
(t[i+1]-t[i-1])|`` (ties: the deepest), *while streaming* the segments in.  This kind
runs the same removal on the whole exact curve at once: the nodes start as the curve's
points (:mod:`._curve`: segment ends with the exact curve's values; a zero-length
segment gives two nodes at one depth, before and after its step, as in AVSM) and the
smallest-metric interior node is removed, the metrics of its two neighbours updated,
until N remain; the first and last point stay.  It separates what AVSM loses by
streaming from what it loses by being greedy (the ``avsm_gap`` experiment).

The removal order does not depend on N, so it is computed once per segments (to the
last interior point; cached) and ``nodes=N`` keeps the N points removed last.  Host
NumPy, float64, vectorised over texels of similar point count (O(K^2) per texel of K
points: one argmin over the texel's points per removal).  Node values are the exact
curve's; their gradients w.r.t. the optical depths are those of the exact curve at
the fixed node depths.  Lookup as AVSM (:func:`.avsm.interpolate`).
"""
from __future__ import annotations

import numpy as np

from . import _curve
from .avsm import INTERPOLATIONS, NodeList
from .registry import register
from .schema import Param, Schema


def vw_removal_rank(x: np.ndarray, v: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Visvalingam-Whyatt removal step of every point of a (B, K) padded block of curves
    (rows: points sorted by depth, ``count`` real points each).

    Returns (B, K) int64: the step at which each interior point is removed (0 first);
    the first and last point and padding get ``K``.  Metric: AVSM's area metric with the
    current neighbours; ties: the deepest point (highest index)."""
    B, K = x.shape
    rows = np.arange(B)
    cols = np.arange(K)
    prev = np.broadcast_to(cols - 1, (B, K)).copy()
    nxt = np.broadcast_to(cols + 1, (B, K)).copy()
    rank = np.full((B, K), K, np.int64)
    interior = (cols[None, :] >= 1) & (cols[None, :] < count[:, None] - 1)

    def metric(r, p, i, q):
        return np.abs((x[r, q] - x[r, p]) * (v[r, q] - v[r, i]) - (x[r, q] - x[r, i]) * (v[r, q] - v[r, p]))

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
        upd = p >= 1
        rp, pp = r[upd], p[upd]
        area[rp, pp] = metric(rp, prev[rp, pp], pp, q[upd])
        upd = q < count[r] - 1
        rq, qq = r[upd], q[upd]
        area[rq, qq] = metric(rq, p[upd], qq, nxt[rq, qq])
    return rank


def removal_ranks(segments) -> tuple[dict, np.ndarray]:
    """The segments' curve points (:func:`._curve.curve_points`) and the VW removal step
    of each point (first / last point of a texel: its point count), cached."""
    def compute():
        pts = _curve.cached(segments, "curve_points", lambda: _curve.curve_points(segments))
        off = pts["off"]
        rank = np.zeros(pts["z"].size, np.int64)
        for tex, kmax in _curve.buckets(off, power=1):
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
    """Offline Visvalingam-Whyatt on the exact curve: N (depth, transmittance) nodes per
    texel (see the module docstring).

    Parameters: nodes N in [2, 64]; interpolation 'linear' (default, as AVSM) or 'exp'.
    ``nbytes_per_texel`` = 2 N itemsize (texels with fewer points repeat their last node).
    Attributes: ``depths``/``values`` (N Dr.Jit arrays of length T), ``node_counts``
    (T,) distinct nodes kept per texel.
    """

    schema = Schema(
        params=(
            Param("nodes", "int", 8, "N nodes (depth, transmittance) per texel", min=2, max=64),
            Param("interpolation", "choice", "linear", "between nodes: 'linear' or 'exp' (as AVSM)",
                  choices=INTERPOLATIONS),
        ),
        size="nodes", sweep=(2, 4, 6, 8, 12, 16, 24, 32), quick_sweep=(2, 4, 8, 16),
        examples=({"nodes": 4}, {"nodes": 8, "interpolation": "exp"}),
        headline={"nodes": 8},
        summary="offline Visvalingam-Whyatt on the exact curve (AVSM's metric, whole curve known)",
        paper="Visvalingam & Whyatt 1993", offline=True,
    )

    def __init__(self, segments, **params):
        super().__init__(segments, **params)
        self.N = self.params["nodes"]
        pts, rank = removal_ranks(segments)
        off = pts["off"]
        count = np.diff(off)[pts["texel"]]
        keep = rank >= count - self.N
        sel = np.flatnonzero(keep)
        tex = pts["texel"][sel]
        node_off = np.concatenate([[0], np.cumsum(np.bincount(tex, minlength=segments.n_texels))])
        slot = np.arange(sel.size) - node_off[tex]
        self.node_counts = np.diff(node_off)
        src = _curve.fill_slots(tex, sel, slot, self.N, segments.n_texels)
        self.depths, self.values = _curve.store_nodes(segments, src, pts)

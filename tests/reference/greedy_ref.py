"""The previous ``greedy`` removal order, kept as the slow reference for the heap
(avsm_dr/representations/greedy.py before it used a heap): Visvalingam-Whyatt with AVSM's
area metric on a (B, K) padded block, one argmin over every point per removal (O(K^2)
per texel).  Ties: the deepest point; a NaN area first (``np.argmin``)."""
from __future__ import annotations

import numpy as np


def vw_removal_rank(x: np.ndarray, v: np.ndarray, count: np.ndarray) -> np.ndarray:
    """(B, K) int64 removal step of every interior point (0 first); first / last point
    and padding get ``K``."""
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

"""Adaptive AVSM under a byte budget in plain float64 Python (checks avsm_adaptive.py):
the complexity score per texel, water-filling one upgrade at a time from a heap, and AVSM
per texel with its own node count (tests/reference/avsm_ref.py), stored compacted."""
from __future__ import annotations

import heapq
import math

import numpy as np

from . import avsm_ref

LADDER = (2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64)


def texel_options(c: int, max_nodes: int) -> list[int]:
    """Node counts a texel with c segments may get: ladder values (capped at max_nodes)
    below K = 2c, and K when K <= max_nodes."""
    K = 2 * c
    lad = [n for n in LADDER if n < max_nodes] + [max_nodes]
    out = [n for n in lad if n < K]
    if K <= max_nodes:
        out.append(K)
    return sorted(out) if c else []


def error(n: int, K: int, w: float) -> float:
    """Modelled squared error w (1/n^2 - 1/K^2)^+."""
    return w * max(1.0 / (n * n) - 1.0 / (K * K), 0.0)


def complexity(offsets, z0, z1, tau) -> list[float]:
    """span (1 - exp(-sum tau))^2 per texel (0 when empty)."""
    out = []
    for k in range(len(offsets) - 1):
        s = slice(offsets[k], offsets[k + 1])
        if offsets[k + 1] == offsets[k]:
            out.append(0.0)
            continue
        span = float(np.max(z1[s]) - np.min(z0[s]))
        out.append(span * math.expm1(-float(np.sum(tau[s]))) ** 2)
    return out


def allocate(counts, weight, budget_nodes: int, max_nodes: int) -> list[int]:
    """Start at each texel's least option; pop the upgrade with the largest gain per node
    (ties: lower texel, then smaller n) while it fits the budget; stop at the first that
    does not fit; upgrades with no gain are never taken."""
    opts = [texel_options(int(c), max_nodes) for c in counts]
    level = [0] * len(counts)
    n = [o[0] if o else 0 for o in opts]
    left = budget_nodes - sum(n)
    heap = []

    def push(t):
        o = opts[t]
        if level[t] + 1 < len(o):
            a, b = o[level[t]], o[level[t] + 1]
            K = 2 * int(counts[t])
            g = (error(a, K, weight[t]) - error(b, K, weight[t])) / (b - a)
            if g > 0:
                heapq.heappush(heap, (-g, t, a, b))

    for t in range(len(counts)):
        push(t)
    while heap:
        g, t, a, b = heapq.heappop(heap)
        if b - a > left:
            break
        left -= b - a
        n[t] = b
        level[t] += 1
        push(t)
    return n


def kernel(n: int, c: int, max_nodes: int) -> int:
    """AVSM N run for an allocation n: n below K = 2c, else the least ladder value >= K."""
    if n == 0:
        return 0
    if n < 2 * c:
        return n
    lad = [m for m in LADDER if m < max_nodes] + [max_nodes]
    return min(m for m in lad if m >= 2 * c)


def texel_nodes(z0, z1, tau, N: int, far: float, sort: bool, store_all: bool):
    """Stored (depths, values) of one texel: AVSM-N (avsm_ref), all N nodes when
    ``store_all`` (compressing), else only the inserted (non-clear) ones."""
    order = np.lexsort((z1, z0)) if sort else np.arange(len(z0))
    nodes = [(far, 1.0, True)] * N
    for s in order:
        a, b, ts = float(z0[s]), float(z1[s]), float(np.exp(-tau[s]))
        if avsm_ref.curve(nodes, a) == 0.0:
            if sort:
                break
            continue
        nodes = avsm_ref.compress(avsm_ref.insert(nodes, a, b, ts), N)
    keep = nodes if store_all else [p for p in nodes if not p[2]]
    return np.array([p[0] for p in keep]), np.array([p[1] for p in keep])


def build(offsets, z0, z1, tau, bytes_per_texel: float, itemsize: int, max_nodes: int = 32,
          sort: bool = False, far: float | None = None):
    """(allocation, list of per-texel (depths, values), nbytes_per_texel)."""
    T = len(offsets) - 1
    counts = np.diff(offsets)
    budget = int((bytes_per_texel * T - 4 * (T + 1)) // (2 * itemsize))
    alloc = allocate(counts, complexity(offsets, z0, z1, tau), budget, max_nodes)
    far = float(np.max(z1)) if far is None else far
    nodes = []
    for k in range(T):
        s = slice(offsets[k], offsets[k + 1])
        if counts[k] == 0:
            nodes.append((np.zeros(0), np.zeros(0)))
            continue
        N = kernel(alloc[k], int(counts[k]), max_nodes)
        nodes.append(texel_nodes(z0[s], z1[s], tau[s], N, far, sort, alloc[k] < 2 * counts[k]))
    total = sum(d.size for d, _ in nodes)
    return alloc, nodes, (4 * (T + 1) + 2 * itemsize * total) / T


def sample(nodes, texel: int, x: float, mode: str = "linear") -> float:
    """T of texel ``texel`` at depth x (1 for an empty texel)."""
    d, v = nodes[texel]
    return 1.0 if d.size == 0 else avsm_ref.sample(d, v, x, mode)

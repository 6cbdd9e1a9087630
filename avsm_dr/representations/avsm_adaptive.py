"""Adaptive AVSM under a memory budget: a total byte budget for the whole map, distributed
over the texels by a cheap estimate of each texel's complexity, then AVSM (Salvi,
Vidimce, Lauritzen and Lefohn 2010, "Adaptive Volumetric Shadow Maps", secs. 3-4) per
texel with its own node count, stored compacted.

Allocation (host float64, from the segments alone).  A texel with ``c`` segments needs at
most ``K = 2 c`` nodes (AVSM with ``N >= 2c`` never compresses); its options are the
:data:`LADDER` values below ``K`` (and at most ``max_nodes``) and ``K`` itself when
``K <= max_nodes``; empty texels get 0 nodes, every other texel at least 2.  The squared
error of ``n`` nodes is modelled as ::

    ``e(n) = span (1 - exp(-tau))^2 (1/n^2 - 1/K^2)^+``

(``span`` the texel's depth extent, ``tau`` its total optical depth: ``n`` nodes cut the
drop ``1 - T_behind`` into ``n`` pieces).  ``e`` is convex in ``n``.  Water-filling: from
the least option of every texel, upgrades to the next option are taken in order of
decreasing gain per node ``(e(n) - e(n')) / (n' - n)`` (ties: lower texel, then smaller
``n``) while the node total fits the budget; upgrades that gain nothing are never taken (the
first upgrade that does not fit found by bisection on the gain: no sort of all upgrades).
Ablations (experiment ``memory_budget``): ``_score='count'`` (``span = 1``, ``tau = c``),
``_score='uniform'`` (the largest count that fits, for every non-empty texel).

Build: :class:`~.avsm.AVSM` per kernel N (the option's ladder value; ``K`` runs with the next
ladder value, which never compresses) on :meth:`~avsm_dr.Segments.select_texels` of chunks of
its texels (about the output's bytes of copied segments each; one per N under gradients) with
the map's near/far: a texel's nodes are bit for bit those of ``build('avsm', seg, nodes=N)``.
Storage (CSR, at most ``bytes_per_texel x T`` bytes): T+1 uint32 offsets, per node a depth and
a transmittance (all N of its kernel where allocated fewer than ``K``, else the ``used`` ones).
Lookup: :func:`~.avsm.csr_lookup`.
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import backend
from ._loops import chunk_stop, texel_lanes
from . import avsm
from .avsm import AVSM, INTERPOLATION, csr_lookup
from .base import SPARSE_OFFSET_BYTES as OFFSET_BYTES, Representation, depth_range, node_build_bytes
from .registry import register
from .schema import FAR, NEAR, Param, Schema

#: Kernel node counts (each distinct one is one compiled AVSM kernel).
LADDER = (2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64)
#: Largest ``bytes_per_texel``: the most one texel can store, 64 float64 nodes and its offset.
MAX_BYTES_PER_TEXEL = float(OFFSET_BYTES + 2 * 8 * LADDER[-1])
SCORES = ("complexity", "count", "uniform")


def ladder(max_nodes: int) -> np.ndarray:
    """Kernel node counts available under ``max_nodes``: :data:`LADDER` below it, and it."""
    return np.array([n for n in LADDER if n < max_nodes] + [max_nodes], np.int64)


def options(counts: np.ndarray, max_nodes: int) -> np.ndarray:
    """(T, L) node-count options per texel, ascending, padded with 0 (empty texels have
    none): the :func:`ladder` values below ``K = 2 c``, then ``K`` where ``K <= max_nodes``."""
    K = 2 * np.asarray(counts, np.int64)
    lad = ladder(max_nodes)
    opt = np.concatenate([np.where(lad[None, :] < K[:, None], lad[None, :], 0),
                          np.where(K <= max_nodes, K, 0)[:, None]], axis=1)
    big = np.iinfo(np.int64).max
    s = np.sort(np.where(opt > 0, opt, big), axis=1)
    return np.where(s == big, 0, s)


def kernel_nodes(n: np.ndarray, counts: np.ndarray, max_nodes: int) -> np.ndarray:
    """(T,) AVSM kernel N for allocated counts ``n``: ``n`` itself below ``K = 2 c``, the
    smallest ladder value >= K at ``K`` (that kernel never compresses), 0 for empty texels."""
    n = np.asarray(n, np.int64)
    K = 2 * np.asarray(counts, np.int64)
    lad = ladder(max_nodes)
    up = lad[np.minimum(np.searchsorted(lad, n), lad.size - 1)]
    return np.where(n == 0, 0, np.where(n < K, n, up))


def model_error(n, K, weight):
    """Modelled squared error ``weight (1/n^2 - 1/K^2)^+`` (0 where ``n`` is 0 or >= K)."""
    n = np.asarray(n, np.float64)
    K = np.asarray(K, np.float64)
    safe = np.where(n > 0, n, 1.0)
    Ks = np.where(K > 0, K, 1.0)
    e = weight * np.maximum(1.0 / (safe * safe) - 1.0 / (Ks * Ks), 0.0)
    return np.where(n > 0, e, 0.0)


def complexity(segments, score: str) -> np.ndarray:
    """(T,) float64 weight of :func:`model_error` per texel: ``span (1 - exp(-tau))^2``
    (``score='count'``: ``(1 - exp(-c))^2``; ``'uniform'``: 1); 0 for empty texels."""
    c = segments.counts
    if score == "uniform":
        return np.where(c > 0, 1.0, 0.0)
    if score == "count":
        return np.expm1(-c.astype(np.float64)) ** 2
    lo, hi = segments.texel_bounds()
    od, tau = dr.detach(segments.optical_depth), np.zeros(c.size)   # tau: float64 sums in CSR order
    if segments.n_segments:
        F64, (texel, first, stop) = backend.types().Float64, texel_lanes(segments)
        tau[texel.numpy()] = dr.while_loop((first, dr.zeros(F64, dr.width(texel))), lambda i, t: i < stop, lambda i, t:
                                           (i + 1, t + F64(dr.gather(type(od), od, i))), label="texel_tau")[1].numpy()
    return np.where(c > 0, (hi - lo) * np.expm1(-tau) ** 2, 0.0)


def allocate(counts, weight, budget_nodes: int, max_nodes: int, uniform: bool = False) -> np.ndarray:
    """(T,) int64 node count per texel within ``budget_nodes`` (module docstring):
    water-filling by decreasing modelled gain per node from each texel's least option;
    ``uniform``: the largest ladder value ``n`` such that every non-empty texel taking
    ``min(n, K)`` fits.  The caller checks that the least options fit."""
    counts = np.asarray(counts, np.int64)
    K, B = 2 * counts, 2048                        # rows in blocks of B texels: bounded temporaries
    first = np.concatenate([options(counts[a:a + B], max_nodes)[:, 0] for a in range(0, counts.size, B)] or [K])
    if uniform:
        best = first
        for n in ladder(max_nodes):
            cand = np.where(K <= n, K, n)
            if cand.sum() <= budget_nodes:
                best = cand
        return best
    gain = np.zeros((counts.size, ladder(max_nodes).size))   # per upgrade step; 0: none
    cost = np.zeros(gain.shape, np.int8)
    for a in range(0, counts.size, B):
        opt, sl = options(counts[a:a + B], max_nodes), slice(a, a + B)
        n0, n1 = opt[:, :-1], opt[:, 1:]
        step = n1 > 0
        Kc = np.broadcast_to(K[sl, None], n0.shape)
        w = np.broadcast_to(np.asarray(weight, np.float64)[sl, None], n0.shape)
        g = (model_error(n0, Kc, w) - model_error(np.where(step, n1, n0), Kc, w)) / np.where(step, n1 - n0, 1)
        g = np.minimum.accumulate(g, axis=1)       # non-increasing per texel (convex e; guards rounding)
        step &= g > 0                              # nothing is spent where the model gains nothing
        gain[sl], cost[sl] = np.where(step, g, 0.0), np.where(step, n1 - n0, 0)
    # Steps are taken in the order (gain descending, texel, n) while their running cost fits the
    # room: all those of gain above the gain g* of the first that does not fit, and those of gain
    # g* in (texel, n) order up to it.  g* by bisection on the bits of the gains (positive floats).
    room, bits = int(budget_nodes) - int(first.sum()), gain.view(np.int64)
    def above(x):       # cost of the steps with gain bits >= x
        return int(np.sum(cost, where=bits >= x, dtype=np.int64))
    if room <= 0 or above(1) <= room:
        return first + (cost.sum(axis=1, dtype=np.int64) if room > 0 else 0)
    lo, hi = 1, int(bits.max()) + 1                # above(lo) > room >= above(hi)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (mid, hi) if above(mid) > room else (lo, mid)
    tie = np.flatnonzero(bits == lo)               # gain g*, in (texel, n) order
    take = tie[:int(np.searchsorted(np.cumsum(cost.flat[tie]), room - above(lo + 1), side="right"))]
    taken = (bits > lo).ravel()
    taken[take] = True
    return first + np.sum(cost, axis=1, where=taken.reshape(cost.shape), dtype=np.int64)


@register("avsm_adaptive")
class AVSMAdaptive(Representation):
    """AVSM with per-texel node counts under a total budget of ``bytes_per_texel`` x T bytes
    (module docstring; ValueError below the offsets plus 2 nodes per non-empty texel).
    Attributes: ``allocated``, ``kernel`` (T,) int64 (allocated counts, AVSM kernel N), the CSR
    nodes as DSM's, ``budget_nodes``, ``groups`` ({N: texels}).  Gradients flow as AVSM's;
    with ``reverse='auto'`` the groups' loops run checkpointed."""

    schema = Schema(
        params=(
            Param("bytes_per_texel", "float", 64.0, "memory budget: mean bytes per texel over the whole map "
                  "(offsets included; total = bytes_per_texel x texels)", min=8.0, max=MAX_BYTES_PER_TEXEL),
            Param("max_nodes", "int", 32, "cap on the nodes of one texel", min=2, max=64),
            Param("sort", "bool", False, "insert segments sorted by depth per texel (as AVSM)"),
            INTERPOLATION,
            NEAR, FAR,
            Param("_score", "choice", "complexity", "private: allocation score 'complexity' (span x drop^2), "
                  "'count' (segments only) or 'uniform' (one count for all non-empty texels)", choices=SCORES),
        ),
        size="bytes_per_texel", sweep=(24.0, 32.0, 48.0, 64.0, 96.0, 128.0, 192.0, 256.0),
        quick_sweep=(32.0, 64.0, 128.0),
        examples=({"bytes_per_texel": 48.0, "interpolation": "exp"},
                  {"bytes_per_texel": 96.0, "max_nodes": 8, "sort": True}),
        headline={"bytes_per_texel": 64.0},
        summary="AVSM with per-texel node counts under a total byte budget (complexity water-filling, CSR)",
        paper="Salvi et al. 2010 (budgeted variant)")

    def _resolve(self):
        P, segments = self.params, self.segments
        P.update(zip(("near", "far"), depth_range(segments, P["near"], P["far"])))
        self._score = P.pop("_score")
        T, item = segments.n_texels, segments.itemsize
        # the allocation's ~10 (T, options) arrays, the AVSM groups every non-empty texel at most
        n_nz = int(np.count_nonzero(segments.counts))
        self._check_build_memory(lambda m: node_build_bytes(n_nz, m, item) + 80.0 * (ladder(m).size + 1) * T,
                                 name="max_nodes")
        self.budget_nodes = int((P["bytes_per_texel"] * T - OFFSET_BYTES * (T + 1)) // (2 * item))
        least = 2 * n_nz
        if self.budget_nodes < least:
            need = (OFFSET_BYTES * (T + 1) + 2 * item * least) / T
            raise ValueError(f"bytes_per_texel: {P['bytes_per_texel']:g} is below the least storage of this map, "
                             f"{need:.6g} (offsets and 2 nodes of {2 * item} bytes per non-empty texel)")

    def _build(self):
        seg, P = self.segments, self.params
        self.allocated = allocate(seg.counts, complexity(seg, self._score), self.budget_nodes, P["max_nodes"],
                                  uniform=self._score == "uniform")
        self.kernel = kernel_nodes(self.allocated, seg.counts, P["max_nodes"])
        self.loop_state_words = 2 * int(self.kernel.max(initial=0)) + 5       # the largest AVSM kernel's
        Float, T, K = seg.Float, seg.n_texels, 2 * seg.counts
        stored = np.zeros(T, np.int64)
        runs = []
        self.groups = {}
        # 'auto' checkpoints: plain loops over 3+ texel subsets of the same grad-enabled
        # segments gave wrong reverse-mode gradients (Dr.Jit 1.5, LLVM)
        reverse = "checkpoint" if self.reverse == "auto" and seg.requires_grad else self.reverse
        budget = max(avsm.MIN_CHUNK_BYTES, P["bytes_per_texel"] * T)       # the output's bytes
        for N in np.unique(self.kernel[self.kernel > 0]):
            tex = np.flatnonzero(self.kernel == N)
            self.groups[int(N)] = tex
            # chunks of the group's texels (without gradients): their copies of the segments
            # (and index arrays, ~8 + 5 itemsize bytes per segment) within the output's bytes
            need = np.r_[0, np.cumsum((8 + 5 * seg.itemsize) * seg.counts[tex])]
            i0 = 0
            while i0 < tex.size:
                i1 = tex.size if seg.requires_grad else chunk_stop(need, i0, budget)
                t = tex[i0:i1]
                sub = AVSM(seg.select_texels(t), nodes=int(N), sort=P["sort"], interpolation=P["interpolation"],
                           near=P["near"], far=P["far"], reverse=reverse, chunk=self._chunk)
                # compressing texels keep all N nodes, the others their inserted ones
                stored[t] = np.where(self.allocated[t] < K[t], int(N), sub.used)
                runs.append((t, self._compact(sub, stored[t])))
                del sub
                if i1 - i0 < tex.size:                     # as AVSM's chunks: buffers leave the cache
                    dr.flush_malloc_cache()
                i0 = i1
        self._set_nodes(stored)
        total = int(self.node_offsets[-1])
        self.node_depth = dr.zeros(Float, total)
        self.node_value = dr.zeros(Float, total)
        for j, (t, (depth, value)) in enumerate(runs):    # each run's nodes to their place, then freed
            n = stored[t]
            dst = A.to_uint32(np.repeat(self.node_offsets[t] - np.r_[0, np.cumsum(n)[:-1]], n) + np.arange(n.sum()))
            dr.scatter(self.node_depth, depth, dst)
            dr.scatter(self.node_value, value, dst)
            dr.eval(self.node_depth, self.node_value)
            runs[j] = None
        dr.eval(self.node_depth, self.node_value)

    @staticmethod
    def _compact(sub, stored):
        """``sub``'s first ``stored[j]`` nodes of each texel ``j``, CSR in texel order (depths, values)."""
        Float, off = sub.Float, np.r_[0, np.cumsum(stored)]
        depth, value = dr.zeros(Float, int(off[-1])), dr.zeros(Float, int(off[-1]))
        for k in range(sub.N):
            lanes = np.flatnonzero(stored > k)
            if lanes.size == 0:
                break
            src, dst = A.to_uint32(lanes), A.to_uint32(off[lanes] + k)
            dr.scatter(depth, dr.gather(Float, sub.depths[k], src), dst)
            dr.scatter(value, dr.gather(Float, sub.values[k], src), dst)
        dr.eval(depth, value)
        return depth, value

    variable_size = True                    # sparse payload: the stored (depth, value) nodes

    def _native_bytes(self) -> float:
        T = self.n_texels
        return (OFFSET_BYTES * (T + 1) + 2 * self.segments.itemsize * int(self.node_offsets[-1])) / T

    def node_depths(self) -> np.ndarray:
        """Depths of every stored node (float64 NumPy, CSR order)."""
        return np.asarray(self.node_depth.numpy(), np.float64)

    def _eval_texels(self, texel, depth):
        return csr_lookup(self._offsets_dr, self._max_nodes, lambda i, a: dr.gather(self.Float, self.node_depth, i, a),
                          self.node_value, texel, depth, self.params["interpolation"], hold_last=False)

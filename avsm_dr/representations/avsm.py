"""Adaptive Volumetric Shadow Maps (Salvi, Vidimce, Lauritzen and Lefohn 2010, EGSR; secs. 3.1-3.3, 4.1-4.2).

Each texel keeps N nodes ``(d_i, t_i)`` sorted by depth, cleared to ``(far, 1)``.

* **Insertion** of a segment ``[a, b]`` with exit transmittance ``ts`` (secs. 3.1, 4.1):
  ``T'(x) = T(x) R(x)`` with the segment's linear ramp
  ``R(x) = 1 (x <= a),  1 + (ts - 1)(x - a)/(b - a) (a < x < b),  ts (x >= b, x > a)``;
  existing nodes are multiplied by ``R(d_i)``; an entry node ``(a, T(a))`` and an exit
  node ``(b, T(b) ts)`` are added after existing nodes of equal depth.
* **Compression** (sec. 3.2): while more than N nodes, remove the interior node with the
  smallest ``|(d[i+1]-d[i-1])(t[i+1]-t[i]) - (d[i+1]-d[i])(t[i+1]-t[i-1])|`` (ties: the
  deepest); the first and last node are never removed, no node is moved.  Variants
  (``insertion``): :mod:`._avsm_insertion`.
* **Sampling** (sec. 3.3): T = 1 in front of the first node, the last node's value behind
  the last one, linear (eq. 2) or exponential interpolation in between.

Conventions the paper leaves open: clear nodes ``(far, T)`` sort after every inserted node
of equal depth and are dropped first when the texel overflows (their metric is exactly 0: the
paper's metric with a fixed tie-break; a texel with room left does no compression work).  A
segment whose entry lies where the stored nodes make the curve 0 (:func:`curve_at`) is not
inserted (behind a fully opaque point nothing changes).

Precision: node values are products of factors evaluated without cancellation: after ``k``
insertions each lies within a relative ``10 k u`` (``u`` the unit roundoff) of exact
arithmetic on the stored inputs.  Kernel: one lane per non-empty texel, the N nodes in
registers; one loop inserts while the texel has room, one compresses.
"""
from __future__ import annotations


import drjit as dr
import numpy as np

from .. import _arrays as A
from .. import backend
from ..texel_sort import MAX_NETWORK, float_of_key
from .registry import register
from ._avsm_insertion import INSERTIONS, KEEP_TOL, fit_values, piece_moments, remove_refit
from ._loops import chunk_stop, count_sorted, run_loop
from .base import Representation, depth_range
from ._precision import PRECISIONS, Stored
from .schema import FAR, NEAR, Param, Schema

INTERPOLATIONS = ("linear", "exp")
#: A sorted build (``sort=True``, segments without gradients) whose sort buffers (64-bit words,
#: estimated at 12 bytes per segment, 24 in texels over ``MAX_NETWORK``) exceed ``max(MIN_CHUNK_BYTES,
#: output bytes)`` twice runs in chunks of whole texels within that budget (with their copy of the
#: segments), each sorted and inserted before the next: its peak follows the output's size, not
#: the segments'.
MIN_CHUNK_BYTES = 1 << 18
#: Parameters of the node-list kinds (avsm, greedy, optimal).
NODES = Param("nodes", "int", 8, "N nodes (depth, transmittance) per texel", min=2, max=64)
INTERPOLATION = Param("interpolation", "choice", "linear", "between nodes: 'linear' (AVSM's eq. 2) or 'exp' "
                      "(uniform density)", choices=INTERPOLATIONS)


def bracket(d, t, x):
    """Nodes around x, branch-free: (d_l, t_l, d_r, t_r) of the last node with d_k <= x and its
    successor (both T = 1 in front of the first node, both the last node behind the last); ``d`` sorted."""
    n = len(d)
    c = [d[k] <= x for k in range(n)]      # true for a prefix (sorted d): tree, right over left where it starts true
    parts = [(c[k], (d[k], t[k], d[min(k + 1, n - 1)], t[min(k + 1, n - 1)])) for k in range(n)]
    _, best = A.pairwise(parts, lambda lt, rt: (lt[0], tuple(dr.select(rt[0], r, l) for l, r in zip(lt[1], rt[1]))))
    one = dr.full(type(x), 1.0, dr.width(x))
    return tuple(dr.select(c[0], v, f) for v, f in zip(best, (x, one, x, one)))


def curve_at(d, t, x):
    """T(x) of the node list (right-continuous, linear between nodes) and whether the
    stored nodes make it exactly 0 there.  Returns (T, zero).

    ``T = t_r + (t_l - t_r) w`` with ``w = (d_r - x) / (d_r - d_l)`` (``t_l`` where
    ``d_r = d_l``), capped at ``t_l``: two terms >= 0, nothing cancels (within a relative
    ``6 u`` of the exact interpolation of the stored nodes).  ``zero`` reads the stored
    nodes (``t_l = 0`` and ``t_r = 0`` or ``x = d_l``), never a computed T."""
    dl, tl, dr_, tr = bracket(d, t, x)
    dd = dr_ - dl
    w = (dr_ - x) / dr.select(dd > 0, dd, 1)       # weight of the left node, 1 at x = d_l
    value = tr + (tl - tr) * w
    value = dr.replace_grad(dr.minimum(value, tl), value)   # rounding may pass t_l by an ulp
    return value, (tl == 0) & ((tr == 0) | (x == dl))


def insert_segment(d, t, used, a, b, ts, full: bool = False, ta=None, tau=None):
    """Nodes after inserting segment [a, b] (exit transmittance ts): N + 2 entries.

    ``used``: number of inserted (non-clear) nodes, which come first in the list.
    ``full``: the caller guarantees ``used >= N - 1`` (compressing phase), so only the
    last node can be a clear node - the same result with fewer instructions.
    ``ta``: ``curve_at(d, t, a)[0]`` when the caller has it.
    Nodes inside the segment take the ramp as ``R = ts + (1 - ts)(b - d_k) / (b - a)``,
    capped at 1 (two terms >= 0: within a relative ``7 u`` of the exact ramp).  ``tau``: the
    segment's optical depth for the exponential ramp ``R = exp(-tau (d_k - a) / (b - a))`` and
    an exponential interpolation of ``T(b)`` (the caller's ``ta`` likewise): exact for uniform
    density, so a list that never compressed holds the exact curve's values in any order.
    """
    n = len(d)
    UInt32 = type(used)
    ta = curve_at(d, t, a)[0] if ta is None else ta
    tb = (curve_at(d, t, b)[0] if tau is None else interpolate(d, t, b, "exp")) * ts
    length = b - a
    inv_len = 1 / dr.select(length > 0, length, 1)
    opacity = 1 - ts
    e = UInt32(0)          # slot of the entry node = inserted nodes with d <= a
    x = UInt32(1)          # slot of the exit node  = inserted nodes with d <= b, + 1
    scaled = []
    for k in range(n):
        if tau is None:
            ramp = ts + opacity * ((b - d[k]) * inv_len)
            ramp = dr.replace_grad(dr.minimum(ramp, 1), ramp)        # in [ts, 1]
        else:
            ramp = dr.exp(-tau * dr.clip((d[k] - a) * inv_len, 0, 1))
        inner = dr.select(d[k] > a, dr.select(d[k] >= b, ts, ramp), 1)
        if full and k < n - 1:
            e += UInt32(d[k] <= a)
            x += UInt32(d[k] <= b)
            factor = inner
        else:
            real = UInt32(k) < used
            e += UInt32(real & (d[k] <= a))
            x += UInt32(real & (d[k] <= b))
            # clear nodes stand behind every blocker: they always take the full ts
            factor = dr.select(real, inner, ts)
        scaled.append(t[k] * factor)
    def pick(mask, node_d, node_t, cd, ct):
        return dr.select(mask, node_d, cd), dr.select(mask, node_t, ct)

    out_d, out_t = [], []
    for j in range(n + 2):
        # slot j holds existing node j - (inserted nodes in front of it); x > e, so an
        # exit in front implies an entry in front
        cd, ct = (d[j], scaled[j]) if j < n else (a, ta)
        if 1 <= j <= n:
            cd, ct = pick(e < j, d[j - 1], scaled[j - 1], cd, ct)
        if 2 <= j <= n + 1:
            cd, ct = pick(x < j, d[j - 2], scaled[j - 2], cd, ct)
        cd, ct = pick(x == j, b, tb, cd, ct)
        cd, ct = pick(e == j, a, ta, cd, ct)
        out_d.append(cd)
        out_t.append(ct)
    return out_d, out_t


def interpolate(d, t, depth, mode: str):
    """Sample the node list at ``depth`` (Salvi et al. 2010, secs. 3.3 / 4.2): :func:`bracket`,
    then :func:`lerp`."""
    return lerp(*bracket(d, t, depth), depth, mode)


def lerp(dl, tl, dr_, tr, depth, mode: str):
    """One interpolation between nodes ``(d_l, t_l)`` and ``(d_r, t_r)``, ``w = (depth - d_l) /
    (d_r - d_l)`` clipped to [0, 1]: linear ``t_l + w (t_r - t_l)`` (eq. 2) or exponential
    ``t_l (t_r / t_l)^w`` (uniform density between nodes; linear where t_l or t_r is 0)."""
    dd = dr_ - dl
    w = dr.clip((depth - dl) / dr.select(dd > 0, dd, 1), 0, 1)
    lin = tl + w * (tr - tl)
    if mode == "exp":
        ok = (tl > 0) & (tr > 0)
        sl = dr.select(ok, tl, 1)
        sr = dr.select(ok, tr, 1)
        lin = dr.select(ok, sl * dr.exp(w * (dr.log(sr) - dr.log(sl))), lin)
    return lin


def csr_lookup(offsets, max_nodes: int, depth_at, values, texel, depth, mode: str, hold_last: bool = True):
    """T at receivers from a CSR node list (``offsets``: UInt32 (T+1,), at most ``max_nodes``
    nodes per texel sorted by depth; ``depth_at(i, active)``: node i's depth; ``values``: the
    nodes' T): binary search for the last node at or before ``depth``, then :func:`lerp` to its
    successor; T = 1 in front of the first node and in empty texels, the last node's value
    behind the last (DSM, avsm_march, avsm_adaptive; ``hold_last`` False: :func:`interpolate`
    of the two nodes, the same value)."""
    Float, U32 = type(depth), backend.types().UInt32
    if max_nodes == 0:
        return dr.full(Float, 1.0, dr.width(depth))
    start = dr.gather(U32, offsets, texel)
    count = dr.gather(U32, offsets, texel + 1) - start
    n_le = count_sorted(depth_at, start, count, depth, max_nodes)      # nodes at or before the depth
    front, behind = n_le == 0, n_le >= count
    il = start + dr.select(front, 0, n_le - 1)
    ir = dr.select(behind | front, il, il + 1)
    zl, zr = depth_at(il, ~front), depth_at(ir, ~front)
    tl, tr = dr.gather(Float, values, il, ~front), dr.gather(Float, values, ir, ~front)
    if not hold_last:
        return dr.select(front, 1.0, interpolate([zl, zr], [tl, tr], depth, mode))
    return dr.select(front, 1.0, dr.select(behind, tl, lerp(zl, tl, zr, tr, depth, mode)))


class NodeList(Representation):
    """Kinds storing N (depth, transmittance) nodes per texel as ``depths``/``values``
    (lists of N Dr.Jit arrays of length T) with ``self.N`` set and an ``interpolation``
    parameter: storage ``2 N itemsize`` and the bracket-then-interpolate lookup.
    ``precision``: depths relative to the texel's node range, values as transmittances
    (:mod:`._precision`)."""

    precisions = PRECISIONS

    def _resolve(self):
        self.N = self.params["nodes"]
        self._check_node_memory()

    def _stored(self):
        return (Stored("depths", "depth", "nodes"), Stored("values", "transmittance", "nodes"))

    def _native_bytes(self) -> float:
        return 2 * self.N * self.segments.itemsize

    def _node_rows(self):
        """The nodes as one row ``[d_0 .. d_{N-1}, t_0 .. t_{N-1}]`` per texel, read by one
        packet gather per lookup instead of 2 N gathers; rebuilt whenever ``depths``/``values``
        change (the cache keeps references to its variables: same indices, same data); None
        while any carries gradients (the lookup then gathers the lists)."""
        bufs = [*self.depths, *self.values]
        if any(dr.grad_enabled(b) for b in bufs):
            return None
        cache = getattr(self, "_rows_cache", None)
        if cache is not None and len(cache[0]) == len(bufs) and all(
                h.index == b.index for h, b in zip(cache[0], bufs)):
            return cache[1]
        W, T = len(bufs), dr.width(bufs[0])
        base = dr.arange(backend.types().UInt32, T) * W
        rows = dr.empty(self.Float, T * W)
        for k, b in enumerate(bufs):
            dr.scatter(rows, b, base + k)
        dr.eval(rows)
        self._rows_cache = ([type(b)(b) for b in bufs], rows)
        return rows

    def _eval_texels(self, texel, depth):
        Float, N = self.Float, len(self.depths)
        rows = self._node_rows() if N else None
        if rows is None:
            d = [dr.gather(Float, self.depths[k], texel) for k in range(N)]
            t = [dr.gather(Float, self.values[k], texel) for k in range(N)]
        else:
            m = backend.types()
            v = dr.gather(m.ArrayXf64 if Float is m.Float64 else m.ArrayXf, rows, texel, shape=(2 * N, dr.width(texel)))
            d, t = [v[k] for k in range(N)], [v[N + k] for k in range(N)]
        return interpolate(d, t, depth, self.params["interpolation"])

    def nodes_numpy(self) -> tuple[np.ndarray, np.ndarray]:
        """(T, N) node depths and transmittances as NumPy arrays."""
        return tuple(np.stack([np.asarray(x.numpy()) for x in b], axis=1) for b in (self.depths, self.values))


@register("avsm")
class AVSM(NodeList):
    """Adaptive volumetric shadow map: N (depth, transmittance) nodes per texel, cleared to
    (far, 1), stored as a :class:`NodeList`.  Attributes: ``used`` (NumPy (T,), inserted nodes
    kept per texel) and ``stats`` (lanes run, segments skipped behind opaque points, insertions
    that compressed).  Gradients flow to optical_depth and z0/z1 with the node layout held fixed.
    ``sort=True`` on a large map (without gradients) sorts and inserts in chunks of texels
    (:data:`MIN_CHUNK_BYTES`): the same nodes, a peak memory near the output's size.
    """

    # Linear (the paper's eq. 2) is the preset: at N = 8 it has the lower receiver error on the smoke
    # and hair scenes in every insertion order but the fog bank front to back; exp wins inside thick
    # uniform media (particles).  Both are reported (docs/research/memory_budget.md).
    PRESET = {"interpolation": "linear"}
    PRESET_VARIANTS = {"linear": {"interpolation": "linear"}, "exp": {"interpolation": "exp"}}
    schema = Schema(
        params=(
            NODES,
            Param("sort", "bool", False, "insert segments sorted by depth per texel (deterministic) "
                  "instead of in the given order"),
            INTERPOLATION,
            Param("insertion", "choice", "stream", "what an overflow does: 'stream' (the paper's removal), "
                  "'refit' (area-preserving refit of the removed node's neighbours), 'refit_l2' (L2 "
                  "removal metric, least-squares refit), 'staged' / 'staged_refit_l2' (compress only "
                  "every 4 segments), 'spare_refit_l2' ('refit_l2' on N + 8 nodes, compressed to N at "
                  "the end), 'spare_exp' (the same with exponential segment ramps), 'spare_exp_fit' "
                  "('spare_exp', then least-squares node values where streaming kept the exact curve); see "
                  "avsm_dr.representations._avsm_insertion",
                  choices=tuple(INSERTIONS)),
            NEAR, FAR,
            # Private ablation switches (benchmarks only; the nodes are the same either way):
            Param("_compact", "bool", True, "private: lanes only for non-empty texels (else one per texel)"),
            Param("_group", "bool", True, "private: lanes ordered by segment count, longest first"),
            Param("_split", "bool", True, "private: an insert-only loop while the texel has room, then a "
                  "compressing loop (else one loop computing both and selecting)"),
        ),
        size="nodes", sweep=(2, 4, 6, 8, 12, 16, 24, 32), quick_sweep=(2, 4, 8, 12, 16),
        examples=({"nodes": 8}, {"nodes": 4, "sort": True}, {"nodes": 8, "interpolation": "exp"}),
        headline={"nodes": 8},
        summary="N (depth, transmittance) nodes, streaming insertion + area-based removal",
        paper="Salvi et al. 2010")

    def _resolve(self):
        P, seg = self.params, self.segments
        P.update(zip(("near", "far"), depth_range(seg, P["near"], P["far"])))
        super()._resolve()
        self._refit, self._metric, self._stage, self._spare, self._ramp, self._fit = INSERTIONS[P["insertion"]]
        # W = N + spare depths and values; 5 counters (6 with the final fit's flag)
        self.loop_state_words = 2 * (self.N + self._spare) + 5 + int(self._fit)
        self._ablation = {k: P.pop(k) for k in ("_compact", "_group", "_split")}

    def _build(self):
        seg, T, Float = self.segments, self.segments.n_texels, self.segments.Float
        self.depths = [dr.opaque(Float, self.params["far"], T) for _ in range(self.N)]   # opaque: no kernel per far
        self.values = [dr.full(Float, 1.0, T) for _ in range(self.N)]
        self.used = np.zeros(T, np.int64)
        self.stats = {"lanes": 0, "segments": seg.n_segments, "skipped": 0, "compressed": 0}
        if seg.n_segments == 0:
            return
        sort_bytes = np.where(seg.counts > MAX_NETWORK, 24, 12) * seg.counts    # estimates, per texel
        budget = max(MIN_CHUNK_BYTES, 2 * self.N * seg.itemsize * T)               # the output's bytes
        chunked = self.params["sort"] and not seg.requires_grad and sort_bytes.sum() > 2 * budget
        need, t0 = np.r_[0, np.cumsum(sort_bytes + 3 * seg.itemsize * seg.counts)], 0
        while t0 < T:         # chunks of whole texels, each sorted and inserted (the nodes do not depend on them)
            t1 = chunk_stop(need, t0, budget) if chunked else T
            self._insert(seg if t1 - t0 == T else seg.texel_range(t0, t1), t0)
            if chunked:       # the chunk's buffers, of sizes the next may not reuse, leave Dr.Jit's cache
                dr.flush_malloc_cache()
            t0 = t1

    def _insert(self, seg, t0: int):
        """Insert the segments of ``seg`` (this build's texels ``t0 ..``) into the nodes."""
        words = not seg.requires_grad and seg.dtype == "float32"     # sort words: z0 with the position
        view = seg.depth_view(words=words) if self.params["sort"] else None
        t_ = backend.types()
        Float, UInt32, Bool = seg.Float, t_.UInt32, t_.Bool
        N, far, T = self.N, self.params["far"], seg.n_texels
        counts = seg.counts
        ablate = self._ablation
        # Non-empty texels only, longest first: a SIMD packet runs as long as its longest lane.
        plan = seg._cache.get("sort_plan", {}) if view is not None and ablate["_compact"] and ablate["_group"] else {}
        if "texel" in plan:                               # the long texels, then the sort's lanes (in this order)
            lanes_np = np.concatenate([(b := np.flatnonzero(counts > MAX_NETWORK))[A.order_by_count(counts[b], True)],
                                       plan["texel"]])
        else:
            lanes_np = np.nonzero(counts > 0)[0] if ablate["_compact"] else np.arange(T)
            if ablate["_group"]:
                lanes_np = lanes_np[A.order_by_count(counts[lanes_np], descending=True)]
        if lanes_np.size == 0 or seg.n_segments == 0:
            return
        lanes = A.to_uint32(lanes_np)
        L = lanes_np.size
        offsets = seg.offsets_dr()
        first = dr.gather(UInt32, offsets, lanes)
        end = dr.gather(UInt32, offsets, lanes + 1)       # one past the texel's last segment
        if view is not None:                              # positions in view[0] instead
            count = end - first
            first = dr.gather(UInt32, view[1], lanes)
            end = first + count
        sorted_input = bool(self.params["sort"])
        max_count = self.segments.max_count               # the loops' bound (trajectory length) ...
        lane_max = int(counts[lanes_np].max())            # ... checked against the lanes' own counts
        params = [seg.z0, seg.z1, seg.optical_depth]      # what gradients flow to

        refit, metric, stage, spare = self._refit, self._metric, self._stage, self._spare
        W = N + spare                                     # nodes while streaming

        def remove(d, t):                                 # 'stream' / 'staged': the paper's removal
            out = remove_refit(d, t, refit, metric, with_gap=self._fit)   # final fit: the chord gap too
            return out if self._fit else (*out, 0.0)

        def segment(p, i, active=True):
            # (entry depth a, exit depth b, exit transmittance ts) of segment i (0 where not active)
            if view is not None and words:                # the texel's next segment in depth order:
                w = dr.gather(type(view[0]), view[0], i, active)   # 3 reads, as unsorted input
                i, a = UInt32(w & 0xFFFFFFFF), dr.select(active, Float(float_of_key(UInt32(w >> 32))), 0.0)
                b, tau = (dr.gather(Float, x, i, active) for x in p[1:])
            else:
                i = i if view is None else dr.gather(UInt32, view[0], i, active)
                a, b, tau = (dr.gather(Float, x, i, active) for x in p)
            return a, b, dr.exp(-tau), tau

        def insert(p, i, used, done, d, t, compress):
            # compress: False (room left), True (full), or a Bool mask (_split=False ablation)
            a, b, ts, tau = segment(p, i)
            ta, skip = curve_at(d, t, a)                  # skip: the stored curve is 0 at a
            tau = tau if self._ramp == "exp" else None
            ta = ta if tau is None else interpolate(d, t, a, "exp")
            nd, nt = insert_segment(d, t, used, a, b, ts, full=compress is True, ta=ta, tau=tau)
            lost = False                                  # a removal changed the curve (final fit)
            if compress is True:
                nd, nt, m1 = remove(nd, nt)
                nd, nt, m2 = remove(nd, nt)
                lost = ~skip & (dr.maximum(m1, m2) > KEEP_TOL) if self._fit else False
            elif compress is not False:
                cd, ct, m1 = remove(nd, nt)
                cd, ct, m2 = remove(cd, ct)
                lost = compress & ~skip & (dr.maximum(m1, m2) > KEEP_TOL) if self._fit else False
                nd = [dr.select(compress, cd[k], nd[k]) for k in range(W)]
                nt = [dr.select(compress, ct[k], nt[k]) for k in range(W)]
            d = [dr.select(skip, d[k], nd[k]) for k in range(W)]
            t = [dr.select(skip, t[k], nt[k]) for k in range(W)]
            return skip, (skip if sorted_input else done), d, t, lost

        # state: i (next segment), used (inserted nodes kept, <= N), done (sorted and behind
        # an opaque point), skipped, compressed (counters), [lossy: a removal changed the curve,
        # final fit only], node depths d_k, transmittances t_k
        E = int(self._fit)                                # extra state words before the nodes
        def cond_room(p, i, used, done, *rest):
            return (i < end) & (used + 2 <= W) & ~done

        def cond_full(p, i, used, done, *rest):
            return (i < end) & ~done

        def body_insert(compress):
            def body(p, i, used, done, skipped, compressed, *rest):
                lossy, dt = rest[:E], rest[E:]
                full = used + 2 > W if compress is None else compress   # None: the _split=False ablation
                skip, done, d, t, lost = insert(p, i, used, done, list(dt[:W]), list(dt[W:]), full)
                lossy = [x | lost for x in lossy]
                if compress is not True:
                    used = dr.select(skip if compress is False else skip | full, used, used + 2)
                if compress is None:    # compressing loop: iterations - skipped, after it (a state word less)
                    compressed = compressed + UInt32(~skip & full)
                return (i + 1, used, done, skipped + UInt32(skip), compressed, *lossy, *d, *t)
            return body

        # staged variants, once full: ``stage`` segments into N + 2 stage nodes, then 2 stage
        # removals; a segment not inserted appends two copies of the last node (zero metric,
        # deepest: dropped first), so ``used`` is the same after the batch as before it.
        def body_staged(p, i, used, done, skipped, compressed, *dt):
            d, t = list(dt[:W]), list(dt[W:])
            grow = used
            for _ in range(stage):
                n = len(d)
                active = (i < end) & ~done
                a, b, ts, _ = segment(p, i, active)
                ta, zero = curve_at(d, t, a)
                nd, nt = insert_segment(d, t, grow, a, b, ts, ta=ta)
                put = active & ~zero
                pd, pt = d + [d[-1], d[-1]], t + [t[-1], t[-1]]
                d = [dr.select(put, nd[k], pd[k]) for k in range(n + 2)]
                t = [dr.select(put, nt[k], pt[k]) for k in range(n + 2)]
                grow = dr.select(put | (grow == n), grow + 2, grow)
                skipped += UInt32(active & zero)
                compressed += UInt32(put)
                if sorted_input:
                    done |= active & zero
                i = dr.select(active, i + 1, i)
            for _ in range(2 * stage):
                d, t, _ = remove(d, t)
            return (i, used, done, skipped, compressed, *d, *t)

        chunk = self.checkpoint_chunk(seg)

        def run(state, cond, body, label):
            # without gradients not re-traced to drop unchanged state (LLVM drops it): 0.4 ms a build
            with dr.scoped_set_flag(dr.JitFlag.OptimizeLoops, seg.requires_grad):   # (AD: Dr.Jit aborts)
                return run_loop(state, params, cond, body, max_count, chunk, label, iterations=lane_max)

        state = (first, dr.zeros(UInt32, L), dr.zeros(Bool, L),
                 dr.zeros(UInt32, L), dr.zeros(UInt32, L), *[dr.zeros(Bool, L)] * E,
                 *[dr.opaque(Float, far, L) for _ in range(W)], *[dr.full(Float, 1.0, L) for _ in range(W)])
        if stage > 1:                                     # staged: always the two loops
            state = run(state, cond_room, body_insert(False), "avsm_insert")
            state = run(state, cond_full, body_staged, "avsm_staged")
        elif ablate["_split"]:
            mid = run(state, cond_room, body_insert(False), "avsm_insert")
            state = run(mid, cond_full, body_insert(True), "avsm_compress")
            state = (*state[:4], state[4] + (state[0] - mid[0]) - (state[3] - mid[3]), *state[5:])
        else:
            state = run(state, cond_full, body_insert(None), "avsm_one_loop")
        i, used, done, skipped, compressed = state[:5]
        lossy, dt = state[5:5 + E], state[5 + E:]
        if spare:   # down to N nodes by "post"; the list ends at the used nodes (all W once compressing)
            fit = self._fit                               # carry the piece moments S0, S1 too
            def body_spare(p, last, *dt):
                m = (dt[2 * W:3 * W], dt[3 * W:]) if fit else None
                d, t, *m = remove_refit(dt[:W], dt[W:2 * W], refit, "post", last=last, moments=m)
                zero = [dr.zeros(type(t[0]), dr.width(t[0]))] * bool(fit)   # a zero-width last piece
                return (last - 1, *d, d[-1], *t, t[-1], *(x for mm in m for x in (*mm, *zero)))
            last = dr.select(compressed > 0, W - 1, used - 1)   # last < W below: not a lane of 0 nodes
            count = dr.minimum(last + 1, N)                     # real nodes after the compression
            if fit:
                dt = (*dt, *(x for mm in piece_moments(dt[:W], dt[W:], last + 1) for x in mm))
            dt = run_loop((last, *dt), params, lambda p, last, *r: (last >= N) & (last < W), body_spare,
                          spare, chunk, "avsm_spare", iterations=spare)[1:]
            used = dr.minimum(used, N)
            if fit:   # least-squares values where every removal kept the curve (exact nodes)
                t = fit_values(dt[:N], dt[W:W + N], dt[2 * W:2 * W + N], dt[3 * W:3 * W + N], count - 1, ~lossy[0])
                dt = (*dt[:W], *t, *dt[W + N:2 * W])
        out = lanes if t0 == 0 else A.to_uint32(lanes_np + t0)   # not lanes + t0: a literal, a kernel per chunk
        for k in range(N):
            dr.scatter(self.depths[k], dt[k], out)
            dr.scatter(self.values[k], dt[W + k], out)
        # one kernel: the counters read below would otherwise each re-run both loops
        dr.eval(self.depths, self.values, used, i, skipped, compressed)
        self.used[lanes_np + t0] = np.asarray(used.numpy(), np.int64)
        # skipped: behind an opaque point (sorted input: the rest of the texel counts too)
        st = self.stats
        st["lanes"] += int(L)
        st["skipped"] += int(dr.sum(skipped)[0]) + int(dr.sum(end - i)[0])
        st["compressed"] += int(dr.sum(compressed)[0])


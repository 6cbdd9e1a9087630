"""Sorting every texel's segments on the device: sorting networks in registers, one lane per texel.

Input: one 64-bit *word* per segment in CSR order, ``word = key << 32 | payload`` with the
32-bit sort key in the high half and a payload unique inside the texel in the low half
(the segment's position, or its concatenation index), so that words are distinct and
comparing words is comparing ``(key, payload)``.  Output: for every CSR position
``o_t + r`` the payload of the ``r``-th smallest word of texel ``t``.

* Texels of ``k <= 64`` segments: one lane per texel sorts its ``k`` words in registers
  (padded with ``2^64 - 1`` up to its size class, :data:`SIZE_CLASSES`) with Batcher's
  odd-even merge sort network (K. E. Batcher, "Sorting networks and their applications",
  AFIPS 1968, section 2), comparators on pads pruned; all classes in one kernel (a chain of
  symbolic conditionals, lanes grouped by class).
* Longer texels: blocks of 64, then bottom-up merges of pairs of sorted runs, one lane per
  pair with both heads in registers.
* Equal keys (:func:`break_ties`): one lane per segment ranks itself inside its run of
  equal keys by a second key, then position.

Also the per-texel order keys of :meth:`Segments.in_order <avsm_dr.segments.Segments.in_order>`
(the ``"random"`` order): the seeded 32-bit shuffle hash :func:`shuffle_key`.
"""
from __future__ import annotations

import math
from functools import lru_cache

import drjit as dr
import numpy as np

from . import _arrays as A
from . import backend

#: Largest texel sorted by a network in one lane; longer texels merge sorted blocks of it.
MAX_NETWORK = 64
#: Network sizes (a lane's texel padded to the next): the powers of two and the midpoints between
#: them; on the plume's 1024^2 captures 13 % (exact) and 26 % (march) fewer comparators than powers of two.
SIZE_CLASSES = (2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64)
#: Packet stores (Dr.Jit's packet scatter) need a target size that every class divides.
PACKET_ALIGN = math.lcm(*SIZE_CLASSES)
#: Flag bits of :func:`sort_texels_view` (counted on the device): two words of a texel share
#: their key; some texel's words were not already increasing in CSR order (always, above 64).
TIE, UNSORTED = 1, 2
_PAD = 0xFFFFFFFFFFFFFFFF


@lru_cache(maxsize=None)
def network(n: int) -> tuple:
    """Comparators ``(i, j)``, ``i < j``, of Batcher's odd-even merge sort for ``n`` inputs:
    the network for the next power of two without the comparators that touch an input
    ``>= n`` (those hold pads larger than every word, so they never exchange)."""
    m = 1 << max(n - 1, 0).bit_length()
    pairs, p = [], 1
    while p < m:
        k = p
        while k >= 1:
            for j in range(k % p, m - k, 2 * k):
                for i in range(min(k, m - j - k)):
                    if (i + j) // (2 * p) == (i + j + k) // (2 * p) and i + j + k < n:
                        pairs.append((i + j, i + j + k))
            k //= 2
        p *= 2
    return tuple(pairs)


def _u32(a: np.ndarray):
    """Host integers as a UInt32 Dr.Jit array from a 64-byte aligned buffer (:func:`~avsm_dr._arrays.aligned`)."""
    return _types()[0](A.aligned(np.asarray(a).astype(np.uint32)))


def _types():
    t = backend.types()
    return dr.detached_t(t.UInt32), dr.detached_t(t.UInt64), dr.detached_t(t.ArrayXu), dr.detached_t(t.ArrayXu64)


def float_key(z):
    """Order-preserving UInt32 of float32 ``z`` (flip the sign bit of positives, every bit of
    negatives), with ``-0.0`` mapped like ``+0.0``: ``a < b`` as floats iff ``key(a) < key(b)``."""
    UInt32 = _types()[0]
    u = UInt32(dr.reinterpret_array(dr.uint32_array_t(type(z)), dr.detach(z)))
    u = dr.select(u == 0x80000000, 0, u)
    return u ^ ((UInt32(0) - (u >> 31)) | 0x80000000)


def float_keys(z) -> tuple:
    """Order-preserving UInt32 keys of float ``z``, most significant first: ``(float_key(z),)``
    for float32; for float64 the high and low halves of its 64-bit key (the same rule on 64 bits)."""
    if dr.type_v(z) != dr.VarType.Float64:
        return (float_key(z),)
    UInt32, UInt64 = _types()[:2]
    u = UInt64(dr.reinterpret_array(dr.uint64_array_t(type(z)), dr.detach(z)))
    u = dr.select(u == 1 << 63, 0, u)
    k = u ^ ((UInt64(0) - (u >> 63)) | (1 << 63))
    return UInt32(k >> 32), UInt32(k & 0xFFFFFFFF)


def _network_branch(word_at, size: int, out, ties: bool):
    """``f(start, count, packet) -> flags``: one lane per run ``[start, start + count)``
    (``count <= size``): its words ``word_at(position, valid)`` sorted in registers, stored
    as packet ``packet`` of ``out`` (payloads into a UInt32 ``out``, words into a UInt64 one);
    flags (UInt64): 1 for equal keys side by side, ``2^32`` when the run was unsorted."""
    UInt32, UInt64, ArrayXu, ArrayXu64 = _types()

    def f(start, count, packet):
        w = [dr.select(count > r, word_at(start + r, count > r), _PAD) for r in range(size)]
        unsorted = w[1] < w[0]
        for r in range(1, size - 1):                  # pads compare greater: no mask needed
            unsorted |= w[r + 1] < w[r]
        for i, j in network(size):
            w[i], w[j] = dr.minimum(w[i], w[j]), dr.maximum(w[i], w[j])
        dr.scatter(out, ArrayXu([UInt32(x) for x in w]) if type(out) is UInt32 else ArrayXu64(w), packet)
        flags = dr.select(unsorted, UInt64(1 << 32), 0)
        if ties:                                      # no dr.width(): the trace is replayed
            tie = ((w[0] ^ w[1]) < (1 << 32)) & (count > 1)
            for r in range(1, size - 1):
                tie |= ((w[r] ^ w[r + 1]) < (1 << 32)) & (count > r + 1)
            flags |= dr.select(tie, UInt64(1), 0)
        return flags
    return f


def word_function(kind: str, sources):
    """``word_at(position, active)`` for the word kinds of this package: ``'float'``,
    ``sources = (z0,)`` (float32): ``key(z0) << 32 | position``; ``'index'``, ``sources =
    (index, key)``: ``key[index] << 32 | index`` with ``index`` read at the position."""
    UInt32, UInt64, _, _ = _types()
    if kind == "float":
        z0, = sources
        return lambda pos, act: (UInt64(float_key(dr.gather(type(z0), z0, pos, act))) << 32) | UInt64(pos)
    index, key = sources

    def at(pos, act):
        i = dr.gather(UInt32, index, pos, act)
        return (UInt64(dr.gather(type(key), key, i, act)) << 32) | UInt64(i)
    return at


def _network_chain(word_at, sizes, out, ties: bool, i: int):
    """:func:`_network_branch` of each lane's size class among ``sizes[:i + 1]``, a chain of
    symbolic conditionals (a module function: a nested recursive one is a reference cycle that
    keeps the sort's buffers alive until a garbage collection)."""
    if i == 0:
        return _network_branch(word_at, sizes[0], out, ties)
    return lambda s, c, p: dr.if_stmt((s, c, p), c > sizes[i - 1], _network_branch(word_at, sizes[i], out, ties),
                                      _network_chain(word_at, sizes, out, ties, i - 1), label=f"network_{sizes[i]}")


def _sort_lanes(kind, sources, start, count, packet, sizes, out, ties: bool):
    """Sort the runs of all lanes (by decreasing size class) in one kernel, a chain of symbolic
    conditionals picking each lane's network; returns the flags summed (UInt64, width 1) and
    per lane (UInt64)."""
    UInt32, UInt64, _, _ = _types()
    flags = _network_chain(word_function(kind, sources), sizes, out, ties, len(sizes) - 1)(start, count, packet)
    counter = dr.zeros(UInt64, 1)             # one atomic add per SIMD packet
    dr.scatter_reduce(dr.ReduceOp.Add, counter, flags, UInt32(0), flags != 0, mode=dr.ReduceMode.Local)
    return counter, flags


def _merge_pass(cur, out, a0, mid, end, n, dst, tie: bool):
    """Merge two sorted runs per lane, ``cur[a0:mid]`` and ``cur[mid:end]``, writing the ``n``
    smallest words to ``out[dst:dst + n]`` (payloads into a UInt32 ``out``, words into a UInt64
    one); returns per lane whether two consecutive outputs share their key (with ``tie``)."""
    UInt32, UInt64, _, _ = _types()
    Bool = dr.mask_t(UInt32)
    a, b, k = UInt32(a0), UInt32(mid), dr.zeros(UInt32, dr.width(a0))
    ha, hb = dr.gather(UInt64, cur, a, a < mid), dr.gather(UInt64, cur, b, b < end)
    prev, same = dr.zeros(UInt64, dr.width(a0)), dr.zeros(Bool, dr.width(a0))

    def body(a, b, k, ha, hb, prev, same):
        take_a = (a < mid) & ((b >= end) | (ha < hb))   # words are distinct: the merge is stable
        w = dr.select(take_a, ha, hb)
        dr.scatter(out, UInt32(w) if type(out) is UInt32 else w, dst + k)
        if tie:
            same |= (k > 0) & ((prev ^ w) < (1 << 32))
            prev = w
        a, b = dr.select(take_a, a + 1, a), dr.select(take_a, b, b + 1)
        nxt = dr.select(take_a, a, b)
        ok = dr.select(take_a, a < mid, b < end)
        w = dr.gather(UInt64, cur, nxt, ok)
        return a, b, k + 1, dr.select(take_a, w, ha), dr.select(take_a, hb, w), prev, same
    state = dr.while_loop((a, b, k, ha, hb, prev, same), lambda a, b, k, *_: k < n, body, label="texel_merge")
    return state[-1]


def plan(counts: np.ndarray, offsets_dr) -> dict:
    """The layout of a sort (a function of the texel counts, so callers may keep it): lanes
    per size class, ``base`` (where each texel's sorted payloads start), blocks of the long
    texels and their merge passes."""
    UInt32 = _types()[0]
    off = UInt32(offsets_dr)
    counts = np.asarray(counts, np.int64)
    base = np.zeros(counts.size, np.int64)
    top = int(min(counts.max(initial=1), MAX_NETWORK))
    sizes = SIZE_CLASSES[:int(np.searchsorted(SIZE_CLASSES, max(top, 2))) + 1]   # 2 .. the class of the longest
    # texels of 1 .. 64 segments by size class, largest first, a class from a multiple of its size
    small = np.flatnonzero((counts > 0) & (counts <= MAX_NETWORK))
    cls = np.searchsorted(sizes, np.arange(MAX_NETWORK + 1))[counts[small]]     # counts <= sizes[cls]
    order = A.order_by_count(counts[small], descending=True)     # classes descending; lanes as AVSM inserts them
    cs, size_of = cls[order], np.asarray(sizes, np.int64)
    lane_texel, lane_size, n_cls, pos = small[order], size_of[cs], np.bincount(cls, minlength=len(sizes)), 0
    first, cstart = np.searchsorted(-cs, -np.arange(len(sizes))), np.zeros(len(sizes), np.int64)
    for c in range(len(sizes) - 1, -1, -1):
        cstart[c] = pos = -(-pos // sizes[c]) * sizes[c]
        pos += int(n_cls[c]) * sizes[c]
    slot = cstart[cs] + (np.arange(cs.size) - first[cs]) * lane_size
    base[lane_texel] = slot
    slots = -(-max(pos, 1) // MAX_NETWORK) * MAX_NETWORK
    out = dict(n=int(counts.sum()), sizes=sizes, big=None, total=slots)
    if small.size:
        lane_t = _u32(lane_texel)
        out.update(texel=lane_texel, start=dr.gather(UInt32, off, lane_t), packet=_u32(slot // lane_size))
        out["count"] = dr.gather(UInt32, off, lane_t + 1) - out["start"]
    big_t = np.flatnonzero(counts > MAX_NETWORK)
    if big_t.size:                                    # blocks of MAX_NETWORK, then merges
        cb = counts[big_t]
        nblk = -(-cb // MAX_NETWORK)
        region = np.concatenate([[0], np.cumsum(nblk * MAX_NETWORK)])
        base[big_t] = slots + np.cumsum(cb) - cb      # after the packets, in texel order
        out["total"] = slots + -(-int(cb.sum()) // MAX_NETWORK) * MAX_NETWORK    # packet stores: whole packets
        blk_r = np.arange(nblk.sum()) - np.repeat(np.cumsum(nblk) - nblk, nblk)    # block within texel
        blk_n = np.minimum(np.repeat(cb, nblk) - blk_r * MAX_NETWORK, MAX_NETWORK)
        p2 = tuple(x for x in sizes if x & (x - 1) == 0)   # blocks start at multiples of 64: powers of two
        blk_c = np.searchsorted(p2, blk_n)            # a texel's last block: the network of its size class
        order = np.argsort(-blk_c, kind="stable")     # lanes grouped by class, largest first
        blk_t, blk_r, blk_n, blk_c = np.repeat(big_t, nblk)[order], blk_r[order], blk_n[order], blk_c[order]
        dest = np.repeat(region[:-1], nblk)[order] + blk_r * MAX_NETWORK              # a multiple of 64
        start = dr.gather(UInt32, off, _u32(blk_t)) + _u32(blk_r * MAX_NETWORK)
        span, widest, passes, w = nblk * MAX_NETWORK, int((nblk * MAX_NETWORK).max()), [], MAX_NETWORK
        while w < widest:                             # pass of width w: lanes merge run pairs of 2 w
            pairs = -(-span // (2 * w))
            t = np.repeat(np.arange(big_t.size), pairs)
            a0 = region[t] + 2 * w * (np.arange(pairs.sum()) - np.repeat(np.cumsum(pairs) - pairs, pairs))
            rend = region[t] + cb[t]                  # the real words: no pads in the runs
            mid, end = np.minimum(a0 + w, rend), np.minimum(a0 + 2 * w, rend)
            final = 2 * w >= widest                   # one lane per texel: the whole texel
            n, dst = (cb[t], base[big_t][t]) if final else (end - a0, a0)
            # lanes in texel order: sequential memory (faster than longest first)
            passes.append(dict(a0=_u32(a0), mid=_u32(mid), end=_u32(end), final=final, n=_u32(n), dst=_u32(dst)))
            w *= 2
        size = int(region[-1])
        out["big"] = dict(
            texel=big_t, start=start, count=_u32(blk_n), packet=_u32(dest // np.asarray(p2)[blk_c]), sizes=p2,
            size=size + MAX_NETWORK * (size == out["n"]), passes=passes)   # widths as for the lanes
    total = -(-out["total"] // PACKET_ALIGN) * PACKET_ALIGN
    out["total"] = total + PACKET_ALIGN * (total == out["n"])   # never the segments' width
    out["base"] = _u32(base)
    dr.eval({k: v for k, v in out.items() if dr.is_array_v(v)}, out["big"])
    return out


def view_order(payloads, base, offsets_dr, texel_of):
    """The permutation of a :func:`sort_texels_view` layout: segment ``i`` of texel ``t`` gets
    ``payloads[base[t] + i - offsets[t]]`` (UInt32 of ``texel_of``'s type)."""
    UInt32 = type(texel_of)
    local = dr.arange(UInt32, dr.width(texel_of)) - dr.gather(UInt32, offsets_dr, texel_of)
    return dr.gather(UInt32, payloads, dr.gather(UInt32, base, texel_of) + local)


def sort_texels_view(counts: np.ndarray, offsets_dr, kind: str, sources, ties: bool = True, layout=None, words=False):
    """``(payloads, base, flags, tied)``: texel ``t``'s ``r``-th smallest word has its payload
    (low 32 bits) at ``payloads[base[t] + r]`` (both Dr.Jit UInt32, evaluated; the permutation:
    :func:`view_order`); ``flags`` the :data:`TIE` / :data:`UNSORTED` bits (a Python int);
    ``tied`` the texels (NumPy int64, ascending) where two words share their key.

    counts: (T,) segments per texel (host); offsets_dr: (T+1,) UInt32 offsets; kind, sources:
    the words (:func:`word_function`), distinct inside a texel; ties: look for equal keys
    (else ``tied`` is empty); layout: :func:`plan` of these counts (computed when None);
    words: the whole sorted words (UInt64) instead of payloads."""
    UInt32, UInt64, _, _ = _types()
    lay = plan(counts, offsets_dr) if layout is None else layout
    pay = dr.empty(UInt64 if words else UInt32, lay["total"])
    counter, lane_flags, same = dr.zeros(UInt64, 1), None, None
    if "start" in lay:
        counter, lane_flags = _sort_lanes(kind, sources, lay["start"], lay["count"], lay["packet"], lay["sizes"],
                                          pay, ties)
    big = lay["big"]
    if big is not None:
        cur = dr.empty(UInt64, big["size"])
        counter += _sort_lanes(kind, sources, big["start"], big["count"], big["packet"], big["sizes"], cur, False)[0]
        dr.eval(cur, counter)
        for p in big["passes"]:
            if p["final"]:                            # payloads to their place, equal keys side by side
                same = _merge_pass(cur, pay, p["a0"], p["mid"], p["end"], p["n"], p["dst"], ties)
                if ties:
                    counter += dr.select(dr.any(same), UInt64(1), 0)
            else:
                nxt = dr.empty(UInt64, big["size"])
                _merge_pass(cur, nxt, p["a0"], p["mid"], p["end"], p["n"], p["dst"], False)
                dr.eval(nxt)
                cur = nxt
    dr.eval(pay, counter, lane_flags if ties else None, same if ties else None)
    n_tie, n_unsorted = int(counter[0]) & 0xFFFFFFFF, int(counter[0]) >> 32
    flags = (TIE if n_tie else 0) | (UNSORTED if n_unsorted or big is not None else 0)   # blocks: not checked
    tied = [np.zeros(0, np.int64)]
    if ties and n_tie:                                # lanes whose words share a key -> their texels
        if lane_flags is not None:
            tied.append(lay["texel"][dr.compress((lane_flags & 0xFFFFFFFF) != 0).numpy()])
        if same is not None:
            tied.append(big["texel"][dr.compress(same).numpy()])
    return pay, lay["base"], flags, np.sort(np.concatenate(tied))


def break_ties(payloads, base, offsets_dr, texel_of, key, second):
    """:func:`sort_texels_view`'s payloads (words ``key << 32 | position``; ``key`` UInt32 and
    ``second`` float per segment) with each run of equal keys ordered by ``(second, position)``:
    one lane per segment counts the run's members before it (float ``second``: ``-0.0 == 0.0``)."""
    UInt32 = _types()[0]
    n = dr.width(texel_of)
    tex, offsets_dr = UInt32(texel_of), UInt32(offsets_dr)
    o = dr.gather(UInt32, offsets_dr, tex)
    c = dr.gather(UInt32, offsets_dr, tex + 1) - o
    b = dr.gather(UInt32, base, tex)
    r = dr.arange(UInt32, n) - o
    p = dr.gather(UInt32, payloads, b + r)
    k, s = dr.gather(UInt32, key, p), dr.gather(type(second), second, p)

    def same(j, ok):                                  # slot j of the texel holds key k
        return ok & (dr.gather(UInt32, key, dr.gather(UInt32, payloads, b + j, ok), ok) == k)
    r0 = dr.while_loop((UInt32(r),), lambda j: same(j - 1, j > 0), lambda j: (j - 1,), label="tie_run_start")[0]
    r1 = dr.while_loop((UInt32(r),), lambda j: same(j + 1, j + 1 < c), lambda j: (j + 1,), label="tie_run_end")[0]

    def rank_body(j, rank):
        pj = dr.gather(UInt32, payloads, b + j)
        sj = dr.gather(type(second), second, pj)
        return j + 1, rank + UInt32((sj < s) | ((sj == s) & (pj < p)))
    rank = dr.while_loop((UInt32(r0), dr.zeros(UInt32, n)), lambda j, rank: (j <= r1) & (r0 < r1), rank_body,
                         label="tie_rank")[1]
    out = dr.empty(UInt32, dr.width(payloads))
    dr.scatter(out, p, b + dr.select(r0 < r1, r0 + rank, r))
    return out


def float_of_key(key):
    """The Float32 whose :func:`float_key` is UInt32 ``key`` (``-0.0`` back as ``+0.0``)."""
    u = key ^ dr.select(key >= 0x80000000, type(key)(0x80000000), type(key)(0xFFFFFFFF))
    return dr.reinterpret_array(dr.float32_array_t(type(key)), u)


def _mix32(x, c1, c2):
    """Chris Wellons' "lowbias32" integer hash (x ^= x >> 16; x *= c1; x ^= x >> 15; x *= c2;
    x ^= x >> 16) on uint32 NumPy or Dr.Jit UInt32 arrays (products modulo 2^32)."""
    x = (x ^ (x >> 16)) * c1
    x = (x ^ (x >> 15)) * c2
    return x ^ (x >> 16)


_MIX = (0x7FEB352D, 0x846CA68B)


def shuffle_key(seed: int, texel, rank):
    """Sort key of the ``"random"`` order (:meth:`Segments.in_order`): the 32-bit hash
    ``h(h(h(seed) + texel) + rank)`` (``h``: :func:`_mix32`, sums modulo 2^32) of the seed,
    the texel and the segment's rank in the texel's depth order.  ``texel``, ``rank``: Dr.Jit
    UInt32 (the seed enters as an opaque scalar, one kernel for every seed).  A texel's
    shuffle therefore depends on (seed, texel, its segment count) only, not on threads or on
    the order it came in."""
    s = int(_mix32(np.array([seed], np.uint32), *(np.uint32(m) for m in _MIX))[0])
    return _mix32(_mix32(texel + dr.opaque(type(texel), s), *_MIX) + rank, *_MIX)


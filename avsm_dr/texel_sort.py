"""Sorting every texel's segments on the device: sorting networks in registers, one lane per texel.

Input: one 64-bit *word* per segment in CSR order, ``word = key << 32 | payload`` with the
32-bit sort key in the high half and a payload unique inside the texel in the low half
(the segment's position, or its concatenation index), so that words are distinct and
comparing words is comparing ``(key, payload)``.  Output: for every CSR position
``o_t + r`` the payload of the ``r``-th smallest word of texel ``t``.

* Texels of ``k <= 64`` segments: one lane per texel loads its ``k`` words into registers
  (``B - k`` pads of ``2^64 - 1`` up to its size class ``B``, the next power of two) and
  sorts them with Batcher's odd-even merge sort network (K. E. Batcher, "Sorting networks
  and their applications", AFIPS 1968, section 2), comparators on pads pruned: no memory
  traffic besides one gather per segment and one packet store per texel.  All classes run
  in one kernel, a chain of symbolic conditionals (lanes grouped by class, so a SIMD
  packet runs one network), whose trace is recorded once and replayed (:func:`drjit.freeze`).
  Measured on random-order captures (2 shared cores, kernel time): 1 ms vs 11 ms at 64^2,
  4 ms vs 40 ms at 128^2 (three_columns, up to 60 segments per texel) for ranking every
  segment against every other of its texel (``k`` gathers per segment).
* Longer texels: blocks of 64 sorted by the same network, then bottom-up merges of sorted
  runs, every word placed by a binary search in the partner run (merge path: O. Green,
  R. McColl, D. A. Bader, "GPU merge path", ICS 2012, section 3), one kernel per doubling.
  Memory-bound: on the 48-voxel plume at 1024^2 (41.6 M segments, 35 M of them in texels of
  65-111) the blocks took 0.8-0.95 s, the merge 1.4-1.6 s, the tie check 0.2-0.3 s.

Flags (counted on the device, read back once): :data:`TIE` when two words of a texel share
their key (the caller may need a finer order), :data:`UNSORTED` when some texel's words
were not already increasing in CSR order (always set when a texel exceeds 64).
"""
from __future__ import annotations

import gc
from functools import lru_cache

import drjit as dr
import numpy as np

from . import _arrays as A
from . import backend

#: Largest texel sorted by a network in one lane; longer texels merge sorted blocks of it.
MAX_NETWORK = 64
#: Flag bits returned by :func:`sort_texels`.
TIE, UNSORTED = 1, 2
_PAD = 0xFFFFFFFFFFFFFFFF
#: Replay the recorded sorting kernel (:data:`_sort_lanes_frozen`) instead of tracing it anew.
FREEZE = True


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
    """Host integers as a UInt32 Dr.Jit array, copied from a 64-byte aligned buffer (a mapped
    NumPy buffer's alignment enters the kernel hash: recompiles at random, seconds for the
    64-input network)."""
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


def _network_branch(word_at, size: int, out, ties: bool):
    """``f(start, count, packet) -> flags``: one lane per run ``[start, start + count)``
    (``count <= size``): its words ``word_at(position, valid)`` sorted in registers, stored
    as packet ``packet`` of ``size`` entries of ``out`` (payloads into a UInt32 ``out``,
    whole words into a UInt64 one); flags (UInt64): 1 for equal keys side by side, ``2^32``
    when the run was not already increasing."""
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


def _sort_lanes_traced(kind: str, sources, start, count, packet, out, sizes: tuple, ties: bool):
    UInt32, UInt64, _, _ = _types()
    word_at = word_function(kind, sources)

    def chain(i):
        if i == 0:
            return _network_branch(word_at, sizes[0], out, ties)
        return lambda s, c, p: dr.if_stmt((s, c, p), c > sizes[i - 1], _network_branch(word_at, sizes[i], out, ties),
                                          chain(i - 1), label=f"network_{sizes[i]}")
    flags = chain(len(sizes) - 1)(start, count, packet)
    counter = dr.zeros(UInt64, 1)             # one atomic add per SIMD packet
    dr.scatter_reduce(dr.ReduceOp.Add, counter, flags, UInt32(0), flags != 0, mode=dr.ReduceMode.Local)
    return counter


#: The sorting kernel, frozen (:func:`drjit.freeze`): its trace (thousands of operations for
#: the 64-input network: ~5-10 ms of Python per call, more than the kernel at 64^2) is
#: replayed for new data of any size; one recording per (kind, size classes, ties).
_sort_lanes_frozen = dr.freeze(_sort_lanes_traced, warn_after=64)


def _sort_lanes(kind, sources, start, count, packet, sizes, out, ties: bool):
    """Sort the runs of all lanes (lanes ordered by decreasing size class) in one kernel: a
    chain of symbolic conditionals picks the network of each lane's size class ``sizes``
    (ascending); SIMD packets whose lanes share a class run one network.  Returns the
    lanes' flags summed (UInt64, width 1; see :func:`_network_branch`)."""
    args = (kind, tuple(sources), start, count, packet, out, tuple(sizes), ties)
    if not FREEZE:
        return _sort_lanes_traced(*args)
    # no garbage collection while a recording may run: a collected array that maps NumPy
    # memory releases it through a host callback, which aborts the process mid-recording
    # ("enqueue_host_func(): this function cannot be recorded")
    enabled = gc.isenabled()
    gc.disable()
    try:
        return _sort_lanes_frozen(*args)
    finally:
        if enabled:
            gc.enable()


def _merge_pass(cur, start, length, width: int):
    """Merge the sorted runs ``[s + 2 m width, s + (2 m + 1) width)`` and the next one of
    every range ``[start, start + length)`` (one lane per word of ``cur``): each word's slot
    is its offset in its own run plus the number of partner-run words below it."""
    UInt32, UInt64, _, _ = _types()
    n = dr.width(cur)
    i = dr.arange(UInt32, n)
    local = i - start
    run = local & UInt32(0xFFFFFFFF ^ (width - 1))
    ps = start + (run ^ width)                         # partner run
    end = start + length
    base, span = UInt32(ps), dr.select(ps < end, dr.minimum(ps + width, end) - ps, 0)
    for _ in range(width.bit_length()):                # lower bound: words are distinct
        half = span >> 1
        m = base + half
        go = (span > 0) & (dr.gather(UInt64, cur, m, span > 0) < cur)
        base = dr.select(go, m + 1, base)
        span = dr.select(go, span - half - 1, half)
    slot = start + (run & UInt32(0xFFFFFFFF ^ width)) + (local - run) + (base - ps)
    out = dr.empty(UInt64, n)
    dr.scatter(out, cur, slot)
    return out


def plan(counts: np.ndarray, offsets_dr) -> dict:
    """The layout of a sort (depends on the texel counts only, so callers may keep it):
    lanes per size class, packet and slot of every texel, blocks of the long texels."""
    UInt32 = _types()[0]
    off = UInt32(offsets_dr)
    counts = np.asarray(counts, np.int64)
    base = np.zeros(counts.size, np.int64)
    top = int(min(counts.max(initial=1), MAX_NETWORK))
    sizes = tuple(1 << b for b in range(1, max(top - 1, 1).bit_length() + 1))   # 2 .. next power of 2
    cls = np.searchsorted(sizes, counts)                                         # counts <= sizes[cls]
    lanes, packets, pos = [], [], 0
    for c in range(len(sizes) - 1, -1, -1):           # largest first: packet offsets stay aligned
        sel = np.flatnonzero((cls == c) & (counts > 0))
        if sel.size:
            base[sel] = pos + np.arange(sel.size) * sizes[c]
            lanes.append(sel)
            packets.append(pos // sizes[c] + np.arange(sel.size))
            pos += sel.size * sizes[c]
    out = dict(off=off, n=int(counts.sum()), sizes=sizes, slots=-(-max(pos, 1) // MAX_NETWORK) * MAX_NETWORK,
               big=None)
    if lanes:
        lane_t = _u32(np.concatenate(lanes))
        out["start"] = dr.gather(UInt32, off, lane_t)
        out["count"] = dr.gather(UInt32, off, lane_t + 1) - out["start"]
        out["packet"] = _u32(np.concatenate(packets))
    big_t = np.flatnonzero(counts > MAX_NETWORK)
    if big_t.size:                                    # blocks of MAX_NETWORK, then merges
        nblk = -(-counts[big_t] // MAX_NETWORK)
        region = np.concatenate([[0], np.cumsum(nblk * MAX_NETWORK)])
        base[big_t] = region[:-1] | (1 << 31)
        blk_r = np.arange(nblk.sum()) - np.repeat(np.cumsum(nblk) - nblk, nblk)    # block within texel
        start = dr.gather(UInt32, off, _u32(np.repeat(big_t, nblk))) + _u32(blk_r * MAX_NETWORK)
        lanes_per_texel = nblk * MAX_NETWORK
        out["big"] = dict(
            start=start, count=_u32(np.minimum(np.repeat(counts[big_t], nblk) - blk_r * MAX_NETWORK, MAX_NETWORK)),
            size=int(region[-1]), widest=int(lanes_per_texel.max()),
            rstart=_u32(np.repeat(region[:-1], lanes_per_texel)),     # per lane: its texel's region
            rlen=_u32(np.repeat(lanes_per_texel, lanes_per_texel)),
            real=_u32(np.repeat(counts[big_t], lanes_per_texel)))
    out["base"] = _u32(base)
    dr.eval({k: v for k, v in out.items() if dr.is_array_v(v)}, out["big"])
    return out


def sort_texels(counts: np.ndarray, offsets_dr, texel_of, kind: str, sources, ties: bool = True, layout=None):
    """``(payloads, flags)``: ``payloads`` (Dr.Jit UInt32, S, lazy) holds at CSR position
    ``o_t + r`` the payload (low 32 bits) of texel ``t``'s ``r``-th smallest word; ``flags``
    the :data:`TIE` / :data:`UNSORTED` bits (a Python int; one device round trip).

    counts: (T,) segments per texel (host); offsets_dr: (T+1,) UInt32 offsets; texel_of:
    (S,) UInt32 texel of every segment; kind, sources: the words (:func:`word_function`),
    distinct inside a texel; ties: look for equal keys; layout: :func:`plan` of these counts
    (computed when None)."""
    UInt32, UInt64, _, _ = _types()
    lay = plan(counts, offsets_dr) if layout is None else layout
    off, tex = lay["off"], UInt32(texel_of)
    small = dr.empty(UInt32, lay["slots"])
    counter = dr.zeros(UInt64, 1)
    if "start" in lay:
        counter = _sort_lanes(kind, sources, lay["start"], lay["count"], lay["packet"], lay["sizes"], small, ties)
    big = lay["big"]
    if big is not None:
        cur = dr.empty(UInt64, big["size"])
        counter += _sort_lanes(kind, sources, big["start"], big["count"], dr.arange(UInt32, dr.width(big["start"])),
                               (MAX_NETWORK,), cur, ties)
        width = MAX_NETWORK
        while width < big["widest"]:
            cur = _merge_pass(cur, big["rstart"], big["rlen"], width)
            dr.eval(cur)
            width *= 2
        if ties:                                      # equal keys side by side after the merge
            q = dr.arange(UInt32, big["size"] - 1)
            ok = (q + 1 - dr.gather(UInt32, big["rstart"], q)) < dr.gather(UInt32, big["real"], q)
            same = ok & ((dr.gather(UInt64, cur, q) ^ dr.gather(UInt64, cur, q + 1)) < (1 << 32))
            counter += dr.select(dr.any(same), UInt64(1), 0)
    dr.eval(small, counter)
    n_tie, n_unsorted = int(counter[0]) & 0xFFFFFFFF, int(counter[0]) >> 32
    flags = (TIE if n_tie else 0) | (UNSORTED if n_unsorted or big is not None else 0)   # blocks: not checked
    local = dr.arange(UInt32, lay["n"]) - dr.gather(UInt32, off, tex)
    b = dr.gather(UInt32, lay["base"], tex)
    if big is None:
        return dr.gather(UInt32, small, b + local), flags
    isbig = b >= (1 << 31)
    from_big = UInt32(dr.gather(UInt64, cur, (b & 0x7FFFFFFF) + local, isbig))
    return dr.select(isbig, from_big, dr.gather(UInt32, small, b + local, ~isbig)), flags

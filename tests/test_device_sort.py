"""Per-texel sorting on the device: the sorting networks of
:mod:`avsm_dr.texel_sort` and ``Segments.sorted()`` on adversarial input, always equal to
a stable host lexsort by (texel, z0, z1)."""
from __future__ import annotations

import itertools
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import avsm_dr as ad
from helpers import compiled_kernels
import drjit as dr
from avsm_dr import texel_sort as TS


@pytest.mark.parametrize("n", range(1, 13))
def test_network_sorts_every_zero_one_input(n):
    """The 0-1 principle (Knuth, TAOCP vol. 3, 5.3.4): a comparator network that sorts all
    2^n sequences of zeros and ones sorts every input of n keys."""
    net = TS.network(n)
    for bits in itertools.product((0, 1), repeat=n):
        x = list(bits)
        for i, j in net:
            if x[i] > x[j]:
                x[i], x[j] = x[j], x[i]
        assert x == sorted(x)


@pytest.mark.parametrize("n", [13, 24, 33, 47, 64])
def test_network_sorts_random_keys_with_repeats(rng, n):
    net = TS.network(n)
    for _ in range(200):
        x = list(rng.integers(0, 5, n))
        for i, j in net:
            if x[i] > x[j]:
                x[i], x[j] = x[j], x[i]
        assert x == sorted(x)


def _host(seg):
    h = seg.numpy()
    perm = np.lexsort((h["z1"], h["z0"], np.repeat(np.arange(seg.n_texels), seg.counts)))
    return {k: h[k][perm] for k in ("z0", "z1", "optical_depth")}


def _segments(counts, z0, rng, z1=None):
    off = np.concatenate([[0], np.cumsum(counts)])
    z1 = z0 + rng.uniform(0.0, 1.0, z0.size) if z1 is None else z1
    return ad.Segments.from_arrays(off, z0, z1, optical_depth=rng.uniform(0.0, 2.0, z0.size))


def _check(seg, network: bool):
    """sorted() equals the host lexsort; ``network``: the networks saw distinct z0 in every
    texel (else equal z0 were flagged and sorted again by z1, then z0)."""
    z0 = dr.detached_t(seg.Float)(dr.detach(seg.z0))
    flags = TS.sort_texels_view(seg.counts, seg.offsets_dr(), "float", (z0,))[2]
    assert bool(flags & TS.TIE) != network
    got = seg.sorted()
    assert got.sorted_by_depth and np.array_equal(got.offsets, seg.offsets)
    want = _host(seg)
    for k, v in got.numpy().items():
        if k != "offsets":
            assert np.array_equal(v, want[k]), k


def _distinct(rng, n):
    """n distinct float32 depths, some negative (sign handling of the integer keys)."""
    z = np.unique(rng.uniform(-50.0, 50.0, 3 * n).astype(np.float32))
    return rng.permutation(z)[:n].astype(np.float64)


@pytest.mark.parametrize("layout", ["every_class", "empty_texels", "one_long_texel", "long_texels"])
def test_random_order_matches_the_host_lexsort(backend, rng, layout):
    """Texels of 0..70 segments (every size class, the 64-segment network and blocks beyond
    it), long texels (64-blocks merged, 1000 segments), empty texels between them."""
    counts = {"every_class": np.arange(71), "empty_texels": rng.integers(0, 3, 400) * rng.integers(0, 20, 400),
              "one_long_texel": np.array([0, 3, 1000, 0, 5]),
              "long_texels": np.array([65, 128, 129, 200, 7, 0, 300])}[layout]
    z0 = _distinct(rng, int(counts.sum()))
    _check(_segments(counts, z0, rng), network=True)


def test_already_sorted_and_reversed(backend, rng):
    counts = np.array([5, 0, 64, 1, 70, 2])
    off = np.concatenate([[0], np.cumsum(counts)])
    z0 = _distinct(rng, int(counts.sum()))
    for t in range(counts.size):
        z0[off[t]:off[t + 1]] = np.sort(z0[off[t]:off[t + 1]])
    seg = _segments(counts, z0, rng)
    small = _segments(counts[:4], z0[:off[4]], rng)          # no texel beyond 64: checked
    assert small.depth_order() is None and small.sorted().z0 is small.z0
    _check(seg, network=True)
    for t in range(counts.size):
        z0[off[t]:off[t + 1]] = z0[off[t]:off[t + 1]][::-1]
    _check(_segments(counts, z0, rng), network=True)


@pytest.mark.parametrize("counts", [[40, 3, 0, 9], [150, 2]])
def test_equal_depths_fall_back_to_the_exact_order(backend, rng, counts):
    """All z0 equal (z1 decides, then the stored order), and -0.0 next to 0.0: the networks
    see equal keys and the rank sort (or host lexsort) orders them."""
    counts = np.array(counts)
    n = int(counts.sum())
    z1 = rng.integers(0, 3, n) * 0.5
    _check(_segments(counts, np.zeros(n), rng, z1=z1), network=False)
    z0 = _distinct(rng, n)
    z0[:2] = 0.0
    seg = _segments(counts, z0, rng)
    seg.z0 = dr.select(dr.arange(ad.backend.types().UInt32, n) == 1, seg.Float(-0.0), seg.z0)
    _check(seg, network=False)


def test_long_texel_with_equal_depths_in_different_blocks(backend, rng):
    """Equal z0 that meet only in a merge of 64-blocks are detected there too."""
    z0 = _distinct(rng, 200)
    z0[150] = z0[3]
    _check(_segments(np.array([200]), z0, rng), network=False)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_long_texels_with_ties_sort_on_the_device(backend, rng, dtype, monkeypatch):
    """Texels of 3000 and 700 segments with z0 and z1 from a few values (long runs of equal
    keys, once a host lexsort's case): the device order equals the host lexsort, and no host
    copy of the segments is made for it."""
    counts = np.array([3000, 0, 700, 5])
    n = int(counts.sum())
    z0 = rng.integers(0, 7, n) * 0.5
    seg = ad.Segments.from_arrays(np.r_[0, np.cumsum(counts)], z0, z0 + rng.integers(0, 3, n) * 0.25,
                                  optical_depth=rng.uniform(0.0, 2.0, n), dtype=dtype)
    want = _host(seg)
    with monkeypatch.context() as m:
        m.setattr(ad.Segments, "numpy", lambda self: pytest.fail("host copy"))
        got = seg.sorted()
        dr.eval(got.z0, got.z1, got.optical_depth)
    for k, v in got.numpy().items():
        if k != "offsets":
            assert np.array_equal(v, want[k]), k


def test_tied_texels_are_reported(backend, rng):
    """``sort_texels_view``'s ``tied``: exactly the texels holding two equal keys, network
    lanes and merged long texels alike."""
    counts = np.array([5, 40, 0, 3, 200, 150, 9])
    z0 = _distinct(rng, int(counts.sum()))
    off = np.r_[0, np.cumsum(counts)]
    for t in (1, 4, 6):                              # a repeat inside texels 1, 4 and 6
        z0[off[t] + counts[t] - 1] = z0[off[t]]
    seg = _segments(counts, z0, rng)
    z = dr.detached_t(seg.Float)(dr.detach(seg.z0))
    _, _, flags, tied = TS.sort_texels_view(seg.counts, seg.offsets_dr(), "float", (z,))
    assert flags & TS.TIE and tied.tolist() == [1, 4, 6]
    assert TS.sort_texels_view(seg.counts, seg.offsets_dr(), "float", (z,), ties=False)[3].size == 0


def test_gradients_follow_the_permutation(backend, rng):
    counts = np.array([3, 0, 4])
    z0 = _distinct(rng, 7)
    seg = _segments(counts, z0, rng)
    dr.enable_grad(seg.optical_depth)
    out = seg.sorted()
    w = ad.backend.types().Float(np.arange(7, dtype=np.float32))
    dr.backward(dr.sum(out.optical_depth * w))
    perm = np.lexsort((seg.numpy()["z0"], np.repeat(np.arange(3), counts)))
    want = np.zeros(7)
    want[perm] = np.arange(7)
    assert np.array_equal(np.asarray(dr.grad(seg.optical_depth)), want)


def _map(rng, counts, ties=False):
    """Random-order segments with texels ``counts`` and light optical depths (compression
    runs); ``ties``: z0 on a grid of 1 and z1 of 0.5, so equal z0 and equal (z0, z1) in most
    texels (sorted again by z1 then position)."""
    n = int(np.sum(counts))
    z0 = _distinct(rng, n)
    z1 = z0 + rng.uniform(0.0, 1.0, n)
    if ties == "few":                 # one texel (the 4th) tied: below 1/8 of the segments
        tied = slice(int(np.sum(counts[:3])), int(np.sum(counts[:4])))
        z0[tied] = np.round(z0[tied])
        z1[tied] = z0[tied] + rng.integers(0, 3, counts[3]) * 0.5
    elif ties:
        z0 = np.round(z0)
        z1 = z0 + rng.integers(0, 3, n) * 0.5
    return ad.Segments.from_arrays(np.concatenate([[0], np.cumsum(counts)]), z0, z1,
                                   optical_depth=rng.uniform(0.0, 0.2, n))


@pytest.mark.parametrize("ties", [False, "few", "few by key passes", True])
def test_depth_view_is_the_order_of_sorted(backend, rng, ties, monkeypatch):
    """Texel t's r-th segment by (z0, z1, position) is ``index[start[t] + r]``: packets of
    the size classes, and texels beyond 64 (three merge passes for 300) after them; with
    ``words`` the same positions in the low halves and the segments' z0 keys in the high ones
    (ties: few go through ``_untie``, on the host up to HOST_UNTIE segments, else by key
    passes on the device; many through ``break_ties``)."""
    counts = np.array([4, 0, 64, 65, 300, 1, 17, 129, 40])
    if ties == "few by key passes":
        monkeypatch.setattr(ad.segments, "HOST_UNTIE", 0)
    elif ties == "few":                               # 65 tied segments: NumPy, no key passes
        monkeypatch.setattr(ad.Segments, "_key_sort", lambda *a: pytest.fail("key passes for 65 tied segments"))
    seg = _map(rng, counts, "few" if ties == "few by key passes" else ties)
    h = seg.numpy()
    perm = np.lexsort((h["z1"], h["z0"], np.repeat(np.arange(counts.size), counts)))
    idx, start = (np.asarray(a) for a in seg.depth_view())
    words, start_w = seg.depth_view(words=True)
    assert dr.type_v(words) == dr.VarType.UInt64 and np.array_equal(np.asarray(start_w), start)
    z0_back = np.asarray(TS.float_of_key(ad.backend.types().UInt32(np.asarray(words >> 32).astype(np.uint32))))
    words = np.asarray(words)
    off = seg.offsets
    for t, c in enumerate(counts):
        assert np.array_equal(idx[start[t]:start[t] + c], perm[off[t]:off[t + 1]]), t
        assert np.array_equal(words[start[t]:start[t] + c] & 0xFFFFFFFF, perm[off[t]:off[t + 1]]), t
        assert np.array_equal(z0_back[start[t]:start[t] + c], h["z0"][perm[off[t]:off[t + 1]]]), t


def test_float_of_key_inverts_float_key(backend):
    z = np.array([0.0, -0.0, 1e-45, -1e-45, 1.5, -1.5, 3.4e38, -3.4e38, np.inf, -np.inf], np.float32)
    key = TS.float_key(ad.backend.types().Float(z))
    back = np.asarray(TS.float_of_key(key))
    assert np.array_equal(back, np.where(z == 0, 0.0, z)) and not np.signbit(back[1])
    assert np.all(np.diff(np.asarray(key)[np.argsort(z, kind="stable")].astype(np.int64)) >= 0)


def test_float64_depth_view_gives_positions_with_words(backend, rng):
    counts = np.array([3, 70, 5])
    seg = _map(rng, counts)
    seg64 = ad.Segments.from_arrays(seg.offsets, *(ad.backend.types().Float64(np.asarray(a, np.float64))
                                                   for a in (seg.z0, seg.z1)),
                                    optical_depth=ad.backend.types().Float64(np.asarray(seg.optical_depth, np.float64)))
    view = seg64.depth_view(words=True)
    assert dr.type_v(view[0]) == dr.VarType.UInt32
    assert np.array_equal(np.asarray(view[0]), np.asarray(seg64.depth_view()[0]))


@pytest.mark.parametrize("ties", [False, "few", True])
def test_sorted_avsm_reads_the_order_bit_for_bit(backend, rng, ties):
    """AVSM with sort=True reads through :meth:`Segments.depth_view` (no sorted copies): its
    nodes, used counts and stats equal those built from ``sorted()`` bit for bit."""
    seg = _map(rng, np.array([0, 3, 9, 33, 64, 65, 129, 300, 2]), ties)
    for nodes in (4, 8):
        got, want = (ad.build("avsm", s, nodes=nodes, sort=True) for s in (seg, seg.sorted()))
        for a, b in zip(got.nodes_numpy(), want.nodes_numpy()):
            assert a.tobytes() == b.tobytes()
        assert np.array_equal(got.used, want.used) and got.stats == want.stats


def test_new_counts_compile_nothing(backend, rng):
    """A second random-order map with other texel counts (other merge passes, other sizes)
    sorts and builds sorted AVSM-8 without compiling a kernel, equal depths or not: sizes
    are not literals."""
    def run(counts):
        out = []
        for ties in (False, True):
            seg = _map(rng, counts, ties)
            s = seg.sorted()
            out += [s.z0, s.z1, s.optical_depth, *ad.build("avsm", seg, nodes=8, sort=True).depths]
        return out

    dr.eval(run(np.array([3, 70, 0, 64, 200, 5])))
    assert [compiled_kernels(lambda: run(np.array(c))) for c in
            ([9, 0, 90, 64, 300, 2, 130, 31], [64, 5, 77, 0, 1, 260, 40])] == [0, 0]


def test_chunked_sorted_builds_compile_no_kernel_per_chunk(backend, rng, monkeypatch):
    """A sorted build in chunks of whole texels (its sort buffers above twice the output) writes
    each chunk's nodes at the chunk's first texel: that offset is an array, not a literal, so a
    second map, chunked at other texels, compiles nothing (the offset as a literal compiled one
    insertion kernel per chunk: about 100 per frame of the temporal study, 40 s of a 1.4 s frame)."""
    from avsm_dr.representations import avsm
    monkeypatch.setattr(avsm, "MIN_CHUNK_BYTES", 1)
    chunks = []
    monkeypatch.setattr(ad.Segments, "texel_range", lambda self, a, b, f=ad.Segments.texel_range:
                        chunks.append((a, b)) or f(self, a, b))

    def run(counts):
        return ad.build("avsm", _map(rng, counts), nodes=4, sort=True).depths

    dr.eval(run(np.r_[40, rng.integers(5, 60, 199)]))
    assert len(chunks) > 3                                    # the build did run in chunks
    second = np.r_[45, rng.integers(5, 60, 230)]
    assert compiled_kernels(lambda: run(second)) == 0


def test_sorts_right_under_debug_and_kernel_history_flags(backend, rng):
    """Sorts at 64^2 then 128^2 with the same size classes, with Dr.Jit's ``Debug`` and
    ``KernelHistory`` flags on (a user debugging, the timers): each equals the host stable
    argsort.  The sort used to replay a recording (``dr.freeze``) of its kernel; under these
    flags the 128^2 replays put other texels' or uninitialised payloads in texels of one and
    two segments, and the consumers' gathers read out of bounds (``Debug`` showed 263
    out-of-bounds reads in ``experiments frame --quick`` with the recording, none without it;
    found while chasing the suite's random-order segfault, which has a cause still open).
    Tolerance: none, orders are exact."""
    with dr.scoped_set_flag(dr.JitFlag.Debug, True), dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        for texels in (4096, 4096, 16384, 16384):
            counts = np.r_[19, rng.integers(0, 8, texels - 1)]
            n = int(counts.sum())
            seg = ad.Segments.from_arrays(np.r_[0, np.cumsum(counts)], rng.uniform(0, 1, n),
                                          rng.uniform(1, 2, n), optical_depth=np.ones(n))
            z0 = dr.detached_t(seg.Float)(seg.z0)
            pay, base, _, _ = TS.sort_texels_view(counts, seg.offsets_dr(), "float", (z0,))
            dr.kernel_history()
            p, b, z, off = np.asarray(pay), np.asarray(base), np.asarray(z0), np.r_[0, np.cumsum(counts)]
            got = np.concatenate([p[b[t]:b[t] + counts[t]] for t in range(texels)])
            want = np.concatenate([off[t] + np.argsort(z[off[t]:off[t + 1]], kind="stable")
                                   for t in range(texels)])
            assert np.array_equal(got, want), texels


_CONCURRENT_SORTS = textwrap.dedent("""
    import faulthandler, gc, sys, threading
    import numpy as np
    import avsm_dr as ad
    import drjit as dr
    from avsm_dr import texel_sort as TS

    faulthandler.dump_traceback_later(float(sys.argv[1]), exit=True)   # a hang: stacks, exit 1
    Float = ad.backend.types().Float
    KEYS = [(top, ties) for top in (2, 4, 8, 16, 32) for ties in (False, True)]
    THREADS, errors, stop = 3, [], threading.Event()
    barrier = threading.Barrier(THREADS)

    def sorter(seed):
        rng = np.random.default_rng(seed)
        try:
            for top, ties in KEYS:
                counts = np.r_[top, rng.integers(0, top + 1, int(rng.integers(30, 300)))]
                n = int(counts.sum())
                seg = ad.Segments.from_arrays(np.r_[0, np.cumsum(counts)], rng.uniform(-1, 1, n),
                                              rng.uniform(1, 2, n), optical_depth=np.ones(n))
                z0 = dr.detached_t(seg.Float)(seg.z0)
                barrier.wait()                        # the threads record each key at once
                pay, base, _, _ = TS.sort_texels_view(seg.counts, seg.offsets_dr(), "float", (z0,), ties)
                pay, base, h = np.asarray(pay), np.asarray(base), seg.numpy()["z0"].astype(np.float32)
                for t in np.flatnonzero(counts):
                    o, c = seg.offsets[t], counts[t]
                    if not np.array_equal(pay[base[t]:base[t] + c], o + np.argsort(h[o:o + c], kind="stable")):
                        errors.append(("wrong order", seed, top, ties, t))
                        break
        except Exception as exc:
            errors.append(repr(exc))
            barrier.abort()

    def collector():                                  # explicit collections of NumPy-mapped cycles
        while not stop.is_set():
            junk = [Float(np.ones(500 + k, np.float32)) for k in range(10)]
            junk.append(junk)
            del junk
            gc.collect()

    c = threading.Thread(target=collector, daemon=True)
    c.start()
    for r in range(3):
        ts = [threading.Thread(target=sorter, args=(10 * r + s,)) for s in range(THREADS)]
        [t.start() for t in ts]
        [t.join() for t in ts]
    stop.set()
    c.join()
    print("errors", errors)
    sys.exit(0 if not errors else 2)
""")


def test_concurrent_sorts_with_collections_finish(tmp_path):
    """Three threads sort (each size-class key at once) while a fourth runs ``gc.collect()``
    on cycles of NumPy-mapped arrays.  With the sort's kernel recorded and replayed
    (``dr.freeze``, since removed) and not serialised, 4 of 4 runs of this script failed or
    aborted (``jit_var(): unknown variable``), and an earlier version hung.  In a subprocess
    with a timeout: every sort is right and nothing hangs."""
    script = tmp_path / "concurrent_sorts.py"
    script.write_text(_CONCURRENT_SORTS)
    try:
        r = subprocess.run([sys.executable, str(script), "150"], capture_output=True, text=True, timeout=200)
    except subprocess.TimeoutExpired as exc:
        pytest.fail(f"concurrent sorts hung: {exc.stdout!r} {exc.stderr!r}")
    assert r.returncode == 0, (r.stdout + r.stderr)[-3000:]

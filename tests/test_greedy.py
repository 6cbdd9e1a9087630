"""``greedy`` on large texels: the heap removal order
(:func:`avsm_dr.representations.greedy.vw_removal_rank_heap`, O(K log K)) equals the
previous O(K^2) scan (tests/reference/greedy_ref.py) exactly, ties included, and texels
above ``HEAP_POINTS`` points never take the scan."""
import heapq

import numpy as np
import pytest

import avsm_dr as ad
from avsm_dr.representations import greedy as greedy_mod
from reference import greedy_ref


def _curves(seed, n_curves=120, max_points=300):
    """Monotone curves with many exact ties: quantised depths (steps: repeated depths)
    and values, collinear runs (equal areas), flat runs (zero areas), huge depths."""
    rng = np.random.default_rng(seed)
    for c in range(n_curves):
        n = int(rng.integers(1, max_points))
        kind = c % 5
        if kind == 0:
            x = np.sort(rng.uniform(0, 1, n))
            v = np.sort(rng.uniform(0, 1, n))[::-1]
        elif kind == 1:
            x = np.sort(rng.integers(0, 12, n).astype(float))
            v = np.sort(rng.integers(0, 5, n) / 4.0)[::-1]
        elif kind == 2:
            x = np.linspace(0, 1, n)
            v = np.clip(1 - np.round(rng.uniform(0, 2, n).cumsum() / max(n, 1), 1), 0, 1)
        elif kind == 3:
            x = np.sort(rng.uniform(-1e300, 1e300, n))   # large, finite areas
            v = np.sort(rng.uniform(0, 1, n))[::-1]
        else:
            x = np.linspace(0, 1, n)
            v = np.linspace(1, 0, n)                    # all areas 0 (up to rounding)
        yield x, v


@pytest.mark.parametrize("seed", range(3))
def test_heap_order_equals_the_quadratic_scan(seed):
    checked = 0
    for x, v in _curves(seed):
        n = x.size
        with np.errstate(all="ignore"):
            want = np.minimum(greedy_ref.vw_removal_rank(x[None], v[None], np.array([n]))[0], n)
        np.testing.assert_array_equal(greedy_mod.vw_removal_rank_heap(x, v, n), want)
        checked += n >= 3
    assert checked >= 100


def test_heap_orders_overflowing_areas():
    # depths near +-1.5e308: differences overflow to inf and inf - inf to NaN (the old
    # scan took an inf area for "removed" and indexed past the end); both orders remove
    # every interior point once, alike
    rng = np.random.default_rng(3)
    n = 200
    x = np.sort(rng.uniform(0, 1.5e308, n) * rng.choice([-1.0, 1.0], n))
    v = np.sort(rng.uniform(0, 1, n))[::-1]
    rank = greedy_mod.vw_removal_rank_heap(x, v, n)
    assert sorted(rank[1:-1]) == list(range(n - 2)) and rank[0] == rank[-1] == n
    with np.errstate(all="ignore"):
        scan = greedy_mod.vw_removal_rank(x[None], v[None], np.array([n]))[0]
    np.testing.assert_array_equal(rank, np.minimum(scan, n))


def test_heap_does_o_n_heap_operations(monkeypatch):
    # lazy deletion: one push per point and two per removal, so pops <= 3 n; each is
    # O(log n): O(n log n) in all (the scan was n argmins over n points)
    counts = {"pop": 0, "push": 0}
    pop, push = heapq.heappop, heapq.heappush

    def counting_pop(h):
        counts["pop"] += 1
        return pop(h)

    def counting_push(h, item):
        counts["push"] += 1
        return push(h, item)

    monkeypatch.setattr(heapq, "heappop", counting_pop)
    monkeypatch.setattr(heapq, "heappush", counting_push)
    rng = np.random.default_rng(4)
    n = 20000
    greedy_mod.vw_removal_rank_heap(np.sort(rng.uniform(0, 1, n)), np.sort(rng.uniform(0, 1, n))[::-1], n)
    assert counts["push"] <= 2 * n and counts["pop"] <= 3 * n


def _random_segments(rng, counts):
    off = np.r_[0, np.cumsum(counts)]
    S = int(off[-1])
    z0 = rng.uniform(0, 1, S).round(3)                  # rounded: coincident ends, ties
    z1 = z0 + np.where(rng.random(S) < 0.15, 0.0, rng.uniform(0, 0.05, S).round(3))
    tau = rng.exponential(0.05, S)
    return ad.Segments.from_arrays(off, z0, z1, optical_depth=tau, dtype="float64")


def test_large_texels_take_the_heap_and_keep_the_same_nodes(monkeypatch):
    rng = np.random.default_rng(7)
    seg = _random_segments(rng, [3, 0, 700, 2500, 40, 1])     # 700 and 2500 segments: > 1024 points
    scan = greedy_mod.vw_removal_rank

    def scan_small_only(x, v, count):
        assert x.shape[1] <= greedy_mod.HEAP_POINTS, "the O(K^2) scan ran on a large texel"
        return scan(x, v, count)

    monkeypatch.setattr(greedy_mod, "vw_removal_rank", scan_small_only)
    pts, rank = greedy_mod.removal_ranks(seg)
    off = pts["off"]
    assert np.diff(off).max() > greedy_mod.HEAP_POINTS
    for t in range(seg.n_texels):
        s = slice(off[t], off[t + 1])
        n = off[t + 1] - off[t]
        if n == 0:
            continue
        want = greedy_ref.vw_removal_rank(pts["z"][None, s], pts["v"][None, s], np.array([n]))[0]
        np.testing.assert_array_equal(rank[s], np.minimum(want, n))
    # and the built nodes equal those of an all-scan build (the previous algorithm)
    monkeypatch.setattr(greedy_mod, "vw_removal_rank", scan)
    for N in (2, 8, 64):
        heap_rep = ad.build("greedy", seg, nodes=N)
        monkeypatch.setattr(greedy_mod, "HEAP_POINTS", 10 ** 9)
        scan_rep = ad.build("greedy", _random_segments(np.random.default_rng(7), [3, 0, 700, 2500, 40, 1]), nodes=N)
        monkeypatch.setattr(greedy_mod, "HEAP_POINTS", 1024)
        for a, b in zip(heap_rep.nodes_numpy(), scan_rep.nodes_numpy()):
            np.testing.assert_array_equal(a, b)

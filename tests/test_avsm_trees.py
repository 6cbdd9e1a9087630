"""The pairwise (tree) reductions in AVSM's loop body: ``_arrays.pairwise``, :func:`.avsm.bracket`
and the least-metric search of :func:`._avsm_insertion.remove_refit` take the same decisions as
the sequential scans they replaced (last node at or before x; least metric, ties to the deepest),
checked against the slow references of ``test_avsm_insertion`` on random and adversarial lanes:
ties in depth, x exactly on a node, in front of the first and behind the last node, ties in the
metric (collinear nodes, metric exactly 0), odd list lengths, and the ``last`` bound.

Exact comparisons: the tree selects among the same float64 values a scan selects among and
computes no new ones, so every output is bit-identical to the reference's.
"""
import functools

import numpy as np
import pytest

from avsm_dr import _arrays as A
from avsm_dr import backend
from avsm_dr.representations._avsm_insertion import remove_refit
from avsm_dr.representations.avsm import bracket
from test_avsm_insertion import _bracket, _remove


@pytest.mark.parametrize("n", range(1, 18))
def test_pairwise_is_the_left_fold_of_an_associative_merge(n):
    # string concatenation: associative, not commutative, so a wrong order or a lost item shows
    items = [chr(ord("a") + k) for k in range(n)]
    assert A.pairwise(items, lambda p, q: p + q) == functools.reduce(lambda p, q: p + q, items)


def test_pairwise_takes_the_deepest_of_equal_minima():
    items = [(3.0, 0), (1.0, 1), (2.0, 2), (1.0, 3), (1.0, 4)]
    assert A.pairwise(items, lambda lt, rt: rt if rt[0] <= lt[0] else lt) == (1.0, 4)


def _lanes(rng, n, lanes=400):
    """Sorted node lists per lane (depths with ties: drawn from few values; some lanes end in
    clear nodes at 1), values non-increasing in [0, 1] (some 0), and query depths on nodes,
    in front, behind and between."""
    d = np.sort(rng.choice(np.linspace(0.1, 0.9, 6), (lanes, n)), axis=1)
    d[rng.random(lanes) < 0.3, -1] = 1.0
    t = np.sort(rng.choice([0.0, 0.25, 0.5, 0.7, 1.0], (lanes, n)), axis=1)[:, ::-1].copy()
    x = np.where(rng.random(lanes) < 0.5, d[np.arange(lanes), rng.integers(0, n, lanes)],
                 rng.choice([0.0, 0.05, 0.33, 0.95, 1.0, 2.0], lanes))
    return d, t, x


@pytest.mark.parametrize("n", [1, 2, 3, 5, 8, 9, 10])
def test_bracket_matches_the_sequential_scan(rng, n):
    F = backend.types().Float64
    d, t, x = _lanes(rng, n)
    got = bracket([F(d[:, k]) for k in range(n)], [F(t[:, k]) for k in range(n)], F(x))
    got = np.stack([v.numpy() for v in got], axis=1)
    ref = np.array([_bracket(list(d[i]), list(t[i]), x[i]) for i in range(len(x))])
    np.testing.assert_array_equal(got, ref)


@pytest.mark.parametrize("n", [3, 4, 7, 10, 11])
@pytest.mark.parametrize("bounded", [False, True])
def test_least_metric_search_matches_the_sequential_scan(rng, n, bounded):
    """Half the lanes are collinear runs (metric exactly 0 at several nodes): the deepest goes.
    ``bounded``: ``last`` (the list's last node) per lane; nodes behind it are ignored."""
    F, U = backend.types().Float64, backend.types().UInt32
    L = 300
    # depths on a 1/4 grid, slopes 1/64 or 1/32 per piece: every product exact, so a run of
    # equal slopes gives nodes of metric exactly 0 (ties); every third lane has one slope only
    step = rng.choice([0.25, 0.5, 1.0], (L, n))
    slope = rng.choice([1 / 64, 1 / 32], (L, n))
    slope[::3] = 1 / 64
    d = np.cumsum(step, axis=1)
    t = 1.0 - np.cumsum(step * slope, axis=1)
    last = rng.integers(2, n, L) if bounded else np.full(L, n - 1)
    out = remove_refit([F(d[:, k]) for k in range(n)], [F(t[:, k]) for k in range(n)], None, "area",
                       last=U(last.astype(np.uint32)) if bounded else None)
    got_d = np.stack([v.numpy() for v in out[0]], axis=1)
    for i in range(L):
        m = last[i] + 1                      # the list the reference sees: nodes 0 .. last
        ref_d, _ = _remove(list(d[i, :m]), list(t[i, :m]), None, "area")
        np.testing.assert_array_equal(got_d[i, :m - 1], ref_d)

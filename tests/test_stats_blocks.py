"""Spatial block bootstrap of avsm_dr.stats (``blocks=``, :func:`experiments._two_metric.texel_blocks`)
against a slow NumPy reference written out replicate by replicate."""
from __future__ import annotations

import numpy as np
import pytest

from avsm_dr import stats
from experiments._two_metric import texel_blocks


def _reference_replicates(x, y, blocks, statistic, n_boot, seed, compare="ratio"):
    """Replicate by replicate, block by block in Python: draw G block numbers (the blocks
    sorted by label, G of them), append each drawn block's values in their original order,
    compare the statistics."""
    labels = sorted(set(np.asarray(blocks).tolist()))
    members = [[i for i in range(len(x)) if blocks[i] == lab] for lab in labels]
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, len(labels), size=(n_boot, len(labels)))
    f = stats.STATISTICS[statistic]
    out = []
    for r in range(n_boot):
        idx = [i for g in picks[r] for i in members[g]]
        sa = f(np.asarray(x)[idx][None], axis=1)[0]
        if y is None:
            out.append(sa)
            continue
        sb = f(np.asarray(y)[idx][None], axis=1)[0]
        out.append(sa / sb if compare == "ratio" else sa - sb)
    return np.array(out)


def _percentile(boot, level=0.95):
    return np.quantile(boot, [(1 - level) / 2, (1 + level) / 2])


@pytest.mark.parametrize("case", ["random", "uneven", "one_block", "singletons"])
def test_block_bootstrap_matches_the_slow_reference(case):
    """Paired ratio and single-sample intervals equal the reference's (same draws: the
    replicates agree to float64 rounding of the same sums) on random labels, very uneven
    block sizes, one block holding everything, and one value per block."""
    rng = np.random.default_rng(7)
    n = 150
    x, y = rng.standard_normal(n), rng.standard_normal(n) * 2 + 0.1
    blocks = {"random": rng.integers(0, 12, n), "uneven": np.where(rng.random(n) < 0.9, 3, rng.integers(0, 40, n)),
              "one_block": np.full(n, 5), "singletons": rng.permutation(n)}[case]
    got = stats.paired_bootstrap(x, y, "rmse", "ratio", n_boot=300, seed=3, blocks=blocks)
    ref = _reference_replicates(x, y, blocks, "rmse", 300, 3)
    lo, hi = _percentile(ref)
    assert got["low"] == pytest.approx(lo, rel=1e-12) and got["high"] == pytest.approx(hi, rel=1e-12)
    assert got["std_error"] == pytest.approx(np.std(ref, ddof=1), rel=1e-10)
    one = stats.bootstrap_ci(x, "mean", n_boot=300, seed=4, blocks=blocks)
    ref1 = _reference_replicates(x, None, blocks, "mean", 300, 4)
    assert [one["low"], one["high"]] == pytest.approx(list(_percentile(ref1)), rel=1e-12, abs=1e-15)
    if case == "one_block":                   # every replicate is the sample itself
        assert one["low"] == pytest.approx(one["estimate"]) and one["high"] == pytest.approx(one["estimate"])


def test_one_value_per_block_in_label_order_is_the_ordinary_bootstrap():
    """Labels 0..n-1 in value order: the same draws as the value bootstrap, so the same interval."""
    x = np.random.default_rng(1).lognormal(size=80)
    y = np.random.default_rng(2).lognormal(size=80)
    a = stats.paired_bootstrap(x, y, "rmse", "ratio", n_boot=400, seed=9)
    b = stats.paired_bootstrap(x, y, "rmse", "ratio", n_boot=400, seed=9, blocks=np.arange(80))
    assert (a["low"], a["high"]) == pytest.approx((b["low"], b["high"]), rel=1e-13)


def test_blocks_widen_the_interval_of_correlated_texels():
    """A 64 x 64 map whose values are constant on 8 x 8 tiles (a random level per tile plus
    1 % noise): the texel bootstrap treats 4096 values as independent and gives an
    interval of the mean about 8x too narrow; the block bootstrap on those tiles gives the
    interval of 64 independent tile means (its width within 30 % of 2 x 1.96 sd / 8)."""
    rng = np.random.default_rng(0)
    tile = rng.standard_normal((8, 8))
    img = np.kron(tile, np.ones((8, 8))) + 0.01 * rng.standard_normal((64, 64))
    x = img.ravel()
    blocks = texel_blocks(np.arange(x.size), 64)
    iid = stats.bootstrap_ci(x, "mean", n_boot=1000, seed=0)
    blk = stats.bootstrap_ci(x, "mean", n_boot=1000, seed=0, blocks=blocks)
    w_iid, w_blk = iid["high"] - iid["low"], blk["high"] - blk["low"]
    assert w_blk > 5 * w_iid
    expected = 2 * 1.96 * np.std(tile, ddof=1) / 8
    assert abs(w_blk / expected - 1) < 0.3


def test_texel_blocks_tiles():
    """Texel (y, x) of a 20-wide map falls in tile (y // 8) * 3 + x // 8 (3 tiles per row,
    the last one partial)."""
    t = np.array([0, 7, 8, 19, 20 * 8, 20 * 8 + 19, 20 * 17 + 9])
    assert texel_blocks(t, 20).tolist() == [0, 0, 1, 2, 3, 5, 7]
    assert texel_blocks(t, 20, size=1).tolist() == t.tolist()


def test_claim_with_blocks_per_configuration():
    """claim() with blocks_by_config: each configuration's interval is the paired block
    bootstrap with seed + c; the pooled interval brackets the estimate."""
    rng = np.random.default_rng(5)
    a = [rng.standard_normal(100) * 0.5 for _ in range(3)]
    b = [rng.standard_normal(100) for _ in range(3)]
    blocks = [rng.integers(0, 10, 100) for _ in range(3)]
    r = stats.claim(a, b, "rmse", "ratio", n_boot=200, seed=11, blocks_by_config=blocks)
    for c in range(3):
        one = stats.paired_bootstrap(a[c], b[c], "rmse", "ratio", n_boot=200, seed=11 + c, blocks=blocks[c])
        assert (r["per_config"][c]["low"], r["per_config"][c]["high"]) == (one["low"], one["high"])
    assert r["low"] <= r["estimate"] <= r["high"]


def test_bad_blocks_name_the_argument():
    x = np.arange(10.0)
    with pytest.raises(ValueError, match="blocks"):
        stats.bootstrap_ci(x, blocks=np.zeros(9))
    with pytest.raises(ValueError, match="method"):
        stats.bootstrap_ci(x, method="bca", blocks=np.zeros(10))
    with pytest.raises(ValueError, match="blocks_by_config"):
        stats.claim([x, x], [x, x], blocks_by_config=[np.zeros(10)])
    with pytest.raises(ValueError, match=r"blocks_by_config\[1\]"):
        stats.claim([x, x], [x + 1, x + 1], blocks_by_config=[np.zeros(10), np.zeros(3)])
    with pytest.raises(ValueError, match="texels"):
        texel_blocks([-1, 2], 4)
    with pytest.raises(ValueError, match="width"):
        texel_blocks([1, 2], 0)


@pytest.mark.parametrize("statistic,compare", [("rmse", "ratio"), ("mean", "difference"), ("mean_abs", "ratio")])
def test_block_sums_give_the_replicates_of_the_generic_path(statistic, compare, monkeypatch):
    """Statistics of a mean take the per-block-sums path (10x faster in findings.json's
    claims); it draws the same blocks and gives the generic path's replicates up to
    summation order (1e-12), the same intervals and the same share of a < b."""
    rng = np.random.default_rng(3)
    a = [rng.standard_normal(900) * 0.2 for _ in range(3)]
    b = [rng.standard_normal(900) for _ in range(3)]
    blocks = [rng.integers(0, 60, 900) for _ in range(3)]
    fast = stats.claim(a, b, statistic, compare, blocks_by_config=blocks, n_boot=300)
    monkeypatch.setattr(stats, "_MEAN_OF", {})
    slow = stats.claim(a, b, statistic, compare, blocks_by_config=blocks, n_boot=300)
    for k in ("estimate", "low", "high"):
        assert fast[k] == pytest.approx(slow[k], rel=1e-12, abs=1e-15)
    for p, q in zip(fast["per_config"], slow["per_config"]):
        assert (p["low"], p["high"]) == pytest.approx((q["low"], q["high"]), rel=1e-12, abs=1e-15)
        assert p["p_a_smaller"] == q["p_a_smaller"]


def test_bootstrap_ci_with_blocks_takes_block_sums_for_means(monkeypatch):
    """bootstrap_ci's block bootstrap of 'mean' / 'rmse' / 'mean_abs' from per-block sums equals
    its generic path (each replicate's values gathered): the same draws, to rounding."""
    rng = np.random.default_rng(4)
    x, blocks = rng.standard_normal(700) + 0.3, rng.integers(0, 50, 700)
    fast = {s: stats.bootstrap_ci(x, s, n_boot=300, seed=2, blocks=blocks) for s in ("mean", "rmse", "mean_abs")}
    monkeypatch.setattr(stats, "_MEAN_OF", {})
    for s, r in fast.items():
        slow = stats.bootstrap_ci(x, s, n_boot=300, seed=2, blocks=blocks)
        for k in ("estimate", "low", "high", "std_error"):
            assert r[k] == pytest.approx(slow[k], rel=1e-12), (s, k)


@pytest.mark.parametrize("case", ["random", "singletons", "none"])
def test_function_of_means_matches_the_slow_reference(case):
    """bootstrap_means_ci of a ratio of two means, sqrt(mean(u) / mean(v)), replicate by replicate
    against the slow reference (whole blocks drawn and their values gathered); without blocks
    it is bootstrap_ci's ordinary bootstrap, draw for draw."""
    rng = np.random.default_rng(8)
    n = 120
    u, v = rng.random(n) + 0.5, rng.random(n) + 1.0
    blocks = {"random": rng.integers(0, 15, n), "singletons": np.arange(n), "none": None}[case]
    got = stats.bootstrap_means_ci(np.stack([u, v]), lambda m: np.sqrt(m[0] / m[1]), n_boot=200, seed=6, blocks=blocks)
    lab = np.arange(n) if blocks is None else blocks
    ru = _reference_replicates(u, None, lab, "mean", 200, 6)
    rv = _reference_replicates(v, None, lab, "mean", 200, 6)
    ref = np.sqrt(ru / rv)
    assert got["estimate"] == pytest.approx(np.sqrt(u.mean() / v.mean()), rel=1e-14)
    assert [got["low"], got["high"]] == pytest.approx(list(_percentile(ref)), rel=1e-12)
    assert got["std_error"] == pytest.approx(np.std(ref, ddof=1), rel=1e-10) and got["n"] == n
    if blocks is None:
        idx = stats.bootstrap_ci(np.arange(n, dtype=np.float64), lambda i, axis: np.sqrt(
            np.mean(u[i.astype(int)], axis=axis) / np.mean(v[i.astype(int)], axis=axis)), n_boot=200, seed=6)
        assert (got["low"], got["high"]) == pytest.approx((idx["low"], idx["high"]), rel=1e-12)
    with pytest.raises(ValueError, match="^x:"):
        stats.bootstrap_means_ci(u, np.mean)
    with pytest.raises(ValueError, match="^blocks:"):
        stats.bootstrap_means_ci(np.stack([u, v]), np.mean, blocks=np.zeros(n - 1))

"""Bootstrap confidence intervals, paired comparisons and claims over configurations.

Efron and Tibshirani, "An Introduction to the Bootstrap", 1993: the percentile interval
(ch. 13) and the bias-corrected and accelerated (BCa) interval (ch. 14, eq. 14.9-14.15;
acceleration from the jackknife).  Every resampling is vectorised NumPy (an (B, n) index
matrix) and seeded, so the same call gives the same interval.  :func:`paired_bootstrap`
resamples the receivers of two methods together (receiver-to-receiver variation cancels);
:func:`claim` pools paired comparisons over configurations (seed x light x ...).

Samples with spatial correlation (texels of one map, receivers looked up through it) take
``blocks``: a block label per value (e.g. tiles of 8 x 8 texels of the map).  A
replicate then draws as many blocks as there are, with replacement, and keeps every value
of each drawn block (the moving-block idea of Kuensch 1989 on fixed, non-overlapping tiles:
Lahiri, "Resampling Methods for Dependent Data", 2003, sec. 2.6), so the interval keeps the
correlation within a tile; with one value per block it is the ordinary bootstrap, draw for draw.
Statistics of means (``'mean'``, ``'rmse'``, ``'mean_abs'``, :func:`bootstrap_means_ci`) take a
replicate's means from per-block sums: the same draws and values (to rounding), no gather.

Statistics are names (``'mean'``, ``'median'``, ``'rmse'``, ``'mean_abs'``, ``'p99'``,
``'max'``) or callables ``f(x, axis) -> array`` reducing along ``axis``.
"""
from __future__ import annotations

from statistics import NormalDist
from typing import Callable

import numpy as np

from . import validation as V

STATISTICS: dict[str, Callable] = {
    "mean": lambda x, axis: np.mean(x, axis=axis),
    "median": lambda x, axis: np.median(x, axis=axis),
    "rmse": lambda x, axis: np.sqrt(np.mean(np.square(x), axis=axis)),
    "mean_abs": lambda x, axis: np.mean(np.abs(x), axis=axis),
    "p99": lambda x, axis: np.percentile(np.abs(x), 99.0, axis=axis),
    "max": lambda x, axis: np.max(np.abs(x), axis=axis)}
#: Statistics ``post(mean(pre(x)))``: block-bootstrap replicates from per-block sums.
_MEAN_OF = {STATISTICS["mean"]: (np.asarray, np.asarray), STATISTICS["rmse"]: (np.square, np.sqrt),
            STATISTICS["mean_abs"]: (np.abs, np.asarray)}
METHODS = ("percentile", "bca")
#: Bound on the entries of one (replicates x samples) index block (host memory).
_BLOCK = 1 << 24


def _stat(statistic) -> Callable:
    if not (callable(statistic) or statistic in STATISTICS):
        raise ValueError(f"statistic: expected one of {sorted(STATISTICS)} or a callable, got {statistic!r}")
    return statistic if callable(statistic) else STATISTICS[statistic]


def _sample(x, name: str) -> np.ndarray:
    a = V.array(x, name).ravel()
    if a.size < 2:
        raise ValueError(f"{name}: expected at least 2 values, got {a.size}")
    return a


def _check(n_boot, level, method, compare="ratio"):
    V.integer(n_boot, "n_boot", 100)
    V.real(level, "level", 0.0, 1.0, open_min=True, open_max=True)
    V.one_of(method, "method", METHODS)
    V.one_of(compare, "compare", ("difference", "ratio"))


def _pair(a, b, name_a: str, name_b: str):
    x, y = _sample(a, name_a), _sample(b, name_b)
    if x.size != y.size:
        raise ValueError(f"{name_b}: expected {x.size} values (paired with {name_a}), got {y.size}")
    return x, y


def _rows(fn: Callable, n: int, count: int, rows: Callable) -> np.ndarray:
    """(count,) values of ``fn(rows(a, b))`` (index rows a..b-1 of length ~n), :data:`_BLOCK`
    entries at a time."""
    out = np.empty(count)
    per = max(1, _BLOCK // max(n, 1))
    for a in range(0, count, per):
        b = min(count, a + per)
        out[a:b] = fn(rows(a, b))
    return out


def _replicates(fn: Callable, n: int, n_boot: int, rng, layout=None) -> np.ndarray:
    """(n_boot,) values of ``fn(idx)``: ``idx`` (B, n) value indices drawn with replacement, or
    with ``layout`` (:func:`_layout`) one row per replicate: the members of G blocks drawn with
    replacement (``rng.integers(0, G, size=(n_boot, G))``, G blocks), concatenated in the order drawn."""
    if layout is None:
        return _rows(fn, n, n_boot, lambda a, b: rng.integers(0, n, size=(b - a, n)))
    members, starts, counts = layout
    picks = rng.integers(0, counts.size, size=(n_boot, counts.size))
    out = np.empty(n_boot)
    for r in range(n_boot):
        lens = counts[picks[r]]
        first = np.repeat(starts[picks[r]] - np.r_[0, np.cumsum(lens)[:-1]], lens)
        out[r] = fn(members[first + np.arange(lens.sum())][None, :])[0]
    return out


def _layout(blocks, n: int, method: str = "percentile", name: str = "blocks"):
    """(members, starts, counts) of the block labels ``blocks`` (n,): the value indices
    sorted by block (stable), each block's start in ``members`` and size; None passes.
    ValueError for BCa with blocks (block intervals are percentile intervals)."""
    if blocks is None:
        return None
    if method != "percentile":
        raise ValueError(f"method: block bootstrap intervals are percentile intervals, got method={method!r}")
    b = np.asarray(blocks).ravel()
    if b.size != n:
        raise ValueError(f"{name}: expected {n} block labels (one per value), got {b.size}")
    _, inv, counts = np.unique(b, return_inverse=True, return_counts=True)
    members = np.argsort(inv, kind="stable")
    return members, np.r_[0, np.cumsum(counts)[:-1]], counts


def _block_means(cols, layout, n_boot: int, rng) -> np.ndarray:
    """(m, n_boot) means of the rows of ``cols`` (m, n) over the values of each replicate's
    blocks (the draws of :func:`_replicates` with ``layout``), from per-block sums."""
    members, starts, counts = layout
    picks = rng.integers(0, counts.size, size=(n_boot, counts.size))
    n = counts[picks].sum(axis=1).astype(np.float64)
    sums = np.add.reduceat(cols[:, members], starts, axis=1)                  # (m, G)
    per = max(1, _BLOCK // counts.size)
    return np.stack([np.concatenate([row[picks[a:a + per]].sum(axis=1) for a in range(0, n_boot, per)])
                     for row in sums]) / n


def _jackknife(fn: Callable, n: int) -> np.ndarray:
    """(n,) leave-one-out values of ``fn(idx)`` (rows of the (n, n - 1) index matrix)."""
    base = np.arange(n - 1)[None, :]
    return _rows(fn, n, n, lambda a, b: base + (base >= np.arange(a, b)[:, None]))     # row r skips index r


def _result(theta, boot, level, method, jack, **extra) -> dict:
    """The result dict of the percentile or BCa interval from bootstrap replicates ``boot``;
    ``jack()``: the jackknife values (BCa's acceleration)."""
    alpha = (1.0 - level) / 2
    q = np.array([alpha, 1.0 - alpha])
    if method == "bca":
        nd = NormalDist()
        frac = (np.count_nonzero(boot < theta) + 0.5 * np.count_nonzero(boot == theta)) / boot.size
        frac = min(max(frac, 0.5 / boot.size), 1 - 0.5 / boot.size)
        z0 = nd.inv_cdf(frac)                                            # bias correction
        th = jack()
        d = th.mean() - th
        den = 6.0 * np.sum(d ** 2) ** 1.5
        acc = float(np.sum(d ** 3) / den) if den > 0 else 0.0             # acceleration
        z = np.array([nd.inv_cdf(v) for v in q])
        adj = z0 + (z0 + z) / (1 - acc * (z0 + z))
        q = np.array([nd.cdf(v) for v in adj])
    lo, hi = np.quantile(boot, q)
    return dict(estimate=float(theta), low=float(lo), high=float(hi), level=level, method=method, n_boot=int(boot.size),
                std_error=float(np.std(boot, ddof=1)), **extra)


def bootstrap_ci(x, statistic="mean", n_boot: int = 2000, level: float = 0.95, method: str = "percentile",
                 seed: int = 0, blocks=None) -> dict:
    """Bootstrap ``level`` interval for ``statistic`` of the sample ``x`` (1-D, >= 2 values).

    Returns dict(estimate (the statistic of x), low, high, level, method, n_boot, n,
    std_error (of the replicates)).  method: 'percentile' or 'bca'.  blocks: a block label
    per value (module docstring; percentile intervals only).
    """
    a = _sample(x, "x")
    _check(n_boot, level, method)
    layout = _layout(blocks, a.size, method)
    f = _stat(statistic)
    rng = np.random.default_rng(seed)
    fn = lambda idx: f(a[idx], axis=1)  # noqa: E731
    if layout is not None and f in _MEAN_OF:               # from per-block sums (same draws)
        pre, post = _MEAN_OF[f]
        return bootstrap_means_ci(pre(a)[None], lambda m: post(m[0]), n_boot, level, seed, blocks)
    boot = _replicates(fn, a.size, n_boot, rng, layout)
    return _result(f(a[None, :], axis=1)[0], boot, level, method, lambda: _jackknife(fn, a.size), n=int(a.size))


def bootstrap_means_ci(x, function: Callable, n_boot: int = 2000, level: float = 0.95, seed: int = 0,
                       blocks=None) -> dict:
    """Percentile interval of ``function(means)``, the means of the m rows of ``x`` (m, n)
    (e.g. a ratio of means); ``function``: (m, B) means -> (B,).  The draws of
    :func:`bootstrap_ci` (``blocks``: whole blocks), the means from per-block sums.  Returns
    the keys of :func:`bootstrap_ci`."""
    a = V.array(x, "x")
    if a.ndim != 2 or a.shape[1] < 2:
        raise ValueError(f"x: expected (quantities, values >= 2) values, got shape {a.shape}")
    _check(n_boot, level, "percentile")
    layout = _layout(np.arange(a.shape[1]) if blocks is None else blocks, a.shape[1])
    boot = np.asarray(function(_block_means(a, layout, n_boot, np.random.default_rng(seed))), np.float64)
    theta = np.asarray(function(a.mean(axis=1, keepdims=True)), np.float64).ravel()[0]
    return _result(theta, boot, level, "percentile", None, n=int(a.shape[1]))


def _compare(sa, sb, compare):
    if compare == "difference":
        return sa - sb
    with np.errstate(divide="ignore", invalid="ignore"):
        return sa / sb


def paired_bootstrap(a, b, statistic="rmse", compare: str = "ratio", n_boot: int = 2000,
                     level: float = 0.95, method: str = "percentile", seed: int = 0, blocks=None) -> dict:
    """Interval for ``stat(a) - stat(b)`` (compare='difference') or ``stat(a) / stat(b)``
    ('ratio') where a[i] and b[i] belong to the same receiver i (e.g. the errors of two
    methods); each replicate resamples receivers once for both.

    Returns the keys of :func:`bootstrap_ci` plus ``a`` and ``b`` (the two statistics)
    and ``p_a_smaller``: the share of replicates with stat(a) < stat(b).  blocks: a block
    label per receiver (module docstring; percentile intervals only).
    """
    x, y = _pair(a, b, "a", "b")
    _check(n_boot, level, method, compare)
    return _paired(x, y, _stat(statistic), compare, n_boot, level, method, seed, _layout(blocks, x.size, method))[0]


def _paired(x, y, f, compare, n_boot, level, method, seed, layout=None):
    """(result dict of :func:`paired_bootstrap`, (n_boot,) replicates); inputs checked;
    ``layout``: :func:`_layout` of block labels, or None (values resampled)."""
    rng = np.random.default_rng(seed)
    smaller = []

    def rep(idx):
        sa, sb = f(x[idx], axis=1), f(y[idx], axis=1)
        smaller.append(np.count_nonzero(sa < sb))
        return _compare(sa, sb, compare)
    if layout is not None and f in _MEAN_OF:               # from per-block sums (same draws)
        pre, post = _MEAN_OF[f]
        ma, mb = post(_block_means(np.stack([pre(x), pre(y)]), layout, n_boot, rng))
        boot = _compare(ma, mb, compare)
        smaller.append(np.count_nonzero(ma < mb))
    else:
        boot = _replicates(rep, x.size, n_boot, rng, layout)
    sa, sb = float(f(x[None], axis=1)[0]), float(f(y[None], axis=1)[0])
    res = _result(float(_compare(np.array(sa), np.array(sb), compare)), boot, level, method,
                  lambda: _jackknife(rep, x.size), n=int(x.size), a=sa, b=sb, p_a_smaller=float(sum(smaller)) / n_boot)
    return res, boot


def claim(a_by_config, b_by_config, statistic="rmse", compare: str = "ratio", below: float | None = None,
          configs=None, n_boot: int = 2000, level: float = 0.95, seed: int = 0, blocks_by_config=None) -> dict:
    """Does ``stat(a) / stat(b) < below`` (compare='ratio', default below = 1) or
    ``stat(a) - stat(b) < below`` ('difference', default 0) hold, per configuration and
    pooled?  ``a_by_config`` / ``b_by_config``: sequences (one per configuration, e.g.
    seed x light) of paired per-receiver values (e.g. |errors| of methods a and b).
    blocks_by_config: None, or per configuration the block labels of its values (module
    docstring).

    Returns dict(per_config: [:func:`paired_bootstrap` result + config + holds (the whole
    interval below ``below``) + point_holds (the estimate below it)]; estimate, low, high:
    the pooled effect, geometric mean of the per-configuration ratios (mean of differences),
    and its interval from a two-stage bootstrap (configurations resampled, then receivers
    within each, replicate by replicate); holds_in_every_configuration,
    point_holds_in_every_configuration, holds_pooled (the pooled interval below ``below``),
    n_configs, below, compare, statistic (its name)).
    """
    if len(a_by_config) != len(b_by_config) or len(a_by_config) == 0:
        raise ValueError(f"b_by_config: expected {len(a_by_config)} configurations (as a_by_config), "
                         f"got {len(b_by_config)}")
    _check(n_boot, level, "percentile", compare)
    below = (1.0 if compare == "ratio" else 0.0) if below is None else float(below)
    C = len(a_by_config)
    configs = list(range(C)) if configs is None else list(configs)
    if len(configs) != C:
        raise ValueError(f"configs: expected {C} labels, got {len(configs)}")
    f = _stat(statistic)
    log = compare == "ratio"
    if blocks_by_config is not None and len(blocks_by_config) != C:
        raise ValueError(f"blocks_by_config: expected {C} configurations (as a_by_config), got {len(blocks_by_config)}")
    per, reps = [], np.empty((C, n_boot))
    for c in range(C):
        x, y = _pair(a_by_config[c], b_by_config[c], f"a_by_config[{c}]", f"b_by_config[{c}]")
        layout = None if blocks_by_config is None else _layout(blocks_by_config[c], x.size,
                                                               name=f"blocks_by_config[{c}]")
        r, reps[c] = _paired(x, y, f, compare, n_boot, level, "percentile", seed + c, layout)
        r.update(config=configs[c], holds=bool(r["high"] < below), point_holds=bool(r["estimate"] < below))
        per.append(r)
    pick = np.random.default_rng(seed + C).integers(0, C, size=(n_boot, C))
    vals = reps[pick, np.arange(n_boot)[:, None]]         # (n_boot, C): config resample x receiver replicate
    est = np.array([r["estimate"] for r in per])
    with np.errstate(divide="ignore", invalid="ignore"):
        pooled = np.exp(np.mean(np.log(vals), axis=1)) if log else np.mean(vals, axis=1)
        theta = float(np.exp(np.mean(np.log(est)))) if log else float(np.mean(est))
    lo, hi = np.quantile(pooled, [(1 - level) / 2, (1 + level) / 2])
    return dict(per_config=per, estimate=theta, low=float(lo), high=float(hi), level=level,
                holds_in_every_configuration=all(r["holds"] for r in per),
                point_holds_in_every_configuration=all(r["point_holds"] for r in per),
                holds_pooled=bool(hi < below), n_configs=C, below=below, compare=compare,
                statistic=statistic if isinstance(statistic, str) else getattr(statistic, "__name__", "custom"))

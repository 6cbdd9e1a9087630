"""``compare``: how much better is method a than method b, with an interval whose unit is
the configuration.

Per configuration c (scene x seed x light) the ratio ``r_c = metric(a, c) / metric(b, c)``;
the pooled ratio is their geometric mean ``exp(mean_c ln r_c)`` (every configuration weighs
alike, whatever its error level), and its interval the bootstrap percentile interval of
that mean over configurations resampled with replacement (:func:`avsm_dr.stats.bootstrap_ci`
on ``ln r_c``; Efron and Tibshirani 1993, ch. 13).  Receivers within a configuration are
not resampled: they share one map and one light, so they are not independent units.
Fewer than :data:`MIN_CONFIGURATIONS` configurations make the result ``indicative``.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from .. import stats
from .. import validation as V

#: Configurations below which a comparison is marked indicative.
MIN_CONFIGURATIONS = 4
#: The columns that identify a configuration.
UNIT = ("scene", "seed", "light")


@dataclasses.dataclass
class Comparison:
    """Result of :func:`compare`: ``ratio`` (geometric mean over configurations) of
    ``metric`` of method ``a`` over ``b``, its ``level`` interval [``low``, ``high``] (NaN
    with one configuration), ``n_configurations``, ``indicative`` (fewer than
    :data:`MIN_CONFIGURATIONS`) and ``per_configuration`` (dicts: scene, seed, light,
    a, b, ratio)."""
    a: str
    b: str
    metric: str
    ratio: float
    low: float
    high: float
    level: float
    n_configurations: int
    indicative: bool
    per_configuration: list
    receivers: str | None = None

    def __str__(self) -> str:
        where = f" at {self.receivers} receivers" if self.receivers else ""
        head = f"{self.metric}({self.a}) / {self.metric}({self.b}){where} = {self.ratio:.3g}"
        iv = "no interval (one configuration)" if math.isnan(self.low) else \
            f"{self.level:.0%} interval [{self.low:.3g}, {self.high:.3g}]"
        tail = f"over {self.n_configurations} configuration{'s' if self.n_configurations != 1 else ''} " \
               "(scene x seed x light)"
        note = f"; indicative: fewer than {MIN_CONFIGURATIONS} configurations" if self.indicative else ""
        return "\n".join([f"{head}, {iv} {tail}{note}"] + [
            f"  {c['scene']} s{c['seed']} {c['light']}: {c['a']:.4g} / {c['b']:.4g} = {c['ratio']:.3g}"
            for c in self.per_configuration])


def _pick(table, method, metric, name):
    rows = table.where(method=method).rows
    if not rows:
        raise ValueError(f"{name}: no rows of method {method!r}; methods: {sorted(set(table.column('method')))}")
    by = {}
    for r in rows:
        if missing := [k for k in UNIT if k not in r]:
            raise ValueError(f"table: rows of {method!r} lack the configuration column(s) {missing}")
        key = tuple(r[k] for k in UNIT)
        try:
            hash(key)
        except TypeError:
            raise ValueError(f"table: the configuration columns {UNIT} of {method!r} hold unhashable values "
                             f"{key!r}") from None
        if key in by:
            differ = [k for k in r if k not in UNIT and _differs(by[key][0].get(k), r.get(k))
                      and k in ("receivers", "order", "resolution", "opaque", "params", "kind")]
            raise ValueError(f"{name}: several rows of {method!r} per configuration (they differ in "
                             f"{differ or 'other columns'}); narrow them, e.g. compare(..., "
                             f"{(differ or ['order'])[0]}=...)")
        by[key] = (r, r.get(metric))
    return by


def _differs(x, y) -> bool:
    return not (x == y or (isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y)))


def compare(table, a: str, b: str, metric: str = "rmse", receivers: str | None = None, scene=None,
            n_boot: int = 2000, level: float = 0.95, seed: int = 0, **where) -> Comparison:
    """``metric(a) / metric(b)`` over the configurations of ``table`` (module docstring).

    table: an :func:`~.harness.evaluate` result; a, b: method labels.
    metric: a numeric column (e.g. 'rmse', 'depth_l2', 'compression_rms', 'p99').
    receivers: the receiver set (default 'in_volume' when the table has it, else its only set).
    scene: a scene name or a list of them (default: every scene, pooled).
    where: further column filters (``table.where``), e.g. ``order='depth'``, ``resolution=64``.
    n_boot, level, seed: the bootstrap's replicates, interval level and seed."""
    V.integer(n_boot, "n_boot", 100)
    V.integer(seed, "seed", 0)
    V.real(level, "level", 0.0, 1.0, open_min=True, open_max=True)
    if not hasattr(table, "where") or not len(table):
        raise ValueError("table: expected a non-empty table of avsm_dr.evaluation.evaluate")
    if metric not in table.columns:
        raise ValueError(f"metric: no column {metric!r}; columns: {table.columns}")
    sets = list(dict.fromkeys(table.column("receivers")))
    if receivers is None and "in_volume" not in sets and len(sets) > 1:
        raise ValueError(f"receivers: the table holds several receiver sets {sets}; choose one")
    if receivers is None:
        receivers = "in_volume" if "in_volume" in sets else sets[0]
    elif receivers not in sets:
        raise ValueError(f"receivers: no rows at receiver set {receivers!r}; sets: {sets}")
    filt = dict(where, receivers=receivers)
    if scene is not None:
        filt["scene"] = [scene] if isinstance(scene, str) else list(scene)
    t = table.where(**filt)
    if not len(t):                                   # name the filter that left nothing
        for k, v in filt.items():
            if not len(table.where(**{k: v})):
                known = sorted({str(x) for x in table.column(k)})
                raise ValueError(f"{k}: no rows with {k}={v!r}; values: {known}")
        raise ValueError(f"where: no rows match {filt} together")
    ra, rb = _pick(t, a, metric, "a"), _pick(t, b, metric, "b")
    if set(ra) != set(rb):
        only = sorted(set(ra) ^ set(rb))
        raise ValueError(f"b: methods {a!r} and {b!r} were not run in the same configurations (unpaired: {only})")
    per = []
    for key in ra:
        va, vb = ra[key][1], rb[key][1]
        try:
            if isinstance(va, (bool, np.bool_)) or isinstance(vb, (bool, np.bool_)):
                raise TypeError
            va, vb = float(va), float(vb)
        except (TypeError, ValueError):
            raise ValueError(f"metric: {metric!r} is not numeric ({va!r}, {vb!r})") from None
        if not (np.isfinite(va) and np.isfinite(vb)):
            raise ValueError(f"metric: {metric!r} is {va!r} / {vb!r} in configuration {key} "
                             "(NaN: not computed - see evaluate's metrics - or no finite estimate: see the "
                             "nonfinite column)")
        if va <= 0 or vb <= 0:
            raise ValueError(f"metric: {metric!r} is {va:g} / {vb:g} in configuration {key}: a ratio needs "
                             "positive values")
        per.append(dict(zip(UNIT, key), a=va, b=vb, ratio=va / vb))
    # ln a - ln b: the quotient itself under- or overflows for far apart metrics (1e-300 / 1e300)
    logs = np.array([math.log(p["a"]) - math.log(p["b"]) for p in per])
    if logs.size >= 2:
        ci = stats.bootstrap_ci(logs, "mean", n_boot=n_boot, level=level, seed=seed)
        ratio, low, high = math.exp(ci["estimate"]), math.exp(ci["low"]), math.exp(ci["high"])
    else:
        ratio, low, high = float(math.exp(logs[0])), float("nan"), float("nan")
    return Comparison(a, b, metric, ratio, low, high, level, len(per), len(per) < MIN_CONFIGURATIONS, per, receivers)

"""A claim "a below b" on both metrics (receiver RMSE and depth-uniform L2), for the studies
that keep their own error arrays (``avsm_gap``, ``memory_budget``): the receiver RMSE ratio (signed errors at the same
receivers, paired) and the depth-uniform L2 ratio (:func:`avsm_dr.evaluation.depth_l2` per
texel, paired), each by :func:`avsm_dr.stats.claim` (pooled: geometric mean of the
per-configuration ratios, two-stage bootstrap; the unit is the configuration, scene seed x
light; within a configuration receivers / texels are resampled in 8 x 8 texel tiles when
``blocks`` are given).  ``metric_dependent`` follows ``error_curves``: both intervals lie
entirely on opposite sides of 1.  ``indicative``: fewer than :data:`MIN_CONFIDENT`
configurations.  Each side's signed mean and leak share (error > 0.02,
:data:`avsm_dr.metrics.THRESHOLD`) are pooled over the configurations.
"""
from __future__ import annotations

import numpy as np

from avsm_dr import validation as V

#: Side in texels of the square tiles of :func:`texel_blocks`.
BLOCK_TEXELS = 8


def texel_blocks(texels, width: int, size: int = BLOCK_TEXELS) -> np.ndarray:
    """(n,) int64 block label of each texel index (row-major, ``y * width + x``): the tile
    ``(y // size, x // size)`` of ``size`` x ``size`` texels, numbered row-major (the
    ``blocks`` of :mod:`avsm_dr.stats`)."""
    t = V.array(texels, "texels").ravel()
    width, size = V.integer(width, "width", 1), V.integer(size, "size", 1)
    if np.any(t < 0) or np.any(t != np.round(t)):
        raise ValueError("texels: expected non-negative integer texel indices")
    t = t.astype(np.int64)
    y, x = t // width, t % width
    return (y // size) * (-(-width // size)) + x // size


#: Below this many configurations a claim is ``indicative`` (``error_curves``' rule).
MIN_CONFIDENT = 4


def direction(m: dict | None, below: float = 1.0) -> str | None:
    """'below' / 'above' when the interval ``[low, high]`` of ``m`` lies entirely below / above
    ``below`` (1 for a ratio), else None (no direction established, or no interval)."""
    if m is None or "low" not in m:
        return None
    return "below" if m["high"] < below else "above" if m["low"] > below else None


def metric_dependent(a: dict | None, b: dict | None, below: float = 1.0) -> bool:
    """True when both intervals (dicts with ``low`` and ``high``) establish a direction against
    ``below`` and the directions differ (a single configuration has no interval, so no
    direction)."""
    d1, d2 = direction(a, below), direction(b, below)
    return bool(d1 and d2 and d1 != d2)


def side(errors) -> dict:
    """Signed mean and leak share of one side's receiver errors, pooled over configurations."""
    from avsm_dr.metrics import THRESHOLD
    e = np.concatenate([np.asarray(x, np.float64) for x in errors])
    return dict(mean_signed_error=float(np.mean(e)), leak_share=float(np.mean(e > THRESHOLD)))


def claim(receivers: tuple, l2: tuple, configs, blocks: tuple = (None, None), n_boot: int = 1000) -> dict:
    """The two-metric claim "a below b" (module docstring).

    receivers, l2: (a, b), each a list over ``configs`` of the side's receiver errors / per-texel
    depth L2 (paired within a configuration); blocks: (receiver tiles, texel tiles), each None
    or a list over ``configs`` of the 8 x 8 tile of each value.  The top-level estimate and
    interval are the receiver RMSE's."""
    from avsm_dr import stats
    configs = list(configs)
    if not configs:
        raise ValueError("configs: expected at least one configuration")
    metrics = {}
    for name, (a, b), blk in (("receiver_rmse", receivers, blocks[0]), ("depth_l2", l2, blocks[1])):
        r = stats.claim(a, b, "rmse", "ratio", configs=configs, n_boot=n_boot, blocks_by_config=blk)
        metrics[name] = dict(estimate=r["estimate"], low=r["low"], high=r["high"], n_configs=r["n_configs"],
                             holds_pooled=r["holds_pooled"],
                             per_config={pc["config"]: [pc["estimate"], pc["low"], pc["high"]]
                                         for pc in r["per_config"]})
    rm = metrics["receiver_rmse"]
    return dict(estimate=rm["estimate"], low=rm["low"], high=rm["high"], n_configs=rm["n_configs"],
                indicative=rm["n_configs"] < MIN_CONFIDENT, interval_unit="configuration",
                within_configuration="8x8 texel blocks" if all(b is not None for b in blocks)
                else "receivers / texels", metrics=metrics, metric_dependent=metric_dependent(rm, metrics["depth_l2"]),
                sides={"a": side(receivers[0]), "b": side(receivers[1])})

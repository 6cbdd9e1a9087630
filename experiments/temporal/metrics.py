"""Error and temporal flicker of a transmittance estimate over an animation, at fixed receivers.

For frames ``t = 0..F-1`` and receivers ``i = 1..K`` (fixed world points, or fixed pixels
when the camera moves), a representation's estimate ``T_rep[t, i]`` and the reference
``T_ref[t, i]`` (the exact curve of the same map and filter, or the true transmittance)::

    e[t, i]         = T_rep[t, i] - T_ref[t, i]                         error
    error_t         = sqrt(mean_i e[t, i]^2)                            error per frame
    flicker_t       = sqrt(mean_i (e[t, i] - e[t-1, i])^2),   t >= 1    flicker per frame
    content_t       = sqrt(mean_i (T_ref[t, i] - T_ref[t-1, i])^2)      the content's own change

Pooled over frames (and receivers): ``error = sqrt(mean_{t,i} e^2)``,
``flicker = sqrt(mean_{t>=1,i} (e_t - e_{t-1})^2)``, ``content`` likewise.  The flicker is the
part of the frame-to-frame change of the *estimate* that the reference does not have
(``T_rep_t - T_rep_{t-1} = (T_ref_t - T_ref_{t-1}) + (e_t - e_{t-1})``), so the content's
own motion cancels; a representation whose error is frozen to the content (it moves with
it) does not flicker, whatever its size.  Two ratios:

    flicker_index       = flicker / (sqrt(2) * error)   0: frozen error; 1: errors of successive
                          frames uncorrelated (zero mean); sqrt(2): sign flips every frame
    flicker_per_content = flicker / content             share of the visible change that is artefact

(for a stationary error of variance s^2, mean m and frame-to-frame correlation rho:
flicker^2 = 2 s^2 (1 - rho), error^2 = s^2 + m^2).

Per frame also the sign of the error::

    signed_mean_t = mean_i e[t, i]                 (> 0: light leaking)
    leak_share_t  = mean_i [e[t, i] > 0.02]        (avsm_dr.metrics.THRESHOLD)
"""
from __future__ import annotations

import numpy as np

from avsm_dr.metrics import THRESHOLD

SQRT2 = float(np.sqrt(2.0))
#: The pooled statistics (:func:`pooled`), in the order of the tables.
STATISTICS = ("error", "flicker", "content", "flicker_index", "flicker_per_content")


def _frames(x, name: str) -> np.ndarray:
    a = np.asarray(x, np.float64)
    if a.ndim != 2 or a.shape[0] < 2:
        raise ValueError(f"{name}: expected (frames >= 2, receivers) values, got shape {a.shape}")
    return a


def per_frame(estimate, reference) -> dict:
    """Per-frame series of the module docstring: ``error``, ``signed_mean``, ``leak_share``
    (F,), ``flicker`` and ``content`` (F,; NaN at t = 0) for (F, K) arrays ``estimate`` and
    ``reference``."""
    est, ref = _frames(estimate, "estimate"), _frames(reference, "reference")
    if est.shape != ref.shape:
        raise ValueError(f"reference: expected shape {est.shape} (as estimate), got {ref.shape}")
    e = est - ref
    nan = np.full(1, np.nan)
    return {"error": np.sqrt(np.mean(e ** 2, axis=1)),
            "flicker": np.concatenate([nan, np.sqrt(np.mean(np.diff(e, axis=0) ** 2, axis=1))]),
            "content": np.concatenate([nan, np.sqrt(np.mean(np.diff(ref, axis=0) ** 2, axis=1))]),
            "signed_mean": np.mean(e, axis=1), "leak_share": np.mean(e > THRESHOLD, axis=1)}


def receiver_sums(estimate, reference) -> np.ndarray:
    """(3, K) per-receiver sums over frames: sum_t e^2, sum_{t>=1} (e_t - e_{t-1})^2 and
    sum_{t>=1} (T_ref_t - T_ref_{t-1})^2; pooled statistics (:func:`pooled`) are ratios of
    their means."""
    est, ref = _frames(estimate, "estimate"), _frames(reference, "reference")
    e = est - ref
    return np.stack([np.sum(e ** 2, axis=0), np.sum(np.diff(e, axis=0) ** 2, axis=0),
                     np.sum(np.diff(ref, axis=0) ** 2, axis=0)])


def pooled(sums, frames: int, axis: int = -1) -> dict:
    """Pooled ``error``, ``flicker``, ``content``, ``flicker_index``, ``flicker_per_content``
    from (3, ..., K) :func:`receiver_sums` of an animation of ``frames`` frames, reducing
    ``axis`` (the receivers)."""
    s = np.asarray(sums, np.float64)
    err = np.sqrt(np.mean(s[0], axis=axis) / frames)
    fl = np.sqrt(np.mean(s[1], axis=axis) / (frames - 1))
    co = np.sqrt(np.mean(s[2], axis=axis) / (frames - 1))
    with np.errstate(divide="ignore", invalid="ignore"):
        return {"error": err, "flicker": fl, "content": co,
                "flicker_index": np.where(err > 0, fl / (SQRT2 * np.where(err > 0, err, 1.0)), 0.0),
                "flicker_per_content": np.where(co > 0, fl / np.where(co > 0, co, 1.0), np.nan)}


def config_ci(per_config: dict, n_boot: int = 1000, seed: int = 0) -> dict:
    """Each statistic of :func:`pooled`: the mean over configurations of each configuration's
    own value (``per_config``: {configuration: :func:`pooled` dict}; the configuration is the
    unit: every one weighs the same, whatever its receivers) with a bootstrap 95 % percentile
    interval over the configurations (:func:`avsm_dr.stats.bootstrap_ci` of the mean; NaN
    bounds with one configuration); also ``per_config`` and ``n_configs``."""
    from avsm_dr.stats import bootstrap_ci
    out = {}
    for key in STATISTICS:
        v = np.array([float(p[key]) for p in per_config.values()], np.float64)
        ci = bootstrap_ci(v, "mean", n_boot=n_boot, seed=seed) if v.size >= 2 else {"low": np.nan, "high": np.nan}
        out[key] = {"estimate": float(np.mean(v)), "low": float(ci["low"]), "high": float(ci["high"])}
    out["per_config"] = {c: {k: float(p[k]) for k in STATISTICS} for c, p in per_config.items()}
    out["n_configs"] = len(per_config)
    return out


def per_config_from_rows(rows) -> dict:
    """{(setting, vs, method): {config: :func:`pooled` dict}} from a run's per-frame rows
    (``data.csv``: ``error_rms``, ``flicker_rms``, ``content_rms`` per frame, strings or
    numbers).  Every frame has the same receivers, so ``error = sqrt(mean_t error_t^2)``,
    ``flicker = sqrt(mean_{t>=1} flicker_t^2)``, ``content`` likewise: the values of
    :func:`receiver_sums` to rounding."""
    groups: dict = {}
    for r in rows:
        groups.setdefault((r["setting"], r["vs"], r["method"]), {}).setdefault(r["config"], []).append(r)
    out = {}
    for key, by_config in groups.items():
        out[key] = {}
        for c, rs in by_config.items():
            rs = sorted(rs, key=lambda r: int(r["frame"]))
            e, f, c2 = (np.array([float(r[k]) for r in rs]) for k in ("error_rms", "flicker_rms", "content_rms"))
            sums = np.array([[np.sum(e ** 2)], [np.sum(f[1:] ** 2)], [np.sum(c2[1:] ** 2)]])
            out[key][c] = {k: float(v) for k, v in pooled(sums, len(rs)).items()}
    return out


"""Error metrics between transmittance estimates and a reference: :func:`error_stats`.

Sign convention: ``error = estimate - reference``; positive = light leaking (the estimate
is brighter than the truth), negative = over-darkening.  All statistics are over the
finite estimates (non-finite ones are counted, not averaged).  With K < 1000 receivers the
99.9th percentile interpolates between the two largest errors.
"""
from __future__ import annotations

import numpy as np

from . import validation as V

#: Default |error| above which a receiver counts as leaking / over-darkening.
THRESHOLD = 0.02


def checked(estimate, reference, threshold):
    """(estimate, reference, which estimates are finite) as flat float64, checked."""
    est = np.asarray(estimate, dtype=np.float64).ravel()
    ref = np.asarray(reference, dtype=np.float64).ravel()
    if est.shape != ref.shape:
        raise ValueError(f"estimate: shape {est.shape} does not match reference {ref.shape}")
    if not np.all(np.isfinite(ref)):
        raise ValueError("reference: contains NaN or inf")
    V.real(threshold, "threshold", 0.0)
    return est, ref, np.isfinite(est)


_KEYS = ("rmse", "max_error", "mean_error", "mean_abs_error", "leak_fraction", "dark_fraction",
         "p99_error", "p999_error")


def summary(diff: np.ndarray, threshold: float, prefix: str = "") -> dict:
    """Statistics of signed errors ``diff`` (finite; the keys of :func:`error_stats` up to
    ``p999_error``, each with ``prefix``), NaN when there are none."""
    if diff.size == 0:
        return {prefix + k: float("nan") for k in _KEYS}
    a = np.abs(diff)
    values = (np.sqrt(np.mean(diff ** 2)), a.max(), np.mean(diff), np.mean(a), np.mean(diff > threshold),
              np.mean(diff < -threshold), *np.percentile(a, [99.0, 99.9]))
    return {prefix + k: float(v) for k, v in zip(_KEYS, values)}


def error_stats(estimate, reference, threshold: float = THRESHOLD) -> dict:
    """Errors of ``estimate`` against ``reference`` (same number of values, any shape).

    Keys: rmse, max_error (max |e|), mean_error (signed mean of e = estimate - reference;
    > 0: light leaking), mean_abs_error, leak_fraction (share of receivers with
    e > threshold), dark_fraction (e < -threshold), p99_error and p999_error (99th /
    99.9th percentile of |e|, linear interpolation), nan_count, inf_count,
    bounds_violations (estimates outside [0, 1]) and n (all values).  Non-finite
    estimates are counted and excluded from the error statistics.
    """
    est, ref, finite = checked(estimate, reference, threshold)
    out = summary(est[finite] - ref[finite], float(threshold))
    out.update({
        "nan_count": int(np.count_nonzero(np.isnan(est))),
        "inf_count": int(np.count_nonzero(np.isinf(est))),
        "bounds_violations": int(np.count_nonzero((est[finite] < 0) | (est[finite] > 1))),
        "n": int(est.size)})
    return out

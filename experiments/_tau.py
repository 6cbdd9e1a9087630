"""Errors in the log domain, for the studies that report them (``error_curves``,
``spatial_budget``): ``tau = -ln max(T, floor)`` (dense media, where T -> 0 hides errors;
floor 1e-4, the capture's default stop threshold), with the statistics and sign convention
of :func:`avsm_dr.metrics.error_stats`."""
from __future__ import annotations

import numpy as np

from avsm_dr import metrics
from avsm_dr import validation as V

#: Default transmittance floor of :func:`optical_depth_error` (tau <= -ln 1e-4 = 9.21).
T_FLOOR = 1e-4


def optical_depth(transmittance, floor: float = T_FLOOR) -> np.ndarray:
    """``-ln max(T, floor)`` (float64): optical depth, capped at ``-ln floor``."""
    V.real(floor, "floor", 0.0, 1.0, open_min=True, open_max=True)
    return -np.log(np.maximum(np.asarray(transmittance, np.float64), floor))


def optical_depth_error(estimate, reference, floor: float = T_FLOOR, threshold: float = 0.1) -> dict:
    """Errors in the log domain: ``e_tau = tau(reference) - tau(estimate)`` with
    ``tau = -ln max(T, floor)`` (so e_tau > 0 is light leaking, as in :func:`avsm_dr.metrics.error_stats`).

    Both sides are clamped at ``floor`` (default 1e-4), so a receiver where both are
    below it has no error and the largest possible |e_tau| is ``-ln floor``.  Keys:
    tau_rmse, tau_max_error, tau_mean_error, tau_mean_abs_error, tau_leak_fraction /
    tau_dark_fraction (|e_tau| > ``threshold``, default 0.1: about 10 % relative error
    in T), tau_p99_error, tau_p999_error, tau_floor.
    """
    est, ref, finite = metrics.checked(estimate, reference, threshold)
    diff = optical_depth(ref[finite], floor) - optical_depth(est[finite], floor)
    out = metrics.summary(diff, float(threshold), prefix="tau_")
    out["tau_floor"] = float(floor)
    return out

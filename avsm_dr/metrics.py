"""Error metrics between transmittance estimates and a reference."""
from __future__ import annotations

import numpy as np


def error_stats(estimate, reference) -> dict:
    """rmse, max_error, mean_error (signed), nan/inf counts and [0, 1] bounds violations.

    Non-finite estimates are counted and excluded from the error statistics."""
    est = np.asarray(estimate, dtype=np.float64).ravel()
    ref = np.asarray(reference, dtype=np.float64).ravel()
    if est.shape != ref.shape:
        raise ValueError(f"estimate: shape {est.shape} does not match reference {ref.shape}")
    finite = np.isfinite(est)
    diff = est[finite] - ref[finite]
    return {
        "rmse": float(np.sqrt(np.mean(diff ** 2))) if diff.size else float("nan"),
        "max_error": float(np.max(np.abs(diff))) if diff.size else float("nan"),
        "mean_error": float(np.mean(diff)) if diff.size else float("nan"),
        "nan_count": int(np.count_nonzero(np.isnan(est))),
        "inf_count": int(np.count_nonzero(np.isinf(est))),
        "bounds_violations": int(np.count_nonzero((est[finite] < 0) | (est[finite] > 1))),
        "n": int(est.size),
    }

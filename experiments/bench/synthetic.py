"""Synthetic segment sets for benchmarks and stress tests (no scene needed)."""
from __future__ import annotations

import numpy as np

from avsm_dr.segments import Segments


def random_map(texels: int, min_count: int = 50, max_count: int = 300, seed: int = 0,
               mean_length: float = 0.01, mean_tau: float = 0.02, empty_fraction: float = 0.0,
               dtype: str = "float32", depth_range=(0.0, 1.0)) -> Segments:
    """``texels`` texels with uniform-random segment counts in [min_count, max_count],
    random overlapping smoke-like segments over ``depth_range``."""
    rng = np.random.default_rng(seed)
    counts = rng.integers(min_count, max_count + 1, texels)
    if empty_fraction > 0:
        counts[rng.random(texels) < empty_fraction] = 0
    offsets = np.concatenate([[0], np.cumsum(counts)])
    n = int(offsets[-1])
    lo, hi = depth_range
    z0 = rng.uniform(lo, hi, n)
    z1 = np.minimum(z0 + rng.exponential(mean_length * (hi - lo), n), hi)
    tau = rng.exponential(mean_tau, n)
    return Segments.from_arrays(offsets, z0, z1, optical_depth=tau, dtype=dtype)

"""The one list of representations and parameters the generic tests run over, and
random / adversarial segment generators shared by the tests."""
from __future__ import annotations

import numpy as np

import avsm_dr as ad

def representations():
    """(kind, build parameters) for every registered kind: its defaults and each of the
    parameter sets its schema lists as ``examples`` (the registry is the one list)."""
    out, seen = [], []
    for kind in ad.kinds():
        schema = ad.REGISTRY[kind].schema
        for params in [{}] + ad.describe(kind)["examples"]:
            full = (kind, schema.validate(kind, params))      # defaults filled in: no duplicates
            if full not in seen:
                seen.append(full)
                out.append((kind, params))
    return out


def available(reps=None):
    return representations() if reps is None else [r for r in reps if r[0] in ad.kinds()]


def case_id(case):
    kind, params = case[0], case[1]
    return kind + "".join(f"-{k}={v}" for k, v in params.items())


def random_segments(rng, texels=64, max_count=20, opaque_fraction=0.05, zero_fraction=0.1,
                    empty_fraction=0.2, depth_range=(0.0, 1.0)):
    """Random overlapping segments with zero-length and opaque ones and empty texels.

    Returns dict(offsets, z0, z1, tau) as float64 NumPy arrays."""
    counts = rng.integers(0, max_count + 1, texels)
    counts[rng.random(texels) < empty_fraction] = 0
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    n = int(offsets[-1])
    lo, hi = depth_range
    span = hi - lo
    z0 = rng.uniform(lo, hi - 0.2 * span, n)
    z1 = z0 + rng.uniform(0, 0.2 * span, n)
    z1 = np.where(rng.random(n) < zero_fraction, z0, z1)
    tau = rng.exponential(0.4, n)
    tau[rng.random(n) < opaque_fraction] = ad.OPAQUE_OPTICAL_DEPTH
    return dict(offsets=offsets, z0=z0, z1=z1, tau=tau)


def to_segments(case, dtype="float32"):
    return ad.Segments.from_arrays(case["offsets"], case["z0"], case["z1"],
                                   optical_depth=case["tau"], dtype=dtype)

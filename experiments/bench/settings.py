"""Settings of the benchmark, its sizes (full and ``--quick``), the synthetic maps and
small helpers shared by its tables."""
from __future__ import annotations

import numpy as np

from avsm_dr.representations import describe, kinds
from avsm_dr.segments import Segments
from .synthetic import random_map
from .._common import measure

#: (kind, parameters) of every setting benchmarked on the synthetic maps; registered kinds
#: not named here join with their ``headline`` configuration (see :func:`settings`).
SETTINGS = [
    ("avsm", {"nodes": 4}), ("avsm", {"nodes": 8}), ("avsm", {"nodes": 16}),
    ("avsm", {"nodes": 8, "sort": True}), ("avsm", {"nodes": 8, "interpolation": "exp"}),
    ("exact", {}), ("osm", {"slices": 32}), ("fom", {"harmonics": 8}),
    ("fom", {"harmonics": 8, "depth_range": "texel"}), ("dsm", {"tolerance": 0.01}),
    ("moments", {}), ("basis", {"basis": "legendre", "n": 8}),
]
#: Settings run on the built-in scenes, in the memory table and the scaling plots.
SCENE_SETTINGS = [("avsm", {"nodes": 8}), ("exact", {}), ("osm", {"slices": 32}),
                  ("fom", {"harmonics": 8}), ("dsm", {"tolerance": 0.01}), ("moments", {})]
#: Settings whose build is slow per segment (DSM compresses on the host, about 1 us of CPU
#: per segment; its peak memory is ~2x its output since the chunked build) or sorts in
#: superlinear time (sort=True: sorting networks per texel on the device, a block merge for
#: texels over 64 segments, stable re-sorts for tied texels and float64):
#: skipped, with a note, on larger maps.
HEAVY = ("dsm", "sort")
HEAVY_MAX_SEGMENTS = 8_000_000
#: Offline kinds (``describe(kind)["offline"]``: greedy, optimal) run on maps up to this size.
OFFLINE_MAX_SEGMENTS = 200_000


def one(fn, repeats=3) -> dict:
    """:func:`~experiments._common.measure` of a single callable."""
    return measure({"x": fn}, repeats)["x"]


def counts_map(side: int, mean: int, seed: int = 1) -> Segments:
    """side^2 texels with uniform-random counts in [mean/2, 3 mean/2] of smoke-like segments."""
    lo, hi = max(1, mean // 2), max(1, (3 * mean) // 2)
    return random_map(side * side, lo, hi, seed=seed)


def label(kind, p) -> str:
    """``kind-name=value-...``: a setting's name in the tables."""
    return kind + "".join(f"-{k}={v}" for k, v in p.items())


def lookups(T: int, K: int, seed: int = 2):
    """K random receivers: (texel indices in [0, T), depths in [0, 1))."""
    rng = np.random.default_rng(seed)
    return rng.integers(0, T, K), rng.uniform(0, 1, K)


def heavy(kind, p) -> bool:
    """True for settings in :data:`HEAVY` (host memory or host sort per segment) and for
    kinds the registry marks ``offline`` (host builds superlinear in the segments)."""
    from avsm_dr import describe
    return kind in HEAVY or any(k in HEAVY and v for k, v in p.items()) or describe(kind)["offline"]


def max_segments(kind) -> int:
    """Largest map (segments) a heavy setting is run on: :data:`HEAVY_MAX_SEGMENTS`, or
    :data:`OFFLINE_MAX_SEGMENTS` for offline kinds."""
    from avsm_dr import describe
    return OFFLINE_MAX_SEGMENTS if describe(kind)["offline"] else HEAVY_MAX_SEGMENTS


def settings(base: list) -> list:
    """``base`` settings of registered kinds, then every other registered kind with its
    ``headline`` parameters (so a new kind is benchmarked without editing this file)."""
    named = {k for k, _ in base}
    return [(k, p) for k, p in base if k in kinds()] + \
        [(k, dict(describe(k)["headline"])) for k in kinds() if k not in named]


def pyplot():
    """matplotlib.pyplot on the Agg backend (files only)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt

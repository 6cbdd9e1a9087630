"""Skip a setting whose build would not fit in memory, before it runs on a large map.

Its build peak (the larger of process RSS growth and Dr.Jit's allocator watermark growth,
:class:`~experiments._common.Meter`; RSS growth under ``RSS_NOISE_BYTES`` counts as none) is
measured on two probes, the map's first texels holding about ``PROBE_SEGMENTS / 2`` and
``PROBE_SEGMENTS`` segments, and extrapolated linearly in the segments (the slope between the
probes: fixed costs do not scale):
``peak(S) = peak(n_2) + max(0, (peak(n_2) - peak(n_1)) / (n_2 - n_1)) (S - n_2)``.  A setting
whose estimate exceeds ``MEMORY_SHARE`` x MemAvailable (``/proc/meminfo``) is skipped with a
note in the run's notes, as heavy settings are; maps of up to ``PROBE_SEGMENTS`` segments
are not probed.
"""
from __future__ import annotations

import numpy as np

from avsm_dr import build
from .._common import Meter, sync
from .settings import label

#: Share of MemAvailable one build may take (the map, its host copy for the peers and the
#: tables' other results stay resident meanwhile).
MEMORY_SHARE = 0.5
#: Segments of the larger probe; maps no larger are not probed.
PROBE_SEGMENTS = 1 << 18
#: RSS growth below this is the interpreter's and allocator's page noise, not the build's: a
#: build that allocates nothing (exact) grew RSS by up to 64 KiB in 2 of 60 probes, which the
#: slope between small probes extrapolates about 12x.  Dr.Jit's watermark always counts.
RSS_NOISE_BYTES = 1 << 20


def available_bytes() -> float:
    """MemAvailable of ``/proc/meminfo`` (bytes); inf where it cannot be read."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024
    except OSError:
        pass
    return float("inf")


def estimate_peak(kind, p, seg) -> tuple[float, float]:
    """(estimated build peak on ``seg`` in bytes, probe slope in bytes per segment) of
    ``build(kind, seg, **p)`` (module docstring; compiled outside the measurement, on other
segments: a kind may cache work on its segments, e.g. the exact curve's points)."""
    points = []
    sync(build(kind, seg.select_texels(np.arange(min(4, seg.n_texels))), **p))    # compile
    for n in (PROBE_SEGMENTS // 2, PROBE_SEGMENTS):
        n_tex = max(1, int(np.searchsorted(seg.offsets, n, side="right")) - 1)
        probe = seg.select_texels(np.arange(n_tex))          # fresh: no cache of an earlier build
        with Meter() as m:
            out = build(kind, probe, **p)
            sync(out)
        del out
        rss = m.rss_bytes if m.rss_bytes > RSS_NOISE_BYTES else 0.0      # NaN (no VmHWM): none
        points.append((probe.n_segments, max(m.heap_bytes, rss)))
    (n1, p1), (n2, p2) = points
    slope = max(0.0, (p2 - p1) / (n2 - n1)) if n2 > n1 else p2 / max(n2, 1)
    return p2 + slope * (seg.n_segments - n2), slope


def too_big(kind, p, seg, name: str, notes: list) -> bool:
    """True, with a note appended to ``notes``, when the estimated build peak of ``(kind, p)``
    on ``seg`` (map ``name``) exceeds ``MEMORY_SHARE`` x MemAvailable."""
    if seg.n_segments <= PROBE_SEGMENTS:
        return False
    need, slope = estimate_peak(kind, p, seg)
    avail = available_bytes()
    if need <= MEMORY_SHARE * avail:
        return False
    notes.append(f"{label(kind, p)} skipped on {name} ({seg.n_segments} segments): build peak estimated at "
                 f"{need / 1e9:.2f} GB ({slope:.0f} B/segment between probes of up to {PROBE_SEGMENTS} segments) "
                 f"> {MEMORY_SHARE} x MemAvailable {avail / 1e9:.2f} GB")
    return True

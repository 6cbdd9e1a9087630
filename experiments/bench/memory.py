"""Peak memory of build and lookup per representation against ``nbytes_per_texel x
texels`` (``memory.csv``, ``memory.png``), with the common :class:`~experiments._common.Meter`.

``build_peak_over_formula`` = build peak / (``nbytes_per_texel x texels``), the output's
size; every online setting's target is :data:`BUILD_PEAK_TARGET` (at 6.5 M segments DSM was 70x, sorted
AVSM-8 42x and avsm_adaptive 30x before their builds ran in chunks of texels) and each row says
whether it meets it.  Rows:
:data:`MEMORY_SETTINGS` and every other registered kind with its ``headline`` parameters
(offline kinds only on maps they run on, :func:`~.settings.max_segments`).
"""
from __future__ import annotations

import drjit as dr
import numpy as np

from avsm_dr import build, describe
from .._common import Meter, sync
from . import memory_guard
from .settings import SCENE_SETTINGS, counts_map, heavy, label, lookups, max_segments, pyplot, settings


#: Largest build peak over the output's size that every setting is meant to reach on the memory
#: map; offline kinds (host dynamic programs, references) have none.
BUILD_PEAK_TARGET = 4.0
#: Settings of the memory table besides each registered kind's headline one.
MEMORY_SETTINGS = SCENE_SETTINGS + [("avsm", {"nodes": 16}), ("avsm", {"nodes": 8, "sort": True}),
                                    ("fom", {"harmonics": 16}), ("fom", {"harmonics": 8, "depth_range": "texel"})]


def memory_settings(n_segments: int) -> list:
    """:data:`MEMORY_SETTINGS` and every other registered kind's headline setting, less those
    :func:`~.settings.heavy` beyond their :func:`~.settings.max_segments`."""
    return [(k, p) for k, p in settings(MEMORY_SETTINGS) if not heavy(k, p) or n_segments <= max_segments(k)]


def _malloc_returns_memory():
    """glibc: serve allocations >= 64 KiB by mmap and trim freed memory, so that RSS
    growth reflects what a call allocates (the default adaptive threshold recycles freed
    blocks from the heap, which is already resident).  No-op elsewhere."""
    try:
        import ctypes
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, 1 << 16)      # M_MMAP_THRESHOLD
        libc.mallopt(-1, 1 << 16)      # M_TRIM_THRESHOLD
        return True
    except (OSError, AttributeError):
        return False


def peak_memory(fn) -> dict:
    """Peak memory while ``fn`` runs (:class:`~experiments._common.Meter`, after
    freeing Dr.Jit's allocation cache): dict(rss = process RSS growth (bytes, Linux VmHWM;
    NaN elsewhere), jit = growth of Dr.Jit's allocator watermark (its buffers, all sizes),
    out = fn's result).  (No tracemalloc: on CPython < 3.12.9 stopping it while Dr.Jit /
    Numba threads allocate crashes the process, which this benchmark hit.)"""
    with Meter() as m:
        out = fn()
        sync(out)
    return dict(rss=m.rss_bytes, jit=m.heap_bytes, out=out)


def memory(P, progress, notes) -> list[dict]:
    """Peak memory of build and lookup per setting against nbytes_per_texel x texels (settings
    that would not fit in memory skipped with a note, :mod:`.memory_guard`)."""
    seg = counts_map(P["memory_side"], 100)
    dr.eval(seg.z0, seg.z1, seg.optical_depth)
    tex, depth = lookups(seg.n_texels, P["lookups"])
    rows = []
    _malloc_returns_memory()
    seg_bytes = seg.n_segments * 3 * 4 + (seg.n_texels + 1) * 8
    for kind, p in memory_settings(seg.n_segments):
        if memory_guard.too_big(kind, p, seg, f"memory map {P['memory_side']}^2 x 100", notes):
            progress.update()
            continue
        build(kind, seg, **p).eval(tex[:10], depth[:10])     # compile outside the measurement
        mb = peak_memory(lambda: build(kind, seg, **p))
        rep = mb["out"]
        ml = peak_memory(lambda r=rep: r.eval(tex, depth))
        formula = rep.nbytes_per_texel * seg.n_texels
        peak = max(mb["rss"], mb["jit"])
        ratio = peak / formula if formula else float("nan")
        target = float("nan") if describe(kind)["offline"] else BUILD_PEAK_TARGET
        rows.append(dict(setting=label(kind, p), texels=seg.n_texels, segments=seg.n_segments,
                         nbytes_per_texel=rep.nbytes_per_texel, formula_bytes=formula, segments_bytes=seg_bytes,
                         build_peak_rss=mb["rss"], build_peak_jit=mb["jit"],
                         build_peak=peak, build_peak_over_formula=ratio,
                         build_peak_target=target,
                         meets_build_peak_target=bool(ratio <= target) if target == target else "",
                         lookup_receivers=tex.size, lookup_peak_rss=ml["rss"], lookup_peak_jit=ml["jit"],
                         lookup_peak=max(ml["rss"], ml["jit"]),
                         lookup_io_bytes=tex.size * 3 * 4))
        del rep, mb, ml
        progress.update()
    return rows


def plot(res, mem):
    """``memory.png``: formula bytes against build and lookup peaks."""
    plt = pyplot()
    # memory
    if mem:
        fig, ax = plt.subplots(figsize=(11, 4))
        x = np.arange(len(mem))
        for k, (key, lab) in enumerate((("formula_bytes", "bytes_per_texel x texels"),
                                        ("build_peak", "build peak"),
                                        ("build_peak_jit", "build: Dr.Jit allocator"),
                                        ("lookup_peak", "lookup peak"))):
            ax.bar(x + 0.2 * k, [max(r[key], 1) / 1e6 for r in mem], 0.2, label=lab)
        ax.set_xticks(x + 0.3, [r["setting"] for r in mem], rotation=30, ha="right", fontsize=7)
        ax.set_yscale("log")
        ax.set_ylabel("MB")
        ax.legend(fontsize=7)
        ax.set_title(f"{mem[0]['texels']} texels, {mem[0]['segments']} segments "
                     f"({mem[0]['segments_bytes'] / 1e6:.0f} MB of segments)")
        res.save_figure(fig, "memory.png")

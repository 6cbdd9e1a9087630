"""Capture cost against the bounding box: a plume in its tight box and in larger, empty boxes.

The same plume density (same voxel size, world position, light and shadow map) is
embedded in zero-padded grids whose box is

* 4x larger per axis (64x the voxels, almost all zero), and
* 4x larger in volume (4^(1/3) ~ 1.59x per axis).

Bar (empty space must be nearly free): capture of a padded grid costs < 1.5x the tight one.

Timings (:func:`~experiments._common.measure`): median of ``repeats`` interleaved
calls after one warm-up call whose time, JIT compile included, is reported separately, for

* ``capture``  - ``ad.capture(scene)`` from a NumPy array (host validation and the
  occupancy grid, O(voxels), included), and
* ``prepared`` - ``ad.capture`` with a :class:`~avsm_dr.capture.GridVolume` prepared once
  (what repeated captures of one grid cost), with its kernels' execution time from
  ``dr.kernel_history``.

    python -m experiments bench_capture [--quick]

Writes ``data.csv`` (one row per box), ``bench_capture.png`` and ``meta.json``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ._common import measure
from ._headline import num
from ._study import Study

#: What this study reproduces (a paper's figure or table, or the guide's section).
REPRODUCES = (
    "The guide's Performance section: throughput, peers (NumPy, Numba, Mitsuba at equal error), "
    "the machine's limit, scaling, skipped work and memory; capture cost against the bounding "
    'box; the whole frame (capture -> build -> lookups) per stage on the built-in scenes.'
)


#: (case name, zero-padding factor per axis); the first case is the reference.
CASES = (("tight", 1.0), ("4x per axis", 4.0), ("4x volume", 4.0 ** (1 / 3)))

#: Parameters of the full and the quick run.
FULL = dict(size=48, resolution=256, repeats=7, cases=[c for c, _ in CASES])
QUICK = dict(FULL, size=16, resolution=64, repeats=2)


def embed(scene, factor_per_axis: float):
    """The scene's grid zero-padded (same voxel size, plume centred) by ~factor per axis."""
    d = scene.density
    lo, hi = (np.asarray(b, np.float64) for b in scene.bbox)
    h = (hi - lo) / np.array(d.shape[::-1])
    n_new = np.round(np.array(d.shape) * factor_per_axis).astype(int)       # (z, y, x)
    off = (n_new - np.array(d.shape)) // 2
    big = np.zeros(tuple(n_new), np.float32)
    big[off[0]:off[0] + d.shape[0], off[1]:off[1] + d.shape[1], off[2]:off[2] + d.shape[2]] = d
    lo_new = lo - off[::-1] * h
    hi_new = lo_new + n_new[::-1] * h
    return dataclasses.replace(scene, name=scene.name + f"_x{factor_per_axis:.3g}", density=big,
                               bbox=(lo_new, hi_new))


def _compute(res, params: dict) -> dict:
    """Capture time, plain and with a prepared grid, per bounding box."""
    from avsm_dr import builtin_scenes as scene_lib
    from avsm_dr.capture import GridVolume, capture

    tight = scene_lib.plume(size=params["size"])
    scenes = [(name, tight if f == 1.0 else embed(tight, f)) for name, f in CASES]
    r = params["resolution"]
    fns = {}
    for name, sc in scenes:
        grid = GridVolume.prepare(sc.density, sc.bbox)
        fns[name, "capture"] = (lambda sc=sc: capture(sc, resolution=r, order="depth"))
        fns[name, "prepared"] = (lambda sc=sc, g=grid: capture(sc, resolution=r, density=g, order="depth"))
    m = measure(fns, repeats=params["repeats"])

    rows = []
    ref = {k: m["tight", k] for k in ("capture", "prepared")}
    for name, sc in scenes:
        c, p = m[name, "capture"], m[name, "prepared"]
        cap = c["out"]
        if p["out"].segments.n_segments != cap.segments.n_segments:
            raise RuntimeError(f"{name}: prepared and plain capture disagree on the segment count")
        grid = cap.stats.get("grid", {})
        rows.append({
            "case": name, "voxels": int(sc.density.size), "shape": "x".join(map(str, sc.density.shape)),
            "segments": cap.segments.n_segments, "lanes": grid.get("lanes"), "iterations": grid.get("iterations"),
            "first_call_s": c["first_s"], "first_call_jit_s": c["jit_s"],
            "kernels_compiled": c["compiled"], "kernels_from_disk_cache": c["from_disk"],
            "capture_s": c["wall_s"], "prepared_s": p["wall_s"], "kernels_s": p["kernel_s"],
            "ratio_capture": c["wall_s"] / ref["capture"]["wall_s"],
            "ratio_prepared": p["wall_s"] / ref["prepared"]["wall_s"],
            "ratio_kernels": p["kernel_s"] / ref["prepared"]["kernel_s"],
        })
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 3.5))
    x = np.arange(len(rows))
    for j, (key, lab) in enumerate((("ratio_capture", "capture (from NumPy)"),
                                    ("ratio_prepared", "capture (prepared grid)"),
                                    ("ratio_kernels", "kernels only"))):
        ax.bar(x + 0.27 * (j - 1), [row[key] for row in rows], 0.27, label=lab)
    ax.axhline(1.5, color="k", ls="--", lw=0.8, label="bar: 1.5x")
    ax.set_xticks(x, [f"{row['case']}\n{row['shape']}" for row in rows])
    ax.set_ylabel("time / tight box")
    ax.set_title(f"capture at {r}^2 (median of {params['repeats']} after warm-up)")
    ax.legend(fontsize=7)
    res.save_figure(fig, "bench_capture.png")

    summary = {row["case"]: {k: row[k] for k in ("ratio_capture", "ratio_prepared", "ratio_kernels")}
               for row in rows}
    summary["within_bar"] = all(row["ratio_prepared"] < 1.5 for row in rows)
    for row in rows:
        print(f"{row['case']:12s} {row['shape']:>13s} voxels={row['voxels']:>9d} segments={row['segments']:>7d} "
              f"first={row['first_call_s'] * 1e3:6.1f} ms (jit {row['first_call_jit_s'] * 1e3:5.1f} ms) | "
              f"capture={row['capture_s'] * 1e3:6.1f} ms (x{row['ratio_capture']:.2f}) "
              f"prepared={row['prepared_s'] * 1e3:6.1f} ms (x{row['ratio_prepared']:.2f}) "
              f"kernels={row['kernels_s'] * 1e3:5.1f} ms (x{row['ratio_kernels']:.2f})")
    return dict(rows=rows, summary=summary)

def _headline(s: dict) -> list[str]:
    """Capture time in each larger, empty box over the tight box's, and the 1.5x bar."""
    out = [f"{case}: capture {num(r['ratio_capture'])}x the tight box's (prepared {num(r['ratio_prepared'])}x, "
           f"kernels {num(r['ratio_kernels'])}x)" for case, r in s.items() if isinstance(r, dict)]
    return out + [f"prepared capture within 1.5x of the tight box's in every case: {num(s.get('within_bar'))}"]


STUDY = Study("bench_capture", "Capture cost against the bounding box: a plume in its tight box and in larger, "
              "empty boxes", REPRODUCES, FULL, QUICK, _compute, headline=_headline)
run = STUDY.run

"""The whole frame: capture -> build -> lookups, per stage, for every built-in scene.

For each built-in scene (and a user grid, ``run(grid=...)``: a ``.vol`` path or a
:class:`~avsm_dr.scene.Scene`), each shadow-map resolution and each grid capture method
(``'march'``: Simpson steps of half a voxel; ``'exact'``: one segment per dual-cell
crossing, :mod:`avsm_dr.capture.dda`), one frame per representation kind of the registry
(``ad.kinds()``, parameters ``ad.describe(kind)['headline']``):

* ``capture`` - ``ad.capture(scene, resolution, method=...)`` from the scene's NumPy
  density (host preparation included), segments per second;
* ``build``   - ``ad.build(kind, segments, **headline)`` on that capture's output, its
  buffers evaluated, segments per second;
* ``lookup``  - ``rep.eval(texel, depth)`` for ``lookups`` receivers (the scene's
  receivers, resampled with jitter; texel and depth already on the device), lookups per second.

Timing (:func:`~experiments._common.measure`): every stage of one (scene,
resolution) is called once (first call, JIT compile reported separately as
``*_first_s`` / ``*_jit_s``), then ``repeats`` rounds interleaved across all stages, so
load from other processes hits them alike; medians.  A kind whose build's declared work
estimate (:data:`.error_curves.cost.FRAME_WORK`: units of about 7 ns of one core, from the
capture's segment and texel counts; never a clock, so which builds run does not depend on the
machine's load) exceeds ``build_budget`` is skipped at that size with a note; kinds without a
model are never skipped.  The budgets (:data:`BUILD_BUDGET`: about 1 s of one core quick, 60 s
full) skip no built-in scene's build (the largest full-mode estimate, ``dsm`` on the marched
``simulated_plume`` at 1024^2, about 41 M segments, is about 2.5e9 units): they guard user grids.
Resolutions above the capture's limit are skipped with a note, and so is a build the memory
guard refuses (its message; e.g. DSM at tolerance 0.01 on a 1024^2 map of ``three_columns`` on a
machine with less memory).

The headline ratios (``meta.json`` summary, wall and process-CPU time): capture
of the plume at the largest resolution over the AVSM-8 build on its output, per capture
method; and sorted over unsorted AVSM-8 end to end (``build(..., sort=True)``, which sorts
each texel on the device, vs ``sort=False``) on the capture's segments shuffled inside every
texel (``random_order``, shuffled once on the host outside the timing), per (scene,
resolution, method): columns ``random_unsorted_s`` / ``random_sorted_s`` of the AVSM rows.
Both builds start from the segments' empty cache (``drop_cache(keep=())``), as on a new
capture: the sort's layout (``Segments._sort_plan``) is part of the sorted build's time.

    python -m experiments frame [--quick]

Each row records the insertion ``order`` its kind's build saw ('depth': the capture is front to
back, for the kinds whose build depends on the order; '-' otherwise).

Writes ``data.csv`` (one row per frame: scene, resolution, method, kind), ``frame.png``
(stacked bars: capture, build, lookup) and ``meta.json``.
"""

from __future__ import annotations

import inspect
import json
import math
import os
from pathlib import Path

import drjit as dr
import numpy as np
from tqdm import tqdm

from avsm_dr import _arrays as A
from avsm_dr import backend
from ._common import Results, measure
from ._headline import num
from ._study import Option, Study

#: What this study reproduces (a paper's figure or table, or the guide's section).
REPRODUCES = (
    "The guide's Performance section: throughput, peers (NumPy, Numba, Mitsuba at equal error), "
    "the machine's limit, scaling, skipped work and memory; capture cost against the bounding "
    'box; the whole frame (capture -> build -> lookups) per stage on the built-in scenes.'
)


RESOLUTIONS = (256, 512, 1024, 2048)
QUICK_RESOLUTIONS = (64, 128)
LOOKUPS = 1 << 20
QUICK_LOOKUPS = 1 << 16
METHODS = ("march", "exact")
#: Grid resolution (voxels per unit, the scenes' ``size``) per mode; the plume at 48 is
#: a 48 x 72 x 48 grid.
SIZES = {"quick": 16, "full": 48}
#: Skip a kind's build where its work estimate (:data:`.error_curves.cost.FRAME_WORK`, units of
#: about 7 ns of one core) exceeds this: about 1 s (quick) and 60 s (full) of one core.
BUILD_BUDGET = {"quick": 1.4e8, "full": 8.6e9}

#: Parameters of the full and the quick run (``scenes`` None: every built-in scene; ``kinds``:
#: the registry's, filled in).
FULL = dict(scenes=None, resolutions=list(RESOLUTIONS), methods=list(METHODS), size=SIZES["full"], lookups=LOOKUPS,
            repeats=3, kinds=None, build_budget=BUILD_BUDGET["full"])
QUICK = dict(FULL, resolutions=list(QUICK_RESOLUTIONS), size=SIZES["quick"], lookups=QUICK_LOOKUPS, repeats=1,
             build_budget=BUILD_BUDGET["quick"])


# ------------------------------------------------------------------ scenes
def builtin_scenes(size: int, names=None) -> dict:
    """The built-in scenes ``names`` (default all), at grid ``size`` where the scene takes one."""
    from avsm_dr import builtin_scenes as lib
    out = {}
    for name in lib.SCENES if names is None else names:
        fn = lib.SCENES[name]
        kw = {"size": size} if "size" in inspect.signature(fn).parameters else {}
        out[name] = fn(**kw)
    return out


def grid_scene(grid):
    """A user grid as a scene: a ``.vol`` path (its header's box, a directional light
    along (1, -0.3, 0.25), receivers resampled from the non-zero voxels) or a Scene."""
    from avsm_dr.io import read_vol
    from avsm_dr.scene import DirectionalLight, Scene
    if isinstance(grid, Scene):
        return grid
    if not isinstance(grid, (str, os.PathLike)):
        raise ValueError(f"grid: expected a .vol path or a Scene, got {type(grid).__name__}")
    try:
        dens, bbox = read_vol(grid, with_bbox=True)
    except (OSError, ValueError) as exc:
        raise ValueError(f"grid: cannot read {str(grid)!r}: {exc}") from None
    if dens.ndim != 3:
        raise ValueError(f"grid: {str(grid)!r} has {dens.shape[-1]} channels, expected 1")
    lo, hi = (np.asarray(b, np.float64) for b in bbox)
    idx = np.argwhere(dens > 0)
    rng = np.random.default_rng(0)
    if idx.size:
        pick = idx[rng.integers(0, idx.shape[0], 1024)][:, ::-1]          # (x, y, z) voxel indices
        rec = lo + (pick + rng.random((1024, 3))) * (hi - lo) / np.array(dens.shape[::-1])
    else:
        rec = rng.uniform(lo, hi, (1024, 3))
    return Scene("grid:" + Path(grid).stem, DirectionalLight((1.0, -0.3, 0.25)), rec,
                 density=dens, bbox=(lo, hi))


def lookup_points(scene, n: int, rng) -> np.ndarray:
    """``n`` receivers: the scene's receivers resampled, jittered by 1e-3 of its extent."""
    rec = np.asarray(scene.receivers, np.float64)
    ext = float(np.ptp(rec, axis=0).max()) or 1.0
    return rec[rng.integers(0, rec.shape[0], n)] + rng.normal(0, 1e-3 * ext, (n, 3))


def random_order(seg, rng):
    """``seg`` with the segments of every texel in random order (flagged unsorted)."""
    from avsm_dr.segments import Segments
    if seg.n_segments == 0:
        return seg
    tex = np.repeat(np.arange(seg.n_texels), seg.counts)
    idx = A.to_uint32(np.lexsort((rng.random(seg.n_segments), tex)).astype(np.uint32))
    F = seg.Float
    out = Segments(seg.offsets, *(dr.gather(F, a, idx) for a in (seg.z0, seg.z1, seg.optical_depth)), seg.dtype)
    dr.eval(out.z0, out.z1, out.optical_depth)
    return out


def _build_evaluated(kind: str, seg, params: dict):
    """``ad.build`` with every Dr.Jit buffer of the result evaluated."""
    from avsm_dr import build
    rep = build(kind, seg, **params)
    dr.eval(vars(rep))
    return rep


def _build_or_refuse(built: dict, refused: dict, key, kind: str, seg, params: dict):
    """``built[key]`` = :func:`_build_evaluated`, or None with ``refused[key]`` = the reason
    when the memory guard refuses the build (a full run's largest maps: a DSM of 1024^2 texels
    at a 0.01 tolerance); any other error propagates."""
    if key in refused:
        return None
    from avsm_dr.validation import MemoryBudgetError
    try:
        built[key] = _build_evaluated(kind, seg, params)
    except MemoryBudgetError as exc:
        refused[key] = "build refused by the memory guard: " + " ".join(str(exc).split())
        return None
    return built[key]


# ------------------------------------------------------------------ one (scene, resolution)
def frame_rows(name, scene, resolution: int, methods, kinds, n_lookups: int, repeats: int,
               budget: float, rng) -> list[dict]:
    """Rows of one (scene, resolution): one per (method, kind); a kind whose work estimate
    (:data:`.error_curves.cost.FRAME_WORK`) exceeds ``budget`` units is skipped with a note."""
    from avsm_dr import capture
    from avsm_dr import describe
    from .error_curves.cost import FRAME_WORK
    from .error_curves.labels import order_dependent
    has_grid = scene.density is not None
    methods = methods if has_grid else methods[:1]          # no grid: the method changes nothing
    caps = {m: capture(scene, resolution=resolution, method=m, order="depth") for m in methods}
    pts = lookup_points(scene, n_lookups, rng)
    t = backend.types()
    fns, notes, built, refused = {}, {}, {}, {}
    for m, cap in caps.items():
        fns["capture", m, ""] = (lambda m=m: capture(scene, resolution=resolution, method=m, order="depth"))
        seg = cap.segments
        texel, depth = cap.lookup(pts)
        tex_d = t.UInt32(texel.astype(np.uint32))
        dep_d = A.to_float(depth, seg.Float)
        for kind in kinds:
            params = describe(kind)["headline"]
            if describe(kind)["offline"]:
                notes[m, kind] = "skipped: offline reference (not part of a frame)"
                continue
            work = FRAME_WORK[kind](seg, params) if kind in FRAME_WORK else 0.0
            if work > budget:
                notes[m, kind] = (f"skipped: build work estimate {work:.3g} > limit {budget:.3g} units "
                                  f"(about 7 ns of one core each) at {seg.n_segments} segments")
                continue
            # the lookups read the representation of the build's latest call (measure() calls
            # every stage once, in this order, before the interleaved repeats); a build the
            # memory guard refuses is noted and skipped, its lookups too
            fns["build", m, kind] = (lambda key=(m, kind), kind=kind, seg=seg, params=params:
                                     _build_or_refuse(built, refused, key, kind, seg, params))
            fns["lookup", m, kind] = (lambda key=(m, kind), a=tex_d, b=dep_d:
                                      built[key].eval(a, b) if key in built else None)
            if kind == "avsm":                           # sorted vs unsorted on random-order input
                shuffled = random_order(seg, rng)
                for srt in (False, True):
                    fns["random", m, srt] = (lambda s=shuffled, srt=srt, params=params:
                                             _build_evaluated("avsm", s.drop_cache(keep=()), dict(params, sort=srt)))
    r = measure(fns, repeats=repeats)
    notes.update({key: f"skipped: {why}" for key, why in refused.items()})

    rows = []
    for m, cap in caps.items():
        c = r["capture", m, ""]
        st = c["out"].stats.get("grid", {})
        segs = cap.segments.n_segments
        lanes = st.get("lanes", 0)
        base = dict(scene=name, grid_shape="x".join(map(str, scene.density.shape)) if has_grid else "",
                    resolution=resolution, method=m if has_grid else "", segments=segs, lanes=lanes,
                    iterations_per_ray=st.get("iterations", 0) / lanes if lanes else 0.0,
                    # density evaluations: two per iteration in both methods (step end and
                    # midpoint; crossing end and midpoint); voxel reads: 16 + 1 vs 8 + 1
                    samples_per_ray=2 * st.get("iterations", 0) / lanes if lanes else 0.0,
                    voxel_reads_per_ray=(17 if m == "march" else 9) * st.get("iterations", 0) / lanes
                    if lanes else 0.0,
                    capture_s=c["wall_s"], capture_first_s=c["first_s"], capture_jit_s=c["jit_s"],
                    capture_grid_s=st.get("seconds", float("nan")),
                    capture_segments_per_s=segs / c["wall_s"] if c["wall_s"] > 0 else float("nan"))
        for kind in kinds:
            row = dict(base, kind=kind, params=json.dumps(describe(kind)["headline"], sort_keys=True),
                       order="depth" if order_dependent(kind) else "-")     # the capture's, front to back
            if (m, kind) in notes:
                row.update(build_s=float("nan"), lookup_s=float("nan"), frame_s=float("nan"),
                           note=notes[m, kind])
                rows.append(row)
                continue
            b, lk = r["build", m, kind], r["lookup", m, kind]
            frame = c["wall_s"] + b["wall_s"] + lk["wall_s"]
            if kind == "avsm":
                ru, rs = r["random", m, False], r["random", m, True]
                row.update(random_unsorted_s=ru["wall_s"], random_sorted_s=rs["wall_s"],
                           random_unsorted_cpu_s=ru["cpu_s"], random_sorted_cpu_s=rs["cpu_s"])
            row.update(build_s=b["wall_s"], build_first_s=b["first_s"], build_jit_s=b["jit_s"],
                       build_segments_per_s=segs / b["wall_s"] if b["wall_s"] > 0 else float("nan"),
                       lookups=n_lookups, lookup_s=lk["wall_s"], lookup_first_s=lk["first_s"],
                       lookup_jit_s=lk["jit_s"], lookups_per_s=n_lookups / lk["wall_s"] if lk["wall_s"] > 0
                       else float("nan"),
                       frame_s=frame, capture_share=c["wall_s"] / frame, build_share=b["wall_s"] / frame,
                       lookup_share=lk["wall_s"] / frame,
                       capture_over_build=c["wall_s"] / b["wall_s"] if b["wall_s"] > 0 else float("nan"),
                       capture_over_build_cpu=c["cpu_s"] / b["cpu_s"] if b["cpu_s"] > 0 else float("nan"),
                       note="")
            rows.append(row)
    return rows


# ------------------------------------------------------------------ figure
def plot(rows, res: Results, kinds) -> None:
    """Stacked bars (capture, build, lookup) per kind; one panel per (scene, resolution)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    resolutions = list(dict.fromkeys(r["resolution"] for r in rows))
    fig, axes = plt.subplots(len(scenes), len(resolutions), figsize=(3.2 * len(resolutions) + 1, 2.3 * len(scenes)),
                             squeeze=False)
    colors = {"capture": "tab:blue", "build": "tab:orange", "lookup": "tab:green"}
    for i, sc in enumerate(scenes):
        for j, reso in enumerate(resolutions):
            ax = axes[i, j]
            sel = [r for r in rows if r["scene"] == sc and r["resolution"] == reso]
            methods = list(dict.fromkeys(r["method"] for r in sel))
            w = 0.8 / max(len(methods), 1)
            for k, m in enumerate(methods):
                x = np.arange(len(kinds)) + (k - (len(methods) - 1) / 2) * w
                got = {r["kind"]: r for r in sel if r["method"] == m}
                bottom = np.zeros(len(kinds))
                for stage in ("capture", "build", "lookup"):
                    v = np.array([got[kd][f"{stage}_s"] if kd in got and math.isfinite(got[kd][f"{stage}_s"])
                                  else 0.0 for kd in kinds]) * 1e3
                    ax.bar(x, v, w, bottom=bottom, color=colors[stage], hatch="//" if k else None,
                           edgecolor="white", linewidth=0.3,
                           label=f"{stage}" + (f" ({m})" if m else "") if i == j == 0 else None)
                    bottom += v
            ax.set_xticks(np.arange(len(kinds)), kinds, rotation=60, fontsize=6)
            ax.tick_params(axis="y", labelsize=6)
            ax.set_title(f"{sc} {reso}^2", fontsize=7)
            if j == 0:
                ax.set_ylabel("ms per frame", fontsize=7)
    axes[0, 0].legend(fontsize=5, ncol=2)
    fig.suptitle("frame = capture + build + lookups (median after warm-up; hatched: second capture method)",
                 fontsize=8)
    fig.tight_layout()
    res.save_figure(fig, "frame.png")


# ------------------------------------------------------------------ run
def _resolve(params: dict, quick: bool, grid=None) -> dict:
    """The options checked (``ValueError`` naming the argument); ``scenes`` None: every
    built-in scene; the registry's kinds; ``grid``: the user's grid's name."""
    from avsm_dr import kinds as all_kinds
    from avsm_dr.builtin_scenes import SCENES
    params["methods"] = list(params["methods"])
    for m in params["methods"]:
        if m not in METHODS:
            raise ValueError(f"methods: expected a subset of {METHODS}, got {tuple(params['methods'])!r}")
    params["scenes"] = list(SCENES) if params["scenes"] is None else list(params["scenes"])
    for n in params["scenes"]:
        if n not in SCENES:
            raise ValueError(f"scenes: unknown scene {n!r}; known: {sorted(SCENES)}")
    if grid is not None:
        grid_scene(grid)
    return dict(params, resolutions=list(params["resolutions"]), repeats=int(params["repeats"]),
                kinds=list(all_kinds()), grid=None if grid is None else str(getattr(grid, "name", grid)))


def _compute(res, params: dict, grid=None) -> dict:
    """Every scene at every resolution: capture, build and lookups per stage and kind;
    ``grid``: also this grid (a ``.vol`` path or a Scene)."""
    from avsm_dr.capture import RESOLUTION_RANGE
    reso, methods, kinds = params["resolutions"], params["methods"], params["kinds"]
    user = grid_scene(grid) if grid is not None else None
    scenes = builtin_scenes(params["size"], params["scenes"])
    if user is not None:
        scenes[user.name] = user
    rng = np.random.default_rng(0)
    rows, skipped = [], []
    todo = [(n, r) for n in scenes for r in sorted(reso)]
    for name, r in tqdm(todo, desc="frame", unit="size"):
        if not RESOLUTION_RANGE[0] <= r <= RESOLUTION_RANGE[1]:
            skipped.append(f"{name} {r}^2: outside the capture's resolutions {RESOLUTION_RANGE}")
            continue
        rows += frame_rows(name, scenes[name], r, list(methods), kinds, params["lookups"], params["repeats"],
                           params["build_budget"], rng)
    plot(rows, res, kinds)

    summary = {"skipped": skipped + [f"{r['scene']} {r['resolution']}^2 {r['method']} {r['kind']}: {r['note']}"
                                     for r in rows if r.get("note")]}
    for name in scenes:
        done = [r for r in rows if r["scene"] == name and r["kind"] == "avsm" and math.isfinite(r["build_s"])]
        if not done:
            continue
        top = max(r["resolution"] for r in done)
        for r in done:
            if r["resolution"] == top:
                key = f"{name}_{top}_{r['method'] or 'capture'}"
                summary[key + "_capture_over_avsm8_build"] = r["capture_over_build"]
                summary[key + "_capture_over_avsm8_build_cpu"] = r["capture_over_build_cpu"]
                summary[key + "_sorted_over_unsorted_random"] = r["random_sorted_s"] / r["random_unsorted_s"]
                summary[key + "_sorted_over_unsorted_random_cpu"] = (r["random_sorted_cpu_s"]
                                                                     / r["random_unsorted_cpu_s"])
                summary[key + "_capture_s"] = r["capture_s"]
                summary[key + "_segments"] = r["segments"]
    for key, v in summary.items():
        if key.endswith(("_build", "_build_cpu", "_random", "_random_cpu")):
            print(f"{key}: {v:.2f}")
    return dict(rows=rows, summary=summary)

def _headline(s: dict) -> list[str]:
    """Per scene and capture method at its largest resolution: the capture's time (and
    segments) against AVSM-8's build, sorted against unsorted random-order builds."""
    out = []
    for key, v in s.items():
        if key.endswith("_capture_s"):
            base = key[:-len("_capture_s")]
            scene, res, method = base.rsplit("_", 2)
            out.append(f"{scene} {res}^2 {method}: capture {num(v * 1e3)} ms ({num(s[base + '_segments'])} "
                       f"segments) = {num(s[base + '_capture_over_avsm8_build'])}x the AVSM-8 build "
                       f"(CPU {num(s[base + '_capture_over_avsm8_build_cpu'])}x); sorted build "
                       f"{num(s[base + '_sorted_over_unsorted_random'])}x unsorted")
    if s.get("skipped"):
        out.append(f"skipped: {len(s['skipped'])} (listed in meta.json)")
    return out


STUDY = Study(
    "frame", "The whole frame: capture -> build -> lookups, per stage, for every built-in scene", REPRODUCES,
    FULL, QUICK, _compute, resolve=_resolve,
    options=(Option("grid", "also time this grid (a .vol file)", metavar="VOL"),
             Option("scenes", "built-in scenes to time (default: all)", nargs="+", metavar="SCENE"),
             Option("resolutions", "shadow-map resolutions (default: the mode's)", type=int, nargs="+",
                    metavar="R"),
             Option("methods", f"capture methods, a subset of {METHODS}", nargs="+", metavar="METHOD"),
             Option("repeats", "timing repeats (default: the mode's)", type=int, metavar="N")), headline=_headline)
run = STUDY.run

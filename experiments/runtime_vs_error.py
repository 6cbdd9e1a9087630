"""Build and lookup time against error for every representation and setting, per scene,
with the Pareto front (no other setting is both faster and more accurate).

Times: median of repeats after a warm-up call (JIT compile excluded, reported as
``first_call_s``); error: RMSE against the exact curve at the scene's receivers.

Fair-comparison columns: ``order`` (the capture's, 'depth', for the kinds whose build depends on
it; '-' otherwise), ``signed_mean`` and ``leak_share`` (error > 0.02) at the receivers,
``depth_l2`` (:func:`avsm_dr.evaluation.depth_l2` against the exact curve), ``bytes`` (sparse
layout) and ``bytes_dense`` (= ``bytes_per_texel``); ``pareto_depth_l2`` marks the front of
time against depth L2 (the summary lists both fronts).  One configuration per scene (the
scene's own seed and light): no interval, every front is indicative.
"""

from __future__ import annotations

import numpy as np
from tqdm import tqdm

from avsm_dr import build, configurations, describe, kinds
from avsm_dr.metrics import error_stats
from ._common import timed
from ._headline import wrap
from ._study import Study
from .error_curves import SCENES

#: What this study reproduces (a paper's figure or table, or the guide's section).
REPRODUCES = (
    'Salvi et al., "Adaptive Volumetric Shadow Maps", EGSR 2010, figures 5-6 and the claims of '
    'sections 3-5: error of AVSM, FOM, OSM, DSM, moments against node / coefficient count and '
    'bytes per texel on the built-in scenes, the depth-range sweep, and findings.json.'
)

#: Parameters of the full and the quick run (``sweeps``: every kind's settings, filled in).
FULL = dict(scenes=SCENES, resolution=256, repeats=7, lookups_per_receiver=1, sweeps=None)
QUICK = dict(FULL, scenes=SCENES[:2], resolution=64, repeats=3)


def pareto(points):
    """Indices of (time, error) points not dominated by any other."""
    idx = []
    for i, (t, e) in enumerate(points):
        if not any((t2 <= t and e2 <= e) and (t2 < t or e2 < e) for j, (t2, e2) in enumerate(points) if j != i):
            idx.append(i)
    return idx


def _resolve(params: dict, quick: bool) -> dict:
    """Every registered kind's size sweep (``ad.configurations``)."""
    return dict(params, sweeps={k: configurations(k, quick) for k in kinds() if k != "exact"})


def _compute(res, params: dict) -> dict:
    """Build and lookup time and error of every setting, per scene, and the Pareto fronts."""
    from avsm_dr import builtin_scenes as scene_lib
    from avsm_dr import capture
    from avsm_dr.evaluation import curve_values, depth_l2
    from .error_curves.labels import order_dependent
    names = params["scenes"]
    rows = []
    for name in tqdm(names, desc="runtime_vs_error", unit="scene"):
        scene = getattr(scene_lib, name)()
        cap = capture(scene, resolution=params["resolution"], order="depth")
        texel, depth = cap.lookup(np.asarray(scene.receivers))
        ex_rep = build("exact", cap.segments)
        t_ex, first_ex, exact = timed(lambda: ex_rep.eval(texel, depth), repeats=params["repeats"])
        exact = np.asarray(exact, dtype=np.float64)
        curve = curve_values(ex_rep, cap.segments)
        rows.append(dict(scene=name, method="exact", param="", build_s=0.0, lookup_s=t_ex, first_call_s=first_ex,
                         rmse=0.0, max_error=0.0, bytes_per_texel=ex_rep.nbytes_per_texel,
                         segments=cap.segments.n_segments, receivers=len(texel), order="-", signed_mean=0.0,
                         leak_share=0.0, depth_l2=0.0, bytes=ex_rep.nbytes_sparse_per_texel,
                         bytes_dense=ex_rep.nbytes_per_texel))
        for kind, settings in params["sweeps"].items():
            size = describe(kind)["size"]
            for p in settings:
                v = p.get(size, "") if size else ""
                t_b, first_b, rep = timed(lambda: build(kind, cap.segments, **p), repeats=params["repeats"])
                t_l, first_l, est = timed(lambda: rep.eval(texel, depth), repeats=params["repeats"])
                st = error_stats(est, exact)
                rows.append(dict(scene=name, method=kind, param=v, build_s=t_b, lookup_s=t_l,
                                 first_call_s=first_b + first_l, rmse=st["rmse"], max_error=st["max_error"],
                                 bytes_per_texel=rep.nbytes_per_texel, segments=cap.segments.n_segments,
                                 receivers=len(texel), order="depth" if order_dependent(kind) else "-",
                                 signed_mean=st["mean_error"], leak_share=st["leak_fraction"],
                                 depth_l2=depth_l2(rep, cap.segments, exact=curve),
                                 bytes=rep.nbytes_sparse_per_texel, bytes_dense=rep.nbytes_per_texel))
    for name in names:
        rs = [r for r in rows if r["scene"] == name and r["method"] != "exact"]
        for key, col in (("rmse", "pareto"), ("depth_l2", "pareto_depth_l2")):
            front = pareto([(r["build_s"] + r["lookup_s"], r[key]) for r in rs])
            for i, r in enumerate(rs):
                r[col] = i in front
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(names), figsize=(4.5 * len(names), 3.8), squeeze=False)
    colors = {"avsm": "C0", "fom": "C1", "osm": "C2", "dsm": "C3"}
    for ax, name in zip(axes[0], names):
        for kind, c in colors.items():
            rs = [r for r in rows if r["scene"] == name and r["method"] == kind]
            if rs:
                ax.loglog([1e3 * (r["build_s"] + r["lookup_s"]) for r in rs], [max(r["rmse"], 1e-6) for r in rs],
                          "o-", color=c, label=kind)
                for r in rs:
                    ax.annotate(str(r["param"]), (1e3 * (r["build_s"] + r["lookup_s"]), max(r["rmse"], 1e-6)),
                                fontsize=6)
        pf = sorted([r for r in rows if r["scene"] == name and r.get("pareto")],
                    key=lambda r: r["build_s"] + r["lookup_s"])
        ax.loglog([1e3 * (r["build_s"] + r["lookup_s"]) for r in pf], [max(r["rmse"], 1e-6) for r in pf], "k:", lw=1,
                  label="Pareto front")
        ax.set_title(name)
        ax.set_xlabel("build + lookup time (ms)")
    axes[0][0].set_ylabel("RMSE vs exact")
    axes[0][-1].legend(fontsize=7)
    res.save_figure(fig, "runtime_vs_error.png")
    summary = {name: [f"{r['method']}-{r['param']}" for r in rows if r["scene"] == name and r.get("pareto")]
               for name in names}
    front_l2 = {name: [f"{r['method']}-{r['param']}" for r in rows if r["scene"] == name
                       and r.get("pareto_depth_l2")] for name in names}
    return dict(rows=rows, summary={"pareto_front": summary, "pareto_front_depth_l2": front_l2,
                                    "indicative": "one configuration per scene"},
                result={"summary": summary})

def _headline(s: dict) -> list[str]:
    """Per scene: the settings on the time-error Pareto front."""
    return [line for scene, front in s.get("pareto_front", {}).items()
            for line in wrap(f"{scene}, on the time-error Pareto front: ", [str(x).rstrip("-") for x in front])]


STUDY = Study("runtime_vs_error", "Build and lookup time against error for every representation and setting",
              REPRODUCES, FULL, QUICK, _compute, resolve=_resolve, headline=_headline)
run = STUDY.run

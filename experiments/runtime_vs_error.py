"""Build and lookup time against error for every representation and setting, per scene,
with the Pareto front (no other setting is both faster and more accurate), over
configurations (scene seed x light; full mode: :data:`FULL_CONFIGS`, ten per scene, two of
them a spot light).

Error, per configuration (in-volume receivers by contribution, :func:`avsm_dr.receivers.in_volume`,
nearest-texel lookups, against the exact curve of the same segments): ``rmse``,
``max_error``, ``signed_mean`` (> 0: light leaking) and ``leak_share`` (error > 0.02,
:data:`avsm_dr.metrics.THRESHOLD`), and ``depth_l2`` (:func:`avsm_dr.evaluation.depth_l2`).

Time, per configuration (:func:`avsm_dr.evaluation.timing.measure`, every call synced):
``lookup_s`` the median of ``repeats`` lookups after a warm-up; ``build_s`` the median of
``build_repeats`` builds, with a warm-up build (``first_call_s``, JIT compile included) only
in the scene's first configuration, so later configurations time warm kernels without a
second warm-up (full mode: 11 builds per setting and scene, where one configuration timed
with seven repeats took 8).  Every timed build is cold (:meth:`avsm_dr.Segments.drop_cache`):
nothing an earlier build cached on the segments (``greedy``'s removal order, the curve points)
is reused, only their layout (device offsets).  ``time_ratio``:
build + lookup time over :data:`REFERENCE`'s in the same configuration (same process).
Per setting the time is the median over configurations of ``time_ratio``, the error the
mean over configurations of ``rmse`` (``depth_l2``); ``pareto`` (``pareto_depth_l2``) marks
the settings on the scene's front of that time against that error (repeated on every
configuration's row), ``pareto_in_config`` (``pareto_depth_l2_in_config``) the settings on
the configuration's own front of ``time_ratio`` against ``rmse`` (``depth_l2``).

The trade that keeps the full run to about 28 minutes of CPU time (1707 s user and system,
measured on a full run with every build timed cold; 28 min 29 s wall on 2 busy cores):
``optimal`` (the best breakpoint subset, a host NumPy DP and the costliest build: 86 of 128
CPU seconds of simulated_plume's first configuration, 63 of 90 of three_columns') is left out
(``exclude``, both modes).  Built with the quick parameters (64^2, plume and three_columns, two
configurations each) it took 3 to 220 times AVSM-8's time and no setting of it was on any
front, pooled or per configuration; ``avsm_gap`` and ``insertion_order`` measure it against
AVSM over the same configurations.

Other columns: ``order`` (the capture's, 'depth', for the kinds whose build depends on it;
'-' otherwise), ``bytes`` (sparse layout) and ``bytes_dense`` (= ``bytes_per_texel``).

``findings.json``, per scene: ``front`` / ``front_depth_l2``, each member with its median
time ratio, mean error on both metrics and ``on_front_share`` (share of configurations
whose own front holds it; ``on_front_in_every_configuration`` needs
:data:`MIN_EVERY` configurations); ``claims``: each pair of neighbours on either front,
"the slower below the faster" on both metrics (:func:`experiments._two_metric.claim`:
receiver RMSE and depth-L2 ratios, paired, intervals whose unit is the configuration,
8 x 8 texel tiles within one), with ``n_configs``, ``indicative``, ``order`` and
``metric_dependent``.
"""

from __future__ import annotations

import statistics

import numpy as np
from tqdm import tqdm

from avsm_dr import build, configurations, describe, kinds
from avsm_dr.metrics import error_stats
from ._common import measure
from ._headline import wrap
from ._study import Study, write_data
from ._two_metric import MIN_CONFIDENT, claim
from .error_curves import SCENES

#: What this study reproduces (a paper's figure or table, or the guide's section).
REPRODUCES = (
    'Salvi et al., "Adaptive Volumetric Shadow Maps", EGSR 2010, figures 5-6 and the claims of '
    'sections 3-5: error of AVSM, FOM, OSM, DSM, moments against node / coefficient count and '
    'bytes per texel on the built-in scenes, the depth-range sweep, and findings.json.'
)

#: The time reference of ``time_ratio`` (a setting of every sweep).
REFERENCE = "avsm-8"
#: Fewer configurations than this: no "in every configuration" statement.
MIN_EVERY = 8
#: Full mode: 4 seeds x both directional lights and 2 seeds x the spot light (error_curves').
FULL_CONFIGS = [[s, li] for s in range(4) for li in ("dir_a", "dir_b", "spot") if li != "spot" or s < 2]

#: Parameters of the full and the quick run (``sweeps``: the settings of every kind but those
#: of ``exclude``, filled in).
FULL = dict(scenes=SCENES, resolution=256, repeats=7, build_repeats=1, configs=FULL_CONFIGS, n_volume=4096,
            n_boot=1000, exclude=["optimal"], sweeps=None)
QUICK = dict(FULL, scenes=SCENES[:2], resolution=64, repeats=3, configs=[[0, "dir_a"], [1, "spot"]],
             n_volume=256, n_boot=200)


def pareto(points):
    """Indices of (time, error) points not dominated by any other."""
    idx = []
    for i, (t, e) in enumerate(points):
        if not any((t2 <= t and e2 <= e) and (t2 < t or e2 < e) for j, (t2, e2) in enumerate(points) if j != i):
            idx.append(i)
    return idx


def _resolve(params: dict, quick: bool) -> dict:
    """Every registered kind's size sweep (``ad.configurations``) but ``exclude``'s; the time
    reference must be in it."""
    P = dict(params, sweeps={k: configurations(k, quick) for k in kinds() if k not in ["exact", *params["exclude"]]})
    kind, n = REFERENCE.split("-")
    if {"nodes": int(n)} not in P["sweeps"].get(kind, []):
        raise ValueError(f"sweeps: the time reference {REFERENCE} is not among the settings")
    return P


def _timed(fn, repeats: int, warm_up: bool) -> tuple[float, float, object]:
    """(median wall seconds of ``repeats`` synced calls, first-call seconds (NaN without
    ``warm_up``), last result); with ``warm_up`` a first, uncounted call compiles the kernels."""
    if warm_up:
        r = measure({"f": fn}, repeats)["f"]
        return r["wall_s"], r["first_s"], r["out"]
    got = [measure({"f": fn}, 0)["f"] for _ in range(repeats)]
    return statistics.median(g["wall_s"] for g in got), float("nan"), got[-1]["out"]


def _config(name: str, seed: int, light: str, P: dict, first: bool, store: dict) -> list[dict]:
    """Rows of one configuration (every setting); its receiver errors, per-texel depth L2
    and the 8 x 8 tiles of both into ``store`` (keyed by setting label and config)."""
    from avsm_dr.evaluation import Configuration, curve_values, depth_grid, depth_l2
    from ._two_metric import texel_blocks
    from .error_curves.labels import order_dependent
    cfg = Configuration(seed, light)
    scene, cap = cfg.capture(name, P["resolution"])
    texel, depth = cap.lookup(cfg.in_volume_receivers(scene, P["n_volume"]))
    seg = cap.segments
    store.setdefault("tiles", {})[cfg.label] = (texel_blocks(texel, cap.width),
                                                texel_blocks(depth_grid(seg)[0], cap.width))
    ex_rep = build("exact", seg)
    t_ex, first_ex, exact = _timed(lambda: ex_rep.eval(texel, depth), P["repeats"], True)
    exact = np.asarray(exact, dtype=np.float64)
    curve = curve_values(ex_rep, seg)
    head = dict(scene=name, config=cfg.label, seed=seed, light=light, segments=seg.n_segments, receivers=len(texel))
    rows = [dict(head, method="exact", param="", build_s=0.0, lookup_s=t_ex, first_call_s=first_ex, rmse=0.0,
                 max_error=0.0, signed_mean=0.0, leak_share=0.0, depth_l2=0.0, order="-",
                 bytes_per_texel=ex_rep.nbytes_per_texel, bytes=ex_rep.nbytes_sparse_per_texel,
                 bytes_dense=ex_rep.nbytes_per_texel)]
    for kind, settings in P["sweeps"].items():
        size = describe(kind)["size"]
        for p in settings:
            v = p.get(size, "") if size else ""
            # cold: each call recomputes what earlier builds cached on the segments (greedy's
            # removal order is otherwise computed once and reused by every later setting)
            t_b, first_b, rep = _timed(lambda: build(kind, seg.drop_cache(), **p), P["build_repeats"], first)
            t_l, first_l, est = _timed(lambda: rep.eval(texel, depth), P["repeats"], True)
            err = np.asarray(est, np.float64) - exact
            st = error_stats(est, exact)
            per_l2 = depth_l2(rep, seg, exact=curve, per_texel=True)
            label = f"{kind}-{v}" if v != "" else kind
            store.setdefault(label, {})[cfg.label] = (err.astype(np.float32), per_l2.astype(np.float32))
            rows.append(dict(head, method=kind, param=v, build_s=t_b, lookup_s=t_l, first_call_s=first_b + first_l,
                             rmse=st["rmse"], max_error=st["max_error"], signed_mean=st["mean_error"],
                             leak_share=st["leak_fraction"],
                             depth_l2=float(np.sqrt(np.mean(per_l2 ** 2))) if per_l2.size else float("nan"),
                             order="depth" if order_dependent(kind) else "-", bytes_per_texel=rep.nbytes_per_texel,
                             bytes=rep.nbytes_sparse_per_texel, bytes_dense=rep.nbytes_per_texel))
    ref = next(r for r in rows if _label(r) == REFERENCE)
    for r in rows:
        r["time_ratio"] = (r["build_s"] + r["lookup_s"]) / (ref["build_s"] + ref["lookup_s"])
    return rows


def _label(r: dict) -> str:
    """``kind-size`` of a row (the kind alone when it has no size)."""
    return f"{r['method']}-{r['param']}" if r["param"] != "" else r["method"]


#: The two fronts: (error column, row flag, findings key).
FRONTS = (("rmse", "pareto", "front"), ("depth_l2", "pareto_depth_l2", "front_depth_l2"))


def _scene_findings(rows: list[dict], store: dict, n_boot: int) -> dict:
    """One scene's fronts (flags set on ``rows``) and the claims between front neighbours."""
    rs = [r for r in rows if r["method"] != "exact"]
    configs = list(dict.fromkeys(r["config"] for r in rs))
    labels = list(dict.fromkeys(_label(r) for r in rs))
    by = {(_label(r), r["config"]): r for r in rs}
    time = {lab: float(np.median([by[lab, c]["time_ratio"] for c in configs])) for lab in labels}
    err = {m: {lab: float(np.mean([by[lab, c][m] for c in configs])) for lab in labels} for m, _, _ in FRONTS}
    out: dict = dict(n_configs=len(configs), configs=configs, indicative=len(configs) < MIN_CONFIDENT, claims={})
    for metric, flag, key in FRONTS:
        front = [labels[i] for i in pareto([(time[lab], err[metric][lab]) for lab in labels])]
        on = {lab: 0 for lab in labels}
        for c in configs:
            own = pareto([(by[lab, c]["time_ratio"], by[lab, c][metric]) for lab in labels])
            for i, lab in enumerate(labels):
                by[lab, c][f"{flag}_in_config"] = i in own
                by[lab, c][flag] = lab in front
                on[lab] += i in own
        front.sort(key=lambda lab: time[lab])
        out[key] = [dict(setting=lab, time_ratio=time[lab], rmse=err["rmse"][lab], depth_l2=err["depth_l2"][lab],
                         on_front_share=on[lab] / len(configs),
                         on_front_in_every_configuration=on[lab] == len(configs) if len(configs) >= MIN_EVERY
                         else None) for lab in front]
        for fast, slow in zip(front, front[1:]):
            name = f"{slow}_below_{fast}"
            if name in out["claims"]:
                out["claims"][name]["fronts"].append(metric)
                continue
            used = [c for c in configs if all(np.any(store[lab][c][0] != 0) and np.any(store[lab][c][1] > 0)
                                              for lab in (slow, fast))]
            if not used:
                continue
            tiles = store["tiles"]
            r = claim(tuple([store[lab][c][0] for c in used] for lab in (slow, fast)),
                      tuple([store[lab][c][1] for c in used] for lab in (slow, fast)), used,
                      ([tiles[c][0] for c in used], [tiles[c][1] for c in used]), n_boot)
            orders = [by[lab, used[0]]["order"] for lab in (slow, fast)]
            out["claims"][name] = dict(statement=f"{slow} below {fast} (neighbours on the time-error front, "
                                                 f"{time[slow] / time[fast]:.3g} x the time)",
                                       order=next((o for o in orders if o != "-"), "-"), fronts=[metric],
                                       time_over=time[slow] / time[fast], **r)
    return out


def _compute(res, params: dict) -> dict:
    """Build and lookup time and error of every setting, per scene and configuration, the
    Pareto fronts and the claims between their neighbours."""
    names = params["scenes"]
    rows, found = [], {}
    jobs = [(name, seed, light) for name in names for seed, light in params["configs"]]
    store: dict = {}
    for name, seed, light in tqdm(jobs, desc="runtime_vs_error", unit="config"):
        first = [seed, light] == list(params["configs"][0])
        if first:
            store = {}
        rows += _config(name, seed, light, params, first, store)
        if [seed, light] == list(params["configs"][-1]):
            found[name] = _scene_findings([r for r in rows if r["scene"] == name], store, params["n_boot"])
    write_data(res, dict(rows=rows, findings=found))          # before the figures
    _plot(res, rows, found, names)
    summary = {name: [d["setting"] for d in f["front"]] for name, f in found.items()}
    front_l2 = {name: [d["setting"] for d in f["front_depth_l2"]] for name, f in found.items()}
    n = len(params["configs"])
    return dict(rows=rows, findings=found,
                summary={"pareto_front": summary, "pareto_front_depth_l2": front_l2, "n_configs": n,
                         "indicative": n < MIN_CONFIDENT},
                result={"summary": summary})


def _plot(res, rows: list[dict], found: dict, names):
    """Per scene: mean RMSE over configurations against the median time ratio, each kind's
    settings joined, the front dotted."""
    import matplotlib
    matplotlib.use("Agg")
    from . import _plotstyle as plotstyle
    cols = min(len(names), 5)
    with plotstyle.context():
        fig, axes = plotstyle.grid(-(-len(names) // cols), cols, panel=(3.2, 2.6), sharex=False, sharey=False)
        for ax in list(axes.flat)[len(names):]:
            ax.set_visible(False)
        for ax, name in zip(axes.flat, names):
            f = found[name]
            pts = {}
            for r in rows:
                if r["scene"] == name and r["method"] != "exact":
                    pts.setdefault(r["method"], {}).setdefault(r["param"], []).append(r)
            for kind, per in pts.items():
                x = [float(np.median([r["time_ratio"] for r in rs])) for rs in per.values()]
                y = [max(float(np.mean([r["rmse"] for r in rs])), 1e-6) for rs in per.values()]
                st = plotstyle.style(kind)
                ax.loglog(x, y, marker=st.get("marker", "o"), color=st["color"], ms=3, lw=1, label=kind)
            fr = f["front"]
            ax.loglog([d["time_ratio"] for d in fr], [max(d["rmse"], 1e-6) for d in fr], "k:", lw=1,
                      label="Pareto front")
            ax.set_title(name)
            ax.set_xlabel(f"time / {REFERENCE}'s")
        for row in axes:
            row[0].set_ylabel("RMSE vs exact")
        fig.suptitle(f"median over {found[names[0]]['n_configs']} configurations of the time ratio; "
                     "mean RMSE", fontsize=9)
        plotstyle.legend_below(fig, axes, ncol=6)
        res.save_figure(fig, "runtime_vs_error.png")


def _headline(s: dict) -> list[str]:
    """Per scene: the settings on the time-error Pareto front."""
    n = s.get("n_configs")
    tail = f" ({n} configurations)" if n else ""
    return [line for scene, front in s.get("pareto_front", {}).items()
            for line in wrap(f"{scene}, on the time-error Pareto front{tail}: ", [str(x) for x in front])]


STUDY = Study("runtime_vs_error", "Build and lookup time against error for every representation and setting",
              REPRODUCES, FULL, QUICK, _compute, resolve=_resolve, writes=("data.csv", "findings.json"),
              headline=_headline)
run = STUDY.run

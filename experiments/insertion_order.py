"""The order study: AVSM (with each of its ``insertion`` variants) and ``avsm_march`` under
the four insertion orders of :func:`avsm_dr.capture` (``submission``, ``depth``,
``reverse_depth``, ``random``), against the offline references ``greedy`` and ``optimal``
(best breakpoint subset, refitted), per scene, configuration and node count N.

Methods: ``avsm`` (``insertion='stream'``, the paper's) and ``avsm_<insertion>`` for the other
insertions of :data:`INSERTION_METHODS` (:mod:`avsm_dr.representations._avsm_insertion`);
their ``build_ratio`` is the build's wall time over stream ``avsm``'s on the same segments
in the same process (least of :data:`TIMING_REPEATS` interleaved builds, the kernels
compiled before), ``kernel_ratio`` the same for the JIT kernels' execution time alone
(Dr.Jit's kernel history: without the Python tracing of the loop bodies, a per-build
constant that dominates small maps).  ``findings.json``'s ``goal`` says per scene and N
whether a method stays within :data:`GOAL_RATIO` of optimal's depth L2 under every order and
its build ratio (geometric mean over the configurations and orders) within
:data:`GOAL_BUILD`.

One capture per configuration (``order='submission'``); the three other orders are
:meth:`avsm_dr.segments.Segments.in_order` of its segments (``random``
seeded with the configuration's seed), so every order sees the same segments and the same
receivers.  ``greedy`` and ``optimal`` do not depend on the order: they are built once per
configuration (on the ``depth`` order) and repeated in every order's rows.

Metrics of each representation (in-volume receivers of :func:`avsm_dr.receivers.in_volume`,
bilinear lookups through :class:`avsm_dr.evaluation.Probe`):

* ``rmse``: receiver RMSE against the exact curve of the same segments; ``rmse_truth``:
  against the ray-marched ground truth (:func:`avsm_dr.evaluation.truth`);
* ``depth_l2``: :func:`avsm_dr.evaluation.depth_l2`, the depth-uniform L2 per texel, RMS
  over the non-empty texels (the cost ``optimal`` minimises per texel over node subsets);
* ``signed_mean`` (``signed_mean_truth``): mean of ``T_rep - T_exact`` (``- T_true``) at
  the receivers; > 0 is light leaking through; ``leak_share`` (``leak_share_truth``): the
  share of receivers where that error exceeds 0.02 (:data:`avsm_dr.metrics.THRESHOLD`);
* ``bytes``: ``nbytes_sparse_per_texel`` (occupancy bit per texel, each non-empty texel's
  payload and offset), ``bytes_dense``: ``nbytes_per_texel``;
* ``ratio_to_optimal`` (``ratio_to_optimal_rmse``), ``ratio_to_greedy``: ``depth_l2``
  (receiver ``rmse``) over the reference's in the same configuration;
  ``beats_optimal_texels``: share of non-empty texels whose depth L2 is below optimal's by
  more than :data:`BEATS_MARGIN` (AVSM's nodes may leave the exact curve, optimal's may
  not, so AVSM can beat it on single texels);
* ``ratio_to_free``: depth L2 (RMS over ``free_texels`` texels sampled per configuration
  and N, seeded) over the free-vertex optimum's on the same texels (:mod:`._free_vertex`:
  N nodes free in depth and value, refined from optimal's; a local optimum, float64), so
  optimal's own row gives the best subset's gap to the free-vertex optimum (for N in
  ``free_nodes`` only: about 0.5 s per texel; NaN otherwise).

``findings.json``: per scene and N, for every kind and order the geometric mean over
configurations of both ratios to optimal with a 95 % bootstrap interval whose unit is the
configuration (seed x light; :func:`avsm_dr.stats.bootstrap_ci` of the log ratios), the
ranking of the kinds by ``depth_l2`` ratio per order and whether the order changes it;
``indicative`` when fewer than :data:`MIN_CONFIGS` configurations back an interval; each
kind's mean ``leak_share`` per order; ``order_over_depth``: per streaming kind, each other
order's receiver RMSE and depth L2 over front to back's (same configuration, segments and
receivers), with intervals over configurations; ``metric_dependent`` wherever the two
metrics' intervals lie entirely on opposite sides of 1 (``error_curves``' rule).  Every
interval's unit is the configuration; no within-map interval is shown.

Flicker (the change of T between frames) is not measured here: it needs the temporal
study's animation (``experiments/temporal``); ``experiments/ordering.py`` measures the change
between shuffled orders of one frame.

``avsm_march`` builds from the exact curve's points in depth order (:mod:`avsm_dr.representations.avsm_march`),
so its rows are the same in every order: a check of the study, not a finding.
"""
from __future__ import annotations

import numpy as np
from tqdm import tqdm

from avsm_dr import build
from ._free_vertex import free_vertex_l2
from ._headline import num, wrap
from ._study import Option, Study, write_data
from ._two_metric import metric_dependent

#: What this study reproduces (a paper's figure or table, or the guide's section).
REPRODUCES = (
    'Salvi et al., "Adaptive Volumetric Shadow Maps", EGSR 2010, section 4.1 (insertion order), '
    "extended: AVSM and avsm_march under submission, depth, reverse-depth and random insertion, "
    "against offline greedy and the best breakpoint subset, on both error metrics."
)

#: Insertion orders compared (the capture's own order first).
ORDERS = ("submission", "depth", "reverse_depth", "random")
#: AVSM's insertion variants compared: method name -> the ``insertion`` parameter.
INSERTION_METHODS = {"avsm": "stream", "avsm_refit": "refit", "avsm_refit_l2": "refit_l2",
                     "avsm_staged": "staged", "avsm_staged_refit_l2": "staged_refit_l2",
                     "avsm_spare_refit_l2": "spare_refit_l2", "avsm_spare_exp": "spare_exp",
                     "avsm_spare_exp_fit": "spare_exp_fit"}
#: Streaming (order-dependent) methods and the offline references (order-independent).
STREAMING = tuple(INSERTION_METHODS) + ("avsm_march",)
REFERENCES = ("greedy", "optimal")
#: The goal: depth L2 within this factor of optimal's under every order ...
GOAL_RATIO = 1.5
#: ... at most this factor of stream AVSM's build time.
GOAL_BUILD = 1.3
#: A texel's depth L2 counts as below optimal's only below it by more than this (float32
#: lookups: ~1e-7 noise in a texel's L2).
BEATS_MARGIN = 1e-6
#: Fewer configurations than this make a claim ``indicative``.
MIN_CONFIGS = 4

#: Scenes per row of the figure's small multiples.
PANELS_PER_ROW = 5

#: Parameters of the full and the quick run (``scenes=None``: every built-in scene; full mode:
#: error_curves' ten configurations, 4 seeds x both directional lights and 2 seeds x the spot light).
FULL = dict(scenes=None, resolution=128, nodes=[4, 8, 16],
            configs=[[s, li] for s in range(4) for li in ("dir_a", "dir_b", "spot") if li != "spot" or s < 2],
            n_volume=2048, n_depths=64, n_boot=2000, timing_repeats=7, free_texels=16, free_nodes=[8], insertions=None)
QUICK = dict(FULL, scenes=["three_columns", "plume"], resolution=64, nodes=[8], configs=[[0, "dir_a"], [1, "dir_b"]],
             n_volume=256, n_boot=500, free_texels=12)
#: Default interleaved builds per AVSM insertion method, order and N (the least time counts).
TIMING_REPEATS = 7


def _method(name: str) -> tuple[str, dict]:
    """(kind, build parameters) of a method name."""
    if name in INSERTION_METHODS:
        return "avsm", {"insertion": INSERTION_METHODS[name]}
    return name, {}


def _timed_avsm_builds(seg, n: int, repeats: int = TIMING_REPEATS, methods=tuple(INSERTION_METHODS)) -> dict:
    """{method: (rep, wall seconds, kernel seconds)} of the AVSM insertion ``methods`` on ``seg``:
    ``repeats`` rounds of interleaved builds (each method compiled first), the least wall
    time and the least total execution time of its JIT kernels (Dr.Jit's kernel history,
    switched on for the measurement and restored)."""
    import time
    import drjit as dr
    flag = dr.JitFlag.KernelHistory
    was = dr.flag(flag)
    dr.set_flag(flag, True)
    try:
        reps = {m: build("avsm", seg, nodes=n, **_method(m)[1]) for m in methods}   # compile
        wall = {m: [] for m in methods}
        kern = {m: [] for m in methods}
        for _ in range(repeats):
            for m in methods:
                dr.sync_thread()
                dr.kernel_history()                          # clears it
                t0 = time.perf_counter()
                reps[m] = build("avsm", seg, nodes=n, **_method(m)[1])
                dr.sync_thread()
                wall[m].append(time.perf_counter() - t0)
                kern[m].append(sum(float(k.get("execution_time", 0.0)) for k in dr.kernel_history()
                                   if k.get("type") == dr.KernelType.JIT) * 1e-3)
    finally:
        dr.kernel_history()
        dr.set_flag(flag, was)
    return {m: (reps[m], min(wall[m]), min(kern[m])) for m in methods}


def _stats(est, ref) -> tuple[float, float, float]:
    """(RMSE, signed mean, leak share) of ``est - ref`` (:func:`avsm_dr.metrics.error_stats`;
    leak: > :data:`avsm_dr.metrics.THRESHOLD`)."""
    from avsm_dr.metrics import error_stats
    s = error_stats(est, ref)
    return s["rmse"], s["mean_error"], s["leak_fraction"]


def _config_rows(name: str, seed: int, light: str, P: dict) -> list[dict]:
    """Rows of one configuration: every kind x N x order."""
    from avsm_dr.evaluation import Configuration, Probe, curve_values, depth_l2
    cfg = Configuration(seed, light)
    scene, cap = cfg.capture(name, P["resolution"], order="submission")
    seg = cap.segments
    segs = {o: seg if o == "submission" else seg.in_order(o, seed=seed if o == "random" else None) for o in ORDERS}
    points = cfg.in_volume_receivers(scene, P["n_volume"])
    probe = Probe(cap, scene, points, n_decomp=0)
    base = segs["depth"]
    exact = build("exact", base)
    ex_lookup = probe.lookup(exact)
    n_depths = P["n_depths"]
    ex_curve = curve_values(exact, base, n_depths)
    head = dict(scene=name, config=cfg.label, seed=seed, light=light, resolution=P["resolution"],
                receivers=int(points.shape[0]), max_segments=int(seg.max_count))

    def measure(rep, s):
        est = probe.lookup(rep)
        rmse, mean, leak = _stats(est, ex_lookup)
        rmse_t, mean_t, leak_t = _stats(est, probe.truth)
        per = depth_l2(rep, s, exact=ex_curve, n_depths=n_depths, per_texel=True)
        return dict(rmse=rmse, signed_mean=mean, leak_share=leak, rmse_truth=rmse_t, signed_mean_truth=mean_t,
                    leak_share_truth=leak_t, depth_l2=float(np.sqrt(np.mean(per ** 2))) if per.size else float("nan"),
                    bytes=rep.nbytes_sparse_per_texel, bytes_dense=rep.nbytes_per_texel), per

    rows = []
    nan = float("nan")
    for n in P["nodes"]:
        ref_reps = {k: build(k, base, nodes=n) for k in REFERENCES}
        ref = {k: measure(rep, base) for k, rep in ref_reps.items()}
        # the free-vertex optimum on a sample of the texels counted (module docstring)
        rng = np.random.default_rng([seed, n])
        n_rows = ref["optimal"][1].size
        sample = np.sort(rng.choice(n_rows, min(P["free_texels"], n_rows), replace=False))
        if n not in P["free_nodes"]:
            sample = sample[:0]
        free = free_vertex_l2(base, ex_curve, ref_reps["optimal"], sample, n_depths)
        free_rms = float(np.sqrt(np.mean(free ** 2))) if free.size else nan
        for order in ORDERS:
            got = dict(ref)
            timed = _timed_avsm_builds(segs[order], n, P["timing_repeats"], P["insertions"])
            _, wall0, kern0 = timed["avsm"]
            streaming = tuple(P["insertions"]) + ("avsm_march",)
            for k in streaming:
                rep = timed[k][0] if k in timed else build(k, segs[order], nodes=n)
                got[k] = measure(rep, segs[order])
            opt, opt_tex = got["optimal"]
            gr = got["greedy"][0]
            for k in streaming + REFERENCES:
                m, per = got[k]
                wall, kern = timed[k][1:] if k in timed else (nan, nan)
                kern_ratio = kern / kern0 if kern0 > 0 else nan
                rows.append(dict(head, kind=k, nodes=n, order=order, insertion=INSERTION_METHODS.get(k, ""),
                                 **m, build_s=wall, build_ratio=wall / wall0, kernel_ratio=kern_ratio,
                                 ratio_to_optimal=m["depth_l2"] / opt["depth_l2"],
                                 ratio_to_optimal_rmse=m["rmse"] / opt["rmse"],
                                 ratio_to_greedy=m["depth_l2"] / gr["depth_l2"],
                                 ratio_to_free=float(np.sqrt(np.mean(per[sample] ** 2))) / free_rms
                                 if free_rms > 0 else nan, free_texels=int(sample.size),
                                 beats_optimal_texels=float(np.mean(per < opt_tex - BEATS_MARGIN))))
    return rows


def _interval(ratios, n_boot: int) -> dict:
    """Geometric mean of per-configuration ratios with a bootstrap interval over the
    configurations (a point estimate alone when there is one)."""
    from avsm_dr import stats
    r = np.asarray(ratios, np.float64)
    est = float(np.exp(np.mean(np.log(r))))
    out = dict(estimate=est, n_configs=int(r.size), indicative=bool(r.size < MIN_CONFIGS))
    if r.size >= 2:
        ci = stats.bootstrap_ci(np.log(r), "mean", n_boot=n_boot)
        out.update(low=float(np.exp(ci["low"])), high=float(np.exp(ci["high"])), level=ci["level"])
    return out


def findings(rows: list[dict], n_boot: int = 2000) -> dict:
    """Per scene and N: every kind's ratios to optimal per order (``depth_l2`` and receiver
    ``rmse``) with intervals over configurations, the ranking per order and whether the
    order changes it."""
    out: dict = {}
    for scene in dict.fromkeys(r["scene"] for r in rows):
        for n in sorted({r["nodes"] for r in rows if r["scene"] == scene}):
            d: dict = {}
            rank = {}
            for order in ORDERS:
                sel = [r for r in rows if r["scene"] == scene and r["nodes"] == n and r["order"] == order]
                per = {}
                for k in (k for k in STREAMING + ("greedy",) if any(r["kind"] == k for r in sel)):
                    rk = sorted((r for r in sel if r["kind"] == k), key=lambda r: r["config"])
                    per[k] = dict(depth_l2=_interval([r["ratio_to_optimal"] for r in rk], n_boot),
                                  rmse=_interval([r["ratio_to_optimal_rmse"] for r in rk], n_boot),
                                  signed_mean=float(np.mean([r["signed_mean"] for r in rk])),
                                  leak_share=float(np.mean([r["leak_share"] for r in rk])),
                                  beats_optimal_texels=float(np.mean([r["beats_optimal_texels"] for r in rk])),
                                  free_vertex=_free_interval(rk, n_boot))
                for k, e in per.items():
                    e["metric_dependent"] = metric_dependent(e["rmse"], e["depth_l2"])
                d[order] = per
                rank[order] = sorted(per, key=lambda k: per[k]["depth_l2"]["estimate"])
            d["order_over_depth"] = _order_over_depth([r for r in rows if r["scene"] == scene and r["nodes"] == n],
                                                      n_boot)
            d["optimal_over_free_vertex"] = _free_interval(
                sorted((r for r in rows if r["scene"] == scene and r["nodes"] == n and r["order"] == "depth"
                        and r["kind"] == "optimal"), key=lambda r: r["config"]), n_boot)
            d["ranking_depth_l2"] = rank
            d["order_changes_ranking"] = len({tuple(v) for v in rank.values()}) > 1
            avsm = [d[o]["avsm"]["depth_l2"]["estimate"] for o in ORDERS]
            d["avsm_worst_over_best_order"] = max(avsm) / min(avsm)
            d["best_avsm_order"] = ORDERS[int(np.argmin(avsm))]
            d["goal"] = _goal(d, [r for r in rows if r["scene"] == scene and r["nodes"] == n])
            out.setdefault(scene, {})[f"N={n}"] = d
    return out


def _order_over_depth(rows: list[dict], n_boot: int) -> dict:
    """Per streaming kind and order other than 'depth': its receiver RMSE and depth L2 over
    the same kind's front to back in the same configuration (same segments and receivers),
    geometric means over configurations with intervals (:func:`_interval`), and
    ``metric_dependent``."""
    out: dict = {}
    for k in (k for k in STREAMING if any(r["kind"] == k for r in rows)):
        base = {r["config"]: r for r in rows if r["kind"] == k and r["order"] == "depth"}
        for o in ORDERS:
            if o == "depth":
                continue
            rk = sorted((r for r in rows if r["kind"] == k and r["order"] == o and r["config"] in base),
                        key=lambda r: r["config"])
            if not rk or any(base[r["config"]][m] <= 0 for r in rk for m in ("rmse", "depth_l2")):
                continue
            e = {m: _interval([r[m] / base[r["config"]][m] for r in rk], n_boot) for m in ("rmse", "depth_l2")}
            e["metric_dependent"] = metric_dependent(e["rmse"], e["depth_l2"])
            out.setdefault(k, {})[o] = e
    return out


def _free_interval(rows, n_boot: int) -> dict | None:
    """The depth-L2 ratio to the free-vertex optimum on the sampled texels, over configurations."""
    r = [x["ratio_to_free"] for x in rows if np.isfinite(x.get("ratio_to_free", np.nan))]
    return _interval(r, n_boot) if r else None


def _goal(d: dict, rows: list[dict]) -> dict:
    """Per AVSM insertion method: its worst depth-L2 ratio to optimal over the orders, the
    geometric means over configurations and orders of its build and kernel time ratios to
    stream AVSM, and whether it meets :data:`GOAL_RATIO` / :data:`GOAL_BUILD`."""
    out = {}
    for k in (k for k in INSERTION_METHODS if k in d[ORDERS[0]]):
        worst = max(d[o][k]["depth_l2"]["estimate"] for o in ORDERS)
        rk = [r for r in rows if r["kind"] == k]
        build_ratio = float(np.exp(np.mean(np.log([r["build_ratio"] for r in rk]))))
        kern = [r["kernel_ratio"] for r in rk if np.isfinite(r["kernel_ratio"])]
        kernel_ratio = float(np.exp(np.mean(np.log(kern)))) if kern else float("nan")
        out[k] = dict(worst_order=ORDERS[int(np.argmax([d[o][k]["depth_l2"]["estimate"] for o in ORDERS]))],
                      worst_ratio=worst, build_ratio=build_ratio, kernel_ratio=kernel_ratio,
                      within_ratio=bool(worst <= GOAL_RATIO), within_build=bool(build_ratio <= GOAL_BUILD),
                      met=bool(worst <= GOAL_RATIO and build_ratio <= GOAL_BUILD))
    return out


def _resolve(P: dict, quick: bool) -> dict:
    """Every built-in scene when ``scenes`` is None, every AVSM insertion method when
    ``insertions`` is None (stream ``avsm`` always: the timing reference); checks of the names."""
    from avsm_dr.builtin_scenes import SCENES
    P["scenes"] = list(SCENES) if P["scenes"] is None else list(P["scenes"])
    for s in P["scenes"]:
        if s not in SCENES:
            raise ValueError(f"scenes: unknown scene {s!r}; known: {sorted(SCENES)}")
    chosen = set(INSERTION_METHODS if P.get("insertions") is None else P["insertions"]) | {"avsm"}
    if chosen - set(INSERTION_METHODS):
        raise ValueError(f"insertions: unknown methods {sorted(chosen - set(INSERTION_METHODS))}; "
                         f"known: {list(INSERTION_METHODS)}")
    P["insertions"] = [m for m in INSERTION_METHODS if m in chosen]
    return P


def _compute(res, P: dict) -> dict:
    """Every configuration's rows, the findings and the figure."""
    rows: list[dict] = []
    jobs = [(name, seed, light) for name in P["scenes"] for seed, light in P["configs"]]
    for name, seed, light in tqdm(jobs, desc="insertion_order", unit="config"):
        rows += _config_rows(name, seed, light, P)
    found = findings(rows, P["n_boot"])
    write_data(res, dict(rows=rows, findings=found))          # before the figures
    _plot(res, found, P["scenes"], P["nodes"])
    summary = {f"{s}_N{n}_avsm_over_optimal_{o}": found[s][f"N={n}"][o]["avsm"]["depth_l2"]["estimate"]
               for s in P["scenes"] for n in P["nodes"] for o in ORDERS}
    summary.update({f"{s}_N{n}_{k}_worst_order_over_optimal": found[s][f"N={n}"]["goal"][k]["worst_ratio"]
                    for s in P["scenes"] for n in P["nodes"] for k in P["insertions"]})
    summary.update({f"{s}_N{n}_optimal_over_free_vertex": (found[s][f"N={n}"]["optimal_over_free_vertex"]
                                                            or {}).get("estimate")
                    for s in P["scenes"] for n in P["nodes"]})
    return dict(rows=rows, findings=found, summary=summary)


#: Figure style per method: AVSM's insertion variants get colours of their own (they are not
#: registered kinds), avsm_march and greedy keep their kinds' fixed style.
METHOD_COLOURS = {"avsm": "rose", "avsm_refit": "sand", "avsm_refit_l2": "olive", "avsm_staged": "wine",
                  "avsm_staged_refit_l2": "indigo", "avsm_spare_refit_l2": "purple", "avsm_spare_exp": "green",
                  "avsm_spare_exp_fit": "orange"}
#: The node count the figure shows (the tables in findings.json have every N).
PLOT_NODES = 8


def _method_style(k: str) -> dict:
    from . import _plotstyle as plotstyle
    if k in METHOD_COLOURS:
        markers = ("o", "s", "D", "v", "P", "X", "*", "h")
        return dict(color=plotstyle.PALETTE[METHOD_COLOURS[k]], linestyle="-",
                    marker=markers[list(METHOD_COLOURS).index(k)])
    return plotstyle.style(k)


def _plot(res, found: dict, names, nodes):
    """Small multiples: a panel per scene and metric (two rows of panels per :data:`PANELS_PER_ROW`
    scenes); each method's ratio to optimal against the order at :data:`PLOT_NODES` nodes (or
    the first N run), one fixed colour and marker per method."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.ticker
    from . import _plotstyle as plotstyle
    x = np.arange(len(ORDERS))
    n = PLOT_NODES if PLOT_NODES in nodes else nodes[0]
    with plotstyle.context():
        cols = min(len(names), PANELS_PER_ROW)
        blocks = -(-len(names) // cols)
        fig, axes = plotstyle.grid(2 * blocks, cols, panel=(2.9, 2.3), sharex=False, sharey=False)
        for j in range(len(names) - (blocks - 1) * cols, cols):          # unused panels of the last block
            axes[-2][j].set_visible(False)
            axes[-1][j].set_visible(False)
        for p, name in enumerate(names):
            b, j = divmod(p, cols)
            cell = found[name][f"N={n}"]
            methods = [k for k in STREAMING + ("greedy",) if k in cell[ORDERS[0]]]
            for i, (metric, label) in enumerate((("depth_l2", "depth-uniform L2 / optimal"),
                                                 ("rmse", "receiver RMSE / optimal"))):
                ax = axes[2 * b + i][j]
                for kk, k in enumerate(methods):
                    v = [cell[o][k][metric] for o in ORDERS]
                    y = np.array([e["estimate"] for e in v])
                    lo = np.array([e.get("low", e["estimate"]) for e in v])
                    hi = np.array([e.get("high", e["estimate"]) for e in v])
                    st = _method_style(k)
                    ax.errorbar(x + 0.04 * (kk - len(methods) / 2), y, yerr=[y - lo, hi - y], color=st["color"],
                                marker=st["marker"], linestyle=st.get("linestyle", "-"), markersize=4,
                                capsize=2, label=k)
                ax.axhline(1.0, color="k", linewidth=0.8, linestyle=":")
                ax.axhline(GOAL_RATIO, color="0.5", linewidth=0.8, linestyle="--")
                ax.set_yscale("log")
                ax.yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
                ax.yaxis.set_minor_locator(matplotlib.ticker.LogLocator(subs=(2.0, 3.0, 5.0)))
                ax.yaxis.set_minor_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
                ax.set_xticks(x, [o.replace("_", "\n") for o in ORDERS])
                if j == 0:
                    ax.set_ylabel(label)
                if i == 0:
                    ax.set_title(name)
        fig.suptitle(f"N = {n}: ratio to optimal, geometric mean over configurations with its 95 % interval "
                     f"(dotted: 1, dashed: the goal {GOAL_RATIO:g})", fontsize=9)
        handles, labels = axes[0][0].get_legend_handles_labels()
        plotstyle.legend_below(fig, axes[-1], ncol=min(len(labels), 4), handles=handles, labels=labels)
        res.save_figure(fig, "insertion_order.png")


def _headline(s: dict) -> list[str]:
    """Per scene and N: AVSM's depth-uniform L2 over the optimum per insertion order, each
    method's worst order over the optimum, and the optimum over the free-vertex fit."""
    import re
    groups: dict = {}
    for key, v in s.items():
        m = re.match(r"(.+)_N(\d+)_(.+)$", key)
        if m:
            groups.setdefault(f"{m[1]} N={m[2]}", {})[m[3]] = v
    out = []
    for head, d in groups.items():
        orders = [f"{k[len('avsm_over_optimal_'):]} {num(v)}" for k, v in d.items()
                  if k.startswith("avsm_over_optimal_")]
        worst = [f"{k[:-len('_worst_order_over_optimal')]} {num(v)}" for k, v in d.items()
                 if k.endswith("_worst_order_over_optimal")]
        out += wrap(f"{head}: AVSM over the optimum by order: ", orders)
        out += wrap(f"{head}: worst order over the optimum: ", worst)
        if "optimal_over_free_vertex" in d:
            out.append(f"{head}: optimum over the free-vertex fit: {num(d['optimal_over_free_vertex'])}")
    return out


STUDY = Study(
    "insertion_order", "AVSM and avsm_march under four insertion orders, against greedy and the optimum",
    REPRODUCES, FULL, QUICK, _compute, resolve=_resolve, writes=("data.csv", "findings.json"),
    options=(Option("scenes", "built-in scenes to run (default: the mode's)", nargs="+", metavar="SCENE"),
             Option("insertions", f"AVSM insertion methods to run, of {' '.join(INSERTION_METHODS)} "
                    "(default: all; stream 'avsm' always)", nargs="+", metavar="METHOD")),
    headline=_headline)
run = STUDY.run

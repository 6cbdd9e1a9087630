"""Moments tuned for participating media: the overestimation beta, the bias alpha and the
bias target of the ``moments`` kind, chosen on held-out seeds, with a sensitivity table.

The kind's defaults are MBOIT's, tuned for transparency (beta = 0.25, MBOIT's float32 bias
alphas and targets; :mod:`avsm_dr.representations.moments`).  This study measures them on
participating media and picks the setting that minimises the error.

**Held-out seeds.**  Every scene is generated with the seeds of ``configs`` (full run:
error_curves' layout of 10 configurations on other seeds: seeds 100-103 with the lights
``dir_a`` and ``dir_b``, the first two also with ``spot``); the seeds of
``error_curves`` (0-3), the study that evaluates the kinds, are never used here
(``_resolve`` refuses an overlap), so a setting chosen here and made the kind's preset is
evaluated there on seeds it was not tuned on.  ``findings.json`` records both seed sets.

**Grid.**  Per moment count and family (power 4, 6, 8; trigonometric 2, 3, 4), always at
the preset's ``depth_range='texel'`` and on the preset's capture (``opaque='separate'``):
beta in ``betas``; alpha = the kind's default alpha for the count (float32) times each of
``alpha_factors`` (at most 1); bias target ``default`` (MBOIT's vector for power moments, the
uniform distribution on the circle for trigonometric ones) and, for power moments,
``uniform`` (the uniform distribution on [-1, 1], :data:`~avsm_dr.representations.moments.UNIFORM_TARGET`).
MBOIT's default (target ``default``, factor 1, beta 0.25) is a grid point.

**Metrics** per scene, configuration (seed x light) and setting (``data.csv``):
``depth_l2`` (:func:`avsm_dr.evaluation.depth_l2`: the depth-uniform L2 of each non-empty
texel's curve against the exact curve, RMS over the texels), ``rmse`` (receiver RMSE at the
in-volume receivers of :func:`avsm_dr.receivers.in_volume` against the exact curve of the
same segments, bilinear lookups through :class:`avsm_dr.evaluation.Probe`) and
``signed_mean`` (mean of ``T_moments - T_exact`` at the receivers; > 0: light leaks
through) and ``leak_share`` (receivers with that error above 0.02,
:data:`avsm_dr.metrics.THRESHOLD`); each row also records the capture's insertion ``order``
('depth'; moments do not depend on it), ``bytes`` (the sparse layout,
``nbytes_sparse_per_texel``) and ``bytes_dense`` (= ``bytes_per_texel``).

**Choice.**  Within each cell (scene, configuration, family, moment count) every setting's
metric is divided by the least of the grid in that cell (``ratio_depth_l2``,
``ratio_rmse``); ``sensitivity.csv`` holds, per family, count and grid point, the geometric
mean of those ratios over scenes and configurations.  The chosen setting of a family and
count is the grid point with the least geometric-mean depth-L2 ratio; ``rmse_choice`` is
receiver RMSE's, and ``metric_dependent`` is true when the two differ and the depth-L2
choice costs more than :data:`METRIC_TOLERANCE` in receiver RMSE over RMSE's own choice.
``preset`` is the one beta for every family and count at the default alpha and target (the
preset holds no per-count value): the least geometric mean of the depth-L2 ratios over all
of them.

**Improvement** (``tuned_over_default``, ``preset_over_default``): per cell the metric at
the chosen setting over MBOIT's default, geometric mean over the cells with a 95 %
bootstrap interval whose unit is the configuration (scene x seed x light;
:func:`avsm_dr.stats.bootstrap_ci` of the log ratios), for both metrics; per scene the
same.  The choice and the ratio use the same held-out seeds (in-sample), so
``cross_validated`` repeats it leaving one seed out: the setting chosen on the other seeds,
measured on the seed left out.  ``preset_beats_defaults``: the preset's interval is below 1
for every family and count under both metrics.
"""
from __future__ import annotations

import itertools
import time

import numpy as np
from tqdm import tqdm

from avsm_dr import build, describe
from avsm_dr.metrics import error_stats
from ._study import Option, Study, write_data
from .error_curves import LIGHTS, SPOT_SEEDS

#: What this study reproduces (a paper's figure or table, or the guide's section).
REPRODUCES = (
    "No paper: the moments kind's beta (overestimation), bias alpha and bias target, which MBOIT "
    '(Muenstermann et al. 2018, "Moment-Based Order-Independent Transparency") tuned for transparency, '
    "tuned for participating media on held-out seeds (never those error_curves evaluates), with a "
    "sensitivity table over both metrics and the improvement over MBOIT's values."
)

SCENES = ["plume", "hair_and_smoke", "particles", "smoke_over_table", "cumulus", "fog_bank"]
#: Held-out seeds: never among error_curves' seeds (checked in ``_resolve``).
HELD_OUT_SEEDS = (100, 101, 102, 103)
#: Configurations: error_curves' layout (its LIGHTS, the spot light with the first
#: SPOT_SEEDS seeds) on the held-out seeds: 10 per scene.
#: (family, moment count) tuned, in table order.
GROUPS = (("power", 4), ("power", 6), ("power", 8),
          ("trigonometric", 2), ("trigonometric", 3), ("trigonometric", 4))
BETAS = (0.0, 0.1, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5, 0.6, 0.75, 1.0)
#: Multiples of the kind's default alpha (the float32 value of the moment count).
ALPHA_FACTORS = (0.01, 0.1, 1.0, 10.0, 100.0)
#: Bias targets: the kind's default, and (power moments only) the uniform distribution's.
TARGETS = ("default", "uniform")
#: Receiver RMSE "chooses differently" (``metric_dependent``) when its own choice is better
#: than the depth-L2 choice by more than this share.
METRIC_TOLERANCE = 0.01
#: Below this many configurations an interval is ``indicative``.
MIN_CONFIGS = 4
METRICS = ("depth_l2", "rmse")

#: Parameters of the full and the quick run (quick: two scenes, 64^2, 3 configurations each,
#: 2 power counts and 1 trigonometric, a small grid).
FULL = dict(scenes=SCENES, resolution=128, n_volume=2048,
            configs=[[s, li] for i, s in enumerate(HELD_OUT_SEEDS) for li in LIGHTS if li != "spot" or i < SPOT_SEEDS],
            groups=[list(g) for g in GROUPS], betas=list(BETAS), alpha_factors=list(ALPHA_FACTORS),
            targets=list(TARGETS), n_depths=64, n_boot=2000)
QUICK = dict(FULL, scenes=["smoke_over_table", "plume"], resolution=64, n_volume=256,
             configs=[[100, "dir_a"], [101, "dir_b"], [102, "spot"]],
             groups=[["power", 4], ["power", 8], ["trigonometric", 3]], betas=[0.0, 0.25, 0.4, 0.45, 0.5, 1.0],
             alpha_factors=[0.1, 1.0, 10.0], n_boot=500)


def default_beta() -> float:
    """MBOIT's beta: the schema default of ``overestimation``."""
    return float(describe("moments")["params"]["overestimation"]["default"])


def default_alpha(family: str, n: int, dtype: str = "float32") -> float:
    """The kind's default alpha for ``n`` moments of ``family`` in storage ``dtype``."""
    from avsm_dr.representations.moments import DEFAULT_BIAS, DEFAULT_TRIG_BIAS
    return float((DEFAULT_TRIG_BIAS if family == "trigonometric" else DEFAULT_BIAS)[n][dtype])


def group_label(family: str, n: int) -> str:
    """'power-4', 'trigonometric-3', ..."""
    return f"{family}-{n}"


def grid(P: dict, family: str) -> list[tuple[str, float, float]]:
    """(target, alpha factor, beta) of every setting of ``family``."""
    targets = [t for t in P["targets"] if family == "power" or t == "default"]
    return list(itertools.product(targets, P["alpha_factors"], P["betas"]))


def is_default(target: str, factor: float, beta: float) -> bool:
    """MBOIT's setting: the default target and alpha, beta 0.25."""
    return target == "default" and factor == 1.0 and beta == default_beta()


def build_params(family: str, n: int, target: str, factor: float, beta: float, dtype: str) -> dict:
    """Build parameters of one grid point (at the preset's per-texel depth range)."""
    from avsm_dr.representations.moments import UNIFORM_TARGET
    p = dict(moments=n, family=family, depth_range="texel", overestimation=float(beta),
             bias=min(default_alpha(family, n, dtype) * factor, 1.0))
    if target == "uniform":
        p["bias_target"] = UNIFORM_TARGET[n]
    return p


# ========================================================================= rows
def _config_rows(name: str, seed: int, light: str, P: dict) -> list[dict]:
    """Every grid point of every family and count in one configuration (scene, seed, light)."""
    from avsm_dr.evaluation import Configuration, Probe, curve_values, depth_l2
    cfg = Configuration(seed, light)
    opaque = describe("moments")["preset_capture"].get("opaque", "inline")
    scene, cap = cfg.capture(name, P["resolution"], opaque=opaque)
    seg = cap.segments
    points = cfg.in_volume_receivers(scene, P["n_volume"])
    probe = Probe(cap, scene, points, n_decomp=0, truth_at_points=np.zeros(len(points)))  # truth unused
    exact = build("exact", seg)
    ex_lookup = probe.lookup(exact)
    ex_curve = curve_values(exact, seg, P["n_depths"])
    head = dict(scene=name, config=cfg.label, seed=seed, light=light, resolution=P["resolution"], opaque=opaque,
                receivers=int(points.shape[0]), texels=int(np.count_nonzero(seg.counts)))
    rows = []
    for family, n in P["groups"]:
        for target, factor, beta in grid(P, family):
            params = build_params(family, n, target, factor, beta, seg.dtype)
            rep = build("moments", seg, **params)
            s = error_stats(probe.lookup(rep), ex_lookup)
            rows.append(dict(head, group=group_label(family, n), family=family, moments=n, target=target,
                             alpha_factor=factor, alpha=float(rep.params["bias"]), beta=float(beta),
                             default=is_default(target, factor, beta),
                             bytes_per_texel=float(rep.nbytes_per_texel),
                             depth_l2=depth_l2(rep, seg, exact=ex_curve, n_depths=P["n_depths"]),
                             rmse=s["rmse"], signed_mean=s["mean_error"],
                             order="depth", bytes=float(rep.nbytes_sparse_per_texel),
                             bytes_dense=float(rep.nbytes_per_texel), leak_share=s["leak_fraction"]))
    return rows


def add_ratios(rows: list[dict]) -> None:
    """``ratio_depth_l2`` / ``ratio_rmse``: each row's metric over the least of its cell
    (scene, configuration, group), in place."""
    best: dict = {}
    for r in rows:
        key = (r["scene"], r["config"], r["group"])
        for m in METRICS:
            best[key + (m,)] = min(best.get(key + (m,), np.inf), r[m])
    for r in rows:
        key = (r["scene"], r["config"], r["group"])
        for m in METRICS:
            r[f"ratio_{m}"] = r[m] / best[key + (m,)] if best[key + (m,)] > 0 else 1.0


# ===================================================================== analysis
def _gmean(x) -> float:
    return float(np.exp(np.mean(np.log(np.asarray(x, np.float64)))))


def _interval(ratios, n_boot: int) -> dict:
    """Geometric mean of per-configuration ratios with a bootstrap interval over the
    configurations (a point estimate alone when there is one)."""
    from avsm_dr import stats
    r = np.asarray(ratios, np.float64)
    out = dict(estimate=_gmean(r), n_configs=int(r.size), indicative=bool(r.size < MIN_CONFIGS))
    if r.size >= 2:
        ci = stats.bootstrap_ci(np.log(r), "mean", n_boot=n_boot)
        out.update(low=float(np.exp(ci["low"])), high=float(np.exp(ci["high"])), level=ci["level"])
    return out


def _setting(r) -> tuple:
    return (r["target"], r["alpha_factor"], r["beta"])


def sensitivity(rows: list[dict]) -> list[dict]:
    """One row per group and grid point: geometric means over the cells of both ratios to the
    cell's best, of both metrics, and the mean signed error."""
    cells: dict = {}
    for r in rows:
        cells.setdefault((r["group"], _setting(r)), []).append(r)
    out = []
    for (group, (target, factor, beta)), rs in cells.items():
        out.append(dict(group=group, family=rs[0]["family"], moments=rs[0]["moments"], target=target,
                        alpha_factor=factor, alpha=rs[0]["alpha"], beta=beta, default=rs[0]["default"],
                        n_cells=len(rs), ratio_depth_l2=_gmean([r["ratio_depth_l2"] for r in rs]),
                        ratio_rmse=_gmean([r["ratio_rmse"] for r in rs]),
                        depth_l2=_gmean([r["depth_l2"] for r in rs]), rmse=_gmean([r["rmse"] for r in rs]),
                        signed_mean=float(np.mean([r["signed_mean"] for r in rs]))))
    return out


def choose(table: list[dict], metric: str = "depth_l2") -> dict:
    """{group: sensitivity row} of the least geometric-mean ratio of ``metric`` (ties: the
    first in grid order)."""
    out = {}
    for r in table:
        g = r["group"]
        if g not in out or r[f"ratio_{metric}"] < out[g][f"ratio_{metric}"]:
            out[g] = r
    return out


def _ratios(rows, group, setting, metric, seeds=None) -> list[float]:
    """Per cell of ``group`` (optionally only ``seeds``): metric at ``setting`` over the default's."""
    by = {}
    for r in rows:
        if r["group"] == group and (seeds is None or r["seed"] in seeds):
            by.setdefault((r["scene"], r["config"]), {})[_setting(r)] = r
    out = []
    for cell in sorted(by):
        d = by[cell]
        dflt = next(r for r in d.values() if r["default"])
        out.append(d[setting][metric] / dflt[metric] if dflt[metric] > 0 else 1.0)
    return out


def _cross_validated(rows, group, metric, n_boot, pick) -> dict | None:
    """Leave one seed out: per seed the setting ``pick(rows of the other seeds)`` chooses,
    its ratio to the default on the seed left out; pooled over the cells."""
    seeds = sorted({r["seed"] for r in rows})
    if len(seeds) < 2:
        return None
    ratios, chosen = [], {}
    for s in seeds:
        setting = pick([r for r in rows if r["seed"] != s])
        chosen[str(s)] = list(setting)
        ratios += _ratios(rows, group, setting, metric, {s})
    return dict(_interval(ratios, n_boot), chosen_per_left_out_seed=chosen)


def _pick_group(group):
    """A function rows -> the depth-L2 choice of ``group`` on those rows."""
    def pick(rs):
        rs = [dict(r) for r in rs if r["group"] == group]      # copies: the ratios are recomputed
        add_ratios(rs)
        return _setting(choose(sensitivity(rs))[group])
    return pick


def preset_table(table: list[dict]) -> list[dict]:
    """Per beta at the default target and alpha: geometric means over every group (a
    geometric mean of the groups' geometric means) of both ratios."""
    out = []
    for beta in sorted({r["beta"] for r in table}):
        sel = [r for r in table if r["beta"] == beta and r["target"] == "default" and r["alpha_factor"] == 1.0]
        out.append(dict(beta=beta, ratio_depth_l2=_gmean([r["ratio_depth_l2"] for r in sel]),
                        ratio_rmse=_gmean([r["ratio_rmse"] for r in sel]), groups=len(sel)))
    return out


def _pick_preset(rs) -> float:
    rs = [dict(r) for r in rs]
    add_ratios(rs)
    return min(preset_table(sensitivity(rs)), key=lambda r: r["ratio_depth_l2"])["beta"]


def findings(rows: list[dict], table: list[dict], P: dict) -> dict:
    """The choices, their improvement over MBOIT's defaults and the preset (module docstring)."""
    from .error_curves import FULL as EC_FULL
    n_boot = P["n_boot"]
    by_l2, by_rmse = choose(table, "depth_l2"), choose(table, "rmse")
    ec_seeds = sorted({s for s, _ in EC_FULL["configs"]})
    out: dict = dict(
        held_out_seeds=sorted({s for s, _ in P["configs"]}), error_curves_seeds=ec_seeds,
        seeds_disjoint=not ({s for s, _ in P["configs"]} & set(ec_seeds)),
        scenes=list(P["scenes"]), configurations=[f"s{s}-{li}" for s, li in P["configs"]],
        interval_unit="configuration (scene x seed x light)",
        default=dict(target="default", alpha_factor=1.0, beta=default_beta()), groups={})
    for family, n in P["groups"]:
        g = group_label(family, n)
        c, cr = by_l2[g], by_rmse[g]
        setting, setting_r = _setting(c), _setting(cr)
        cost = c["ratio_rmse"] / cr["ratio_rmse"]
        dflt = next(r for r in table if r["group"] == g and r["default"])
        out["groups"][g] = dict(
            family=family, moments=n,
            chosen=dict(target=c["target"], alpha_factor=c["alpha_factor"], alpha=c["alpha"], beta=c["beta"],
                        ratio_depth_l2=c["ratio_depth_l2"], ratio_rmse=c["ratio_rmse"],
                        signed_mean=c["signed_mean"]),
            default=dict(alpha=dflt["alpha"], beta=dflt["beta"], ratio_depth_l2=dflt["ratio_depth_l2"],
                         ratio_rmse=dflt["ratio_rmse"], signed_mean=dflt["signed_mean"]),
            rmse_choice=dict(target=cr["target"], alpha_factor=cr["alpha_factor"], alpha=cr["alpha"],
                             beta=cr["beta"], ratio_rmse=cr["ratio_rmse"]),
            same_choice=setting == setting_r, rmse_cost_of_depth_l2_choice=cost,
            metric_dependent=bool(setting != setting_r and cost > 1 + METRIC_TOLERANCE),
            tuned_over_default={m: _interval(_ratios(rows, g, setting, m), n_boot) for m in METRICS},
            per_scene={s: {m: _interval(_ratios([r for r in rows if r["scene"] == s], g, setting, m), n_boot)
                           for m in METRICS} for s in P["scenes"]},
            cross_validated={m: _cross_validated(rows, g, m, n_boot, _pick_group(g)) for m in METRICS})
    # one beta for every group at the default alpha and target: what a preset can hold
    pt = preset_table(table)
    beta = min(pt, key=lambda r: r["ratio_depth_l2"])["beta"]
    beta_rmse = min(pt, key=lambda r: r["ratio_rmse"])["beta"]
    over = {}
    for family, n in P["groups"]:
        g = group_label(family, n)
        over[g] = {m: _interval(_ratios(rows, g, ("default", 1.0, beta), m), n_boot) for m in METRICS}
    pooled = {m: _interval([x for family, n in P["groups"]
                            for x in _ratios(rows, group_label(family, n), ("default", 1.0, beta), m)], n_boot)
              for m in METRICS}
    beats = all(o[m].get("high", o[m]["estimate"]) < 1 for o in over.values() for m in METRICS)
    cv = None
    if len({r["seed"] for r in rows}) >= 2:
        ratios = {m: [] for m in METRICS}
        chosen = {}
        for s in sorted({r["seed"] for r in rows}):
            b = _pick_preset([r for r in rows if r["seed"] != s])
            chosen[str(s)] = b
            for family, n in P["groups"]:
                for m in METRICS:
                    ratios[m] += _ratios(rows, group_label(family, n), ("default", 1.0, b), m, {s})
        cv = dict({m: _interval(v, n_boot) for m, v in ratios.items()}, beta_per_left_out_seed=chosen)
    out["preset"] = dict(beta=beta, rmse_beta=beta_rmse, metric_dependent=bool(beta != beta_rmse),
                         by_beta=pt, preset_over_default=over, pooled_over_default=pooled,
                         cross_validated=cv, preset_beats_defaults=bool(beats),
                         current_preset=describe("moments")["preset"])
    return out


# ======================================================================== figure
def _plot(res, table: list[dict], found: dict, groups) -> None:
    """Small multiples: one column per moment count, two rows per family (the two metrics),
    the geometric mean of the ratio to the cell's best against beta, one line per alpha factor
    (default target); the chosen setting circled, MBOIT's beta dotted."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.ticker
    from . import _plotstyle as plotstyle
    factors = sorted({r["alpha_factor"] for r in table})
    colours = list(plotstyle.PALETTE.values())
    markers = ("o", "s", "^", "D", "v", "P", "X")
    styles = ("-", "--", "-.", ":", (0, (5, 1)), (0, (1, 1)), (0, (3, 1, 1, 1)))
    rows_ = (("depth_l2", "depth L2"), ("rmse", "RMSE"))
    families = list(dict.fromkeys(f for f, _ in groups))
    counts = {f: [n for g, n in groups if g == f] for f in families}
    cols = max(len(v) for v in counts.values())
    with plotstyle.context():
        fig, axes = plotstyle.grid(len(rows_) * len(families), cols, panel=(2.5, 2.0), sharex=True, sharey="row")
        for b, family in enumerate(families):
            for j in range(len(counts[family]), cols):                       # unused panels
                for i in range(len(rows_)):
                    axes[b * len(rows_) + i][j].set_visible(False)
        for family, n in groups:
            g = group_label(family, n)
            b, j = families.index(family), counts[family].index(n)
            chosen = found["groups"][g]["chosen"]
            for i, (metric, ylabel) in enumerate(rows_):
                ax = axes[b * len(rows_) + i][j]
                lines = []
                for k, f in enumerate(factors):
                    sel = sorted((r for r in table if r["group"] == g and r["target"] == "default"
                                  and r["alpha_factor"] == f), key=lambda r: r["beta"])
                    lines.append([r[f"ratio_{metric}"] for r in sel])
                    ax.plot([r["beta"] for r in sel], lines[-1], color=colours[k % len(colours)],
                            marker=markers[k % len(markers)], linestyle=styles[k % len(styles)], markersize=3,
                            label=f"alpha = {f:g} x default")
                spread = float(np.max(np.max(lines, axis=0) / np.min(lines, axis=0)) - 1)
                note = "< 0.01 %" if spread < 1e-4 else f"<= {100 * spread:.2g} %"
                ax.text(0.5, 0.97, f"alpha changes it by {note}", transform=ax.transAxes,
                        ha="center", va="top", fontsize=6.5)
                pick = next(r for r in table if r["group"] == g and _setting(r) == (
                    chosen["target"], chosen["alpha_factor"], chosen["beta"]))
                ax.plot([pick["beta"]], [pick[f"ratio_{metric}"]], linestyle="none", marker="o", markersize=9,
                        markerfacecolor="none", markeredgecolor="k", label="chosen on depth L2")
                ax.axvline(default_beta(), color="0.4", linewidth=0.8, linestyle=":",
                           label=f"MBOIT's beta ({default_beta():g})")
                ax.set_yscale("log")
                ax.yaxis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
                ax.yaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
                ax.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
                ax.set_title(f"{'trig.' if family == 'trigonometric' else family} {n}"
                             f"{' (complex)' if family == 'trigonometric' else ''}: "
                             + ("depth-uniform L2" if i == 0 else "receiver RMSE"), fontsize=8)
                if b == len(families) - 1 and i == len(rows_) - 1 or j >= len(counts[families[-1]]) \
                        and i == len(rows_) - 1:
                    ax.set_xlabel("overestimation beta\n(0: lower bound, light; 1: upper, dark)")
                    ax.xaxis.set_tick_params(labelbottom=True)
                if j == 0:
                    ax.set_ylabel(f"{ylabel} / cell's best\n(geometric mean)")
        fig.suptitle(f"moments on held-out seeds {', '.join(map(str, found['held_out_seeds']))}: error against beta,\n"
                     f"default bias target, {len(found['scenes'])} scenes x {len(found['configurations'])} "
                     f"configurations per point", fontsize=9)
        plotstyle.legend_below(fig, axes, ncol=min(len(factors) + 2, 4))
        res.save_figure(fig, "moment_tuning.png")


# =========================================================================== run
def _resolve(P: dict, quick: bool) -> dict:
    """Scenes and groups checked; the seeds checked held out from error_curves'; the default
    (MBOIT's) setting checked on the grid."""
    from avsm_dr.builtin_scenes import SCENES as KNOWN
    from avsm_dr.representations.moments import FAMILIES
    from .error_curves import FULL as EC_FULL
    P["scenes"] = list(P["scenes"])
    for s in P["scenes"]:
        if s not in KNOWN:
            raise ValueError(f"scenes: unknown scene {s!r}; known: {sorted(KNOWN)}")
    for family, n in P["groups"]:
        if family not in FAMILIES or n not in FAMILIES[family]:
            raise ValueError(f"groups: {family!r} takes {FAMILIES.get(family)}, got {n}")
    used = {s for s, _ in P["configs"]} & {s for s, _ in EC_FULL["configs"]}
    if used:
        raise ValueError(f"configs: seeds {sorted(used)} are evaluated by error_curves; tuning seeds must be held out")
    if default_beta() not in P["betas"] or 1.0 not in P["alpha_factors"] or "default" not in P["targets"]:
        raise ValueError("betas / alpha_factors / targets: MBOIT's default (beta 0.25, factor 1, target 'default') "
                         "must be a grid point")
    return P


def _compute(res, P: dict) -> dict:
    """Every configuration's rows, the sensitivity table, the findings and the figure."""
    t0 = time.perf_counter()
    rows: list[dict] = []
    jobs = [(name, seed, light) for name in P["scenes"] for seed, light in P["configs"]]
    for name, seed, light in tqdm(jobs, desc="moment_tuning", unit="config"):
        rows += _config_rows(name, seed, light, P)
    add_ratios(rows)
    table = sensitivity(rows)
    found = findings(rows, table, P)
    found["run_seconds"] = time.perf_counter() - t0
    write_data(res, dict(rows=rows, tables={"sensitivity.csv": table}, findings=found))   # before the figures
    _plot(res, table, found, [tuple(g) for g in P["groups"]])
    summary = {}
    for g, d in found["groups"].items():          # at most 100 characters per line
        c, t = d["chosen"], d["tuned_over_default"]
        summary[g] = (f"b={c['beta']:g} a={c['alpha_factor']:g}x {c['target']}: /MBOIT L2 {_fmt(t['depth_l2'])} "
                      f"RMSE {_fmt(t['rmse'])}" + (" metric-dep." if d["metric_dependent"] else ""))
    p = found["preset"]
    summary["preset beta"] = (f"{p['beta']:g}: /MBOIT L2 {_fmt(p['pooled_over_default']['depth_l2'])} RMSE "
                              f"{_fmt(p['pooled_over_default']['rmse'])}, beats it: {p['preset_beats_defaults']}")
    summary["run seconds"] = round(found["run_seconds"], 1)
    return dict(rows=rows, tables={"sensitivity.csv": table}, findings=found, summary=summary)


def _fmt(iv: dict) -> str:
    if "low" in iv:
        return f"{iv['estimate']:.2f} [{iv['low']:.2f}, {iv['high']:.2f}]"
    return f"{iv['estimate']:.2f}"


STUDY = Study("moment_tuning", "moments' beta, bias and target tuned for media on held-out seeds", REPRODUCES,
              FULL, QUICK, _compute, resolve=_resolve, writes=("data.csv", "sensitivity.csv", "findings.json"),
              options=(Option("scenes", "built-in scenes to run (default: the mode's)", nargs="+", metavar="SCENE"),))
run = STUDY.run

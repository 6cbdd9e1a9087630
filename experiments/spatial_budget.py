"""Spatial vs depth budget: at a fixed number of bytes per shadow map, is it better to spend
them on texels (resolution) or on nodes / coefficients per texel?

For each byte budget B and resolution R the depth budget is ``B / R^2`` bytes per texel;
each kind (:data:`KINDS`) gets the largest value of its size parameter that fits (read from
the registry: ``describe(kind)['size']``, bytes from ``rep.nbytes_per_texel``), e.g.
B = 512 KiB: AVSM 16 nodes at 64^2 or 4 nodes at 128^2.  Kinds without a size parameter
(4 power moments) get the one resolution their fixed bytes allow.  The uncompressed
``exact`` curve at each resolution is the spatial floor (its bytes are not budgeted).

Error: against the *true* transmittance at each receiver, the float64 midpoint quadrature
of the trilinear density along its light ray (:func:`avsm_dr.groundtruth.transmittance`,
``'raymarch'``, step voxel / 8), not against a shadow map; bilinear lookups; every
configuration (seed x light) of every scene; receivers split into ``volume`` (in the
smoke) and ``surface`` (the receiver plane) besides ``all``.  Statistics
(:mod:`avsm_dr.metrics`): RMSE, signed mean, leak / dark fractions, p99 / p99.9, optical-depth
RMSE; a bootstrap 95 % interval of the RMSE over receivers (:mod:`avsm_dr.stats`).
Per row also: the capture's insertion ``order`` ('depth'), ``bytes`` (the sparse
layout, ``nbytes_sparse_per_texel``) and ``bytes_dense`` (= ``bytes_per_texel``, the unit of
the budgets), and ``depth_l2``, the depth-uniform L2 of the map's curve against the exact
curve at the same resolution (:func:`avsm_dr.evaluation.depth_l2`; 0 for ``exact``);
``mean_error`` is the signed mean and ``leak_fraction`` the leak share.  The claims (best
resolution, vs the runner-up) use the receiver RMSE against the truth only: the depth-uniform
L2 measures compression at one resolution and is blind to the spatial error the study
trades against, so it cannot rank resolutions.  Intervals per resolution are over the
receivers of all configurations (``interval_unit``); the comparison with the runner-up is
over configurations (:func:`avsm_dr.stats.claim`), ``indicative`` below
:data:`MIN_CONFIDENT` of them.
Lookup cost per bilinear lookup, in each scene's first configuration: Dr.Jit kernel
execution time of a batch (``lookup_ns``, median after warm-up, ``dr.kernel_history``) and
wall time including host work and any recompilation (``lookup_wall_ns``).
"""

from __future__ import annotations

import functools
import re

import numpy as np
from tqdm import tqdm

from avsm_dr import allows, build, describe, kinds
from avsm_dr.evaluation import curve_values, depth_l2
from avsm_dr.metrics import error_stats
from avsm_dr.scene import DirectionalLight
from ._common import measure
from ._headline import interval, num
from ._study import Study, write_data
from ._tau import optical_depth_error

#: What this study reproduces (a paper's figure or table, or the guide's section).
REPRODUCES = (
    "The guide's spatial-vs-depth budget table: at a fixed number of bytes per shadow map, "
    'resolution against nodes / coefficients per texel, error against the true transmittance.'
)


#: Kinds swept (size parameter from the registry; None = fixed size).  The lead may switch
#: this to every registered kind with a size parameter.
KINDS = ["avsm", "fom", "osm", "moments"]
#: Largest size-parameter value tried for kinds whose schema has no maximum.
MAX_SIZE_VALUE = 256
#: Light directions of the configurations (the scene's own first).
LIGHTS = [None, (0.6, -0.75, -0.3)]
#: Receiver groups: scenes put half their receivers in the volume, half on the plane.
GROUPS = ("all", "volume", "surface")
#: Below this many configurations (seed x light) a comparison is ``indicative``.
MIN_CONFIDENT = 4

#: Parameters of the full and the quick run.
FULL = dict(scenes=["plume", "simulated_plume", "hair_and_smoke"], seeds=[0, 1, 2, 3], lights=LIGHTS,
            budgets=[1 << 19, 1 << 21], resolutions=[64, 128, 256, 512], n_receivers=4096, step_fraction=0.125,
            filter="bilinear", lookups=1 << 18, kinds=KINDS)
QUICK = dict(FULL, scenes=["plume"], seeds=[0], lights=LIGHTS[:1], budgets=[1 << 19], resolutions=[64, 128],
             n_receivers=1024, lookups=1 << 16)


@functools.lru_cache(maxsize=None)
def bytes_per_texel(kind: str, **params) -> float:
    """``nbytes_per_texel`` of ``kind`` with ``params`` (built on a one-segment toy map;
    float32 storage)."""
    from avsm_dr import Segments
    seg = Segments.from_arrays(np.array([0, 1]), np.array([0.0]), np.array([1.0]), optical_depth=np.array([0.1]))
    return float(build(kind, seg, **params).nbytes_per_texel)


def fit(kind: str, budget_per_texel: float) -> dict | None:
    """The kind's headline parameters with the largest size value whose bytes per texel fit
    ``budget_per_texel`` (None when even the smallest does not fit).  Kinds without a size
    parameter: their headline, if it fits."""
    d = describe(kind)
    base = dict(d["headline"])
    if d["size"] is None:
        return base if bytes_per_texel(kind, **base) <= budget_per_texel else None
    spec = d["params"][d["size"]]
    lo = int(spec["min"] or 1)
    hi = int(spec["max"] or MAX_SIZE_VALUE)
    # bytes per texel are affine in the size value for every swept kind (8 N, 4 (2n + 1), 4 n):
    # toy builds at the two smallest allowed values give the line, one more checks the chosen
    # value (the schema's constraint may allow only some values, e.g. even power-moment counts)
    ok = lambda v: allows(kind, dict(base, **{d["size"]: v}))  # noqa: E731
    a1 = next((v for v in range(lo, hi + 1) if ok(v)), None)
    a2 = next((v for v in range(a1 + 1, hi + 1) if ok(v)), None) if a1 is not None else None
    if a1 is None or a2 is None:
        return None
    b0 = bytes_per_texel(kind, **dict(base, **{d["size"]: a1}))
    slope = (bytes_per_texel(kind, **dict(base, **{d["size"]: a2})) - b0) / (a2 - a1)
    if b0 > budget_per_texel or slope <= 0:
        return None
    best = min(hi, a1 + int((budget_per_texel - b0) // slope))
    while best > a1 and not ok(best):
        best -= 1
    out = dict(base, **{d["size"]: best})
    if bytes_per_texel(kind, **out) > budget_per_texel:
        raise RuntimeError(f"{kind}: bytes per texel are not affine in {d['size']!r}")
    return out


def plan(budget: int, resolutions) -> list[tuple[str, int, dict]]:
    """(kind, resolution, params) of every point of the sweep at ``budget`` bytes per map."""
    out = []
    for kind in KINDS:
        if kind not in kinds():
            continue
        if describe(kind)["size"] is None:
            r = int(np.sqrt(budget / bytes_per_texel(kind, **describe(kind)["headline"])))
            if 64 <= r <= 1024:
                out.append((kind, r, dict(describe(kind)["headline"])))
            continue
        for r in resolutions:
            p = fit(kind, budget / r ** 2)
            if p is not None:
                out.append((kind, int(r), p))
    return out


def _groups(n):
    """Receiver slices: the built-in scenes put the first half in the volume."""
    half = n // 2
    return {"all": slice(0, n), "volume": slice(0, half), "surface": slice(half, n)}


def _configs(names, seeds, lights, n_receivers):
    from avsm_dr import scenes as scene_lib
    for name in names:
        for seed in seeds:
            for li, light in enumerate(lights):
                kw = dict(seed=seed, n_receivers=n_receivers)
                if light is not None:
                    kw["light"] = DirectionalLight(direction=light)
                yield name, seed, li, scene_lib.get(name, **kw)


def _compute(res, params: dict) -> dict:
    """Every kind at each budget and resolution, per configuration; the findings and figures."""
    from avsm_dr import capture
    from avsm_dr.receivers import marched, voxel_step
    from avsm_dr.stats import bootstrap_ci, claim
    plans = {b: plan(b, params["resolutions"]) for b in params["budgets"]}
    resolutions = sorted({r for p in plans.values() for _, r, _ in p} | set(params["resolutions"]))
    rows, errors = [], {}                     # errors[(scene, budget, kind, res, config)] = signed errors
    configs = list(_configs(params["scenes"], params["seeds"], params["lights"], params["n_receivers"]))
    for name, seed, li, scene in tqdm(configs, desc="spatial_budget", unit="config"):
        pts = np.asarray(scene.receivers, np.float64)
        step = voxel_step(scene, params["step_fraction"])
        truth = marched(scene, pts, params["step_fraction"])
        groups = _groups(pts.shape[0])
        many = np.resize(pts, (params["lookups"], 3))          # the lookup-timing batch (receivers first)
        base = dict(scene=name, seed=seed, light=li)
        timing = seed == params["seeds"][0] and li == 0
        for r in resolutions:
            need = [(b, k, p) for b in params["budgets"] for k, rr, p in plans[b] if rr == r]
            if not need and r not in params["resolutions"]:
                continue
            cap = capture(scene, resolution=r, step=step, order="depth")
            todo = [("exact", None, {})] + [(k, b, p) for b, k, p in need]
            ex_curve = None
            for kind, b, p in todo:
                rep = build(kind, cap.segments, **p)
                if ex_curve is None:                   # exact comes first: the curves' reference
                    ex_curve = curve_values(rep, cap.segments)
                l2 = depth_l2(rep, cap.segments, exact=ex_curve)
                # timed in each scene's first configuration only (the cost does not depend on
                # seed or light); the batch starts with the receivers, so its first call gives
                # the estimates too
                tm = measure({"lookup": lambda: cap.transmittance(rep, many if timing else pts,
                                                                  filter=params["filter"])},
                             repeats=(2 if res.quick else 3) if timing else 0)["lookup"]
                est = np.asarray(tm["out"], np.float64)[:pts.shape[0]]
                cost = dict(lookup_ns=tm["kernel_s"] / params["lookups"] * 1e9,
                            lookup_wall_ns=tm["wall_s"] / params["lookups"] * 1e9) if timing else {}
                size = describe(kind)["size"]
                for g in GROUPS:
                    sl = groups[g]
                    st = error_stats(est[sl], truth[sl])
                    od = optical_depth_error(est[sl], truth[sl])
                    rows.append(dict(base, budget_bytes=b if b is not None else "", receivers=g, kind=kind,
                                     resolution=r, param=p.get(size, "") if size else "",
                                     bytes_per_texel=rep.nbytes_per_texel, map_bytes=rep.nbytes_per_texel * r * r,
                                     **{k: st[k] for k in ("rmse", "mean_error", "mean_abs_error", "leak_fraction",
                                                           "dark_fraction", "p99_error", "p999_error", "max_error",
                                                           "nan_count")},
                                     tau_rmse=od["tau_rmse"], **cost, order="depth",
                                     bytes=float(rep.nbytes_sparse_per_texel),
                                     bytes_dense=float(rep.nbytes_per_texel), depth_l2=l2))
                if kind != "exact":
                    errors[(name, b, kind, r, (seed, li))] = est - truth
    summary = _summarise(rows, errors, params, bootstrap_ci, claim)
    write_data(res, dict(rows=rows, findings=summary))        # before the figures
    _plot(res, rows, params, summary)
    return dict(rows=rows, findings=summary, summary=summary)


def _summarise(rows, errors, params, bootstrap_ci, claim) -> dict:
    """Per scene, budget and kind: RMSE per resolution pooled over configurations (all
    receivers) with a bootstrap 95 % interval over receivers, the best resolution, and
    whether it beats the runner-up in every configuration (paired, :func:`stats.claim`)."""
    out = {}
    for name in params["scenes"]:
        for b in params["budgets"]:
            for kind in KINDS:
                keys = sorted({(k[3]) for k in errors if k[0] == name and k[1] == b and k[2] == kind})
                if not keys:
                    continue
                per_res = {}
                for r in keys:
                    cfgs = sorted(c for (n, bb, k, rr, c) in errors if (n, bb, k, rr) == (name, b, kind, r))
                    e = np.concatenate([errors[(name, b, kind, r, c)] for c in cfgs])
                    ci = bootstrap_ci(e, "rmse", seed=0)
                    par = next((row["param"] for row in rows if row["scene"] == name and row["kind"] == kind
                                and row["resolution"] == r and row["budget_bytes"] == b), "")
                    per_res[r] = dict(param=par, rmse=ci["estimate"], low=ci["low"], high=ci["high"])
                best = min(per_res, key=lambda r: per_res[r]["rmse"])
                item = dict(per_resolution=per_res, best_resolution=best)
                if len(per_res) > 1:
                    second = sorted(per_res, key=lambda r: per_res[r]["rmse"])[1]
                    cfgs = sorted(c for (n, bb, k, rr, c) in errors if (n, bb, k, rr) == (name, b, kind, best))
                    cl = claim([np.abs(errors[(name, b, kind, best, c)]) for c in cfgs],
                               [np.abs(errors[(name, b, kind, second, c)]) for c in cfgs],
                               configs=[f"seed{c[0]}_light{c[1]}" for c in cfgs])
                    item["vs_runner_up"] = dict(runner_up=second, rmse_ratio=cl["estimate"], low=cl["low"],
                                                high=cl["high"],
                                                holds_in_every_configuration=cl["holds_in_every_configuration"],
                                                n_configs=cl["n_configs"],
                                                indicative=cl["n_configs"] < MIN_CONFIDENT,
                                                interval_unit="configuration")
                item["interval_unit"] = "receiver (per resolution, all configurations pooled)"
                out[f"{name}_{b}B_{kind}"] = item
    return out


def _plot(res, rows, params, summary):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    colors = {"avsm": "C0", "fom": "C1", "osm": "C2", "moments": "C4", "exact": "k"}
    names, budgets = params["scenes"], params["budgets"]
    fig, axes = plt.subplots(len(budgets), len(names), figsize=(4.6 * len(names), 3.8 * len(budgets)),
                             squeeze=False)
    for i, b in enumerate(budgets):
        for j, name in enumerate(names):
            ax = axes[i][j]
            ex = sorted({r["resolution"] for r in rows if r["scene"] == name and r["kind"] == "exact"})
            ax.plot(ex, [_mean(rows, name, "exact", r, "") for r in ex], "k--", lw=1,
                    label="exact (spatial floor)")
            for kind in KINDS:
                item = summary.get(f"{name}_{b}B_{kind}")
                if not item:
                    continue
                rs = sorted(item["per_resolution"])
                y = [item["per_resolution"][r]["rmse"] for r in rs]
                err = [[y[k] - item["per_resolution"][r]["low"] for k, r in enumerate(rs)],
                       [item["per_resolution"][r]["high"] - y[k] for k, r in enumerate(rs)]]
                ax.errorbar(rs, y, yerr=err, fmt="o-", color=colors.get(kind), capsize=2, label=kind)
                for r, yy in zip(rs, y):
                    ax.annotate(str(item["per_resolution"][r]["param"]), (r, yy), fontsize=6,
                                textcoords="offset points", xytext=(3, 3))
            ax.set_xscale("log", base=2)
            ax.set_yscale("log")
            ax.set_title(f"{name}, {b / 1024:.0f} KiB per map", fontsize=9)
            ax.set_xlabel("resolution (texels per side)")
        axes[i][0].set_ylabel("RMSE vs true T (all receivers)")
    axes[0][0].legend(fontsize=7)
    fig.suptitle("equal bytes per map: resolution x depth (labels: nodes / harmonics / slices)")
    fig.tight_layout()
    res.save_figure(fig, "error_vs_resolution.png")

    fig, ax = plt.subplots(figsize=(5, 3.6))
    for kind in ["exact"] + KINDS:
        pts = sorted({(r["resolution"], r["lookup_ns"]) for r in rows if r["kind"] == kind and r["receivers"] == "all"
                      and r["scene"] == names[0] and r["seed"] == params["seeds"][0] and r["light"] == 0})
        if pts:
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o", color=colors.get(kind), label=kind)
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("resolution")
    ax.set_ylabel("ns per bilinear lookup")
    ax.legend(fontsize=7)
    fig.tight_layout()
    res.save_figure(fig, "lookup_cost.png")


def _mean(rows, name, kind, r, budget):
    v = [x["rmse"] for x in rows if x["scene"] == name and x["kind"] == kind and x["resolution"] == r
         and x["receivers"] == "all" and x["budget_bytes"] == budget]
    return float(np.sqrt(np.mean(np.square(v)))) if v else np.nan

def _headline(s: dict) -> list[str]:
    """Per scene, budget and kind: the best shadow-map resolution at equal total bytes, its
    RMSE, and its RMSE over the runner-up's."""
    out = []
    for key, d in s.items():
        if not isinstance(d, dict) or "best_resolution" not in d:
            continue
        scene, nbytes, kind = re.match(r"(.+)_(\d+)B_(.+)$", key).groups()
        best = str(d["best_resolution"])
        r = d["per_resolution"][best]
        line = f"{scene}, {kind} in {num(int(nbytes))} B: best at {best}^2 (param {r['param']}), RMSE {interval(r)}"
        v = d.get("vs_runner_up")
        if v:
            line += (f"; RMSE over {v['runner_up']}^2's {interval(v)}"
                     + (" in every configuration" if v.get("holds_in_every_configuration") else ""))
        out.append(line)
    return out


STUDY = Study("spatial_budget", "Spatial vs depth budget: shadow-map resolution against nodes at equal bytes",
              REPRODUCES, FULL, QUICK, _compute, writes=("data.csv", "findings.json"), headline=_headline)
run = STUDY.run

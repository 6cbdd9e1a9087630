"""Effect of insertion order on AVSM (Salvi et al. 2010, sec. 4.1): error against the exact curve and
temporal flicker (the change of T between two random insertion orders of the same
segments, as unordered GPU capture would produce frame to frame), with and without
sorting, for several node counts, over configurations (scene seed x light; full mode:
:data:`FULL_CONFIGS`, ten per scene, two of them a spot light).

Per scene, configuration, N and ``sorted``: ``orders`` shuffles of the captured segments
(:func:`shuffled`, seeded per configuration), AVSM-N built on each, unsorted (``order``
'random') or sorted front to back by ``build(..., sort=True)`` (``order`` 'depth').
Columns, at the in-volume receivers by contribution (:func:`avsm_dr.receivers.in_volume`,
nearest-texel lookups) against the exact curve: ``rmse`` (mean over the shuffles),
``max_error``, ``signed_mean`` and ``leak_share`` (error > 0.02, means over the shuffles),
``depth_l2`` (:func:`avsm_dr.evaluation.depth_l2`, RMS over the shuffles); flicker between
consecutive shuffles: ``flicker_rms`` and ``flicker_max`` of ``|T_k+1 - T_k|`` at the
receivers, ``flicker_texels_over_1pct`` (share of receivers changing by more than 0.01) and
``flicker_depth_l2`` (the depth-uniform L2 of one shuffle's curve against the previous
one's, RMS over texels and pairs); ``bytes`` (sparse) and ``bytes_dense``.

``findings.json``, per scene and N, two claims on both metrics, their intervals' unit the
configuration (8 x 8 texel tiles within one; ``n_configs``, ``indicative`` below
:data:`experiments._two_metric.MIN_CONFIDENT` configurations, ``order`` 'depth / random':
the sorted side against the unsorted one, ``metric_dependent``, each side's signed mean and
leak share): ``sorted_below_unsorted`` (:func:`experiments._two_metric.claim`: error ratios,
the shuffles' errors pooled) and ``sorting_removes_flicker`` (:func:`flicker_claim`: the
difference of the flicker RMS, sorted minus unsorted, at the receivers and in depth L2;
``holds_in_every_configuration`` from :data:`MIN_EVERY` configurations on).
:mod:`experiments.insertion_order` compares the four capture orders against the optimum.

Full run: about 100 CPU seconds of configurations (3 scenes x 10, extrapolated from three
configurations per scene measured at full parameters: 1.7 to 5.7 s each).
"""

from __future__ import annotations

import numpy as np
from tqdm import tqdm

from avsm_dr import build
from avsm_dr.metrics import error_stats
from avsm_dr.segments import Segments
from ._headline import num, wrap
from ._study import Study, write_data
from ._two_metric import MIN_CONFIDENT, claim, metric_dependent, side

#: What this study reproduces (a paper's figure or table, or the guide's section).
REPRODUCES = (
    'Salvi et al., "Adaptive Volumetric Shadow Maps", EGSR 2010, section 4.1 (insertion order): '
    'AVSM error and frame-to-frame flicker under shuffled insertion, sorted against unsorted.'
)

#: Fewer configurations than this: no "in every configuration" statement.
MIN_EVERY = 8
#: Seed of the shuffles (with the configuration's index).
SHUFFLE_SEED = 3


def shuffled(seg: Segments, rng) -> Segments:
    """The same segments in a random order within every texel."""
    h = seg.numpy()
    tex = np.repeat(np.arange(seg.n_texels), seg.counts)
    perm = np.lexsort((rng.random(tex.size), tex))
    return Segments.from_arrays(h["offsets"], h["z0"][perm], h["z1"][perm], optical_depth=h["optical_depth"][perm],
                                dtype=seg.dtype)


#: Full mode: 4 seeds x both directional lights and 2 seeds x the spot light (error_curves').
FULL_CONFIGS = [[s, li] for s in range(4) for li in ("dir_a", "dir_b", "spot") if li != "spot" or s < 2]

#: Parameters of the full and the quick run.
FULL = dict(scenes=["three_columns", "hair_and_smoke", "plume"], resolution=128, orders=8, nodes=[4, 8, 12, 16],
            configs=FULL_CONFIGS, n_volume=2048, n_boot=1000)
QUICK = dict(FULL, scenes=["three_columns"], resolution=64, orders=3, nodes=[4, 8, 16],
             configs=[[0, "dir_a"], [1, "spot"]], n_volume=256, n_boot=200)


def _config(name: str, ci: int, P: dict, store: dict) -> list[dict]:
    """Rows of configuration ``P['configs'][ci]`` of scene ``name``; per (N, sorted) its
    receiver errors, per-texel depth L2, receiver flicker and per-texel flicker L2 (each
    pooled over the shuffles or their pairs) and the 8 x 8 tiles into ``store``."""
    from avsm_dr.evaluation import Configuration, curve_values, depth_grid, depth_l2
    from ._two_metric import texel_blocks
    seed, light = P["configs"][ci]
    cfg = Configuration(seed, light)
    scene, cap = cfg.capture(name, P["resolution"])
    texel, depth = cap.lookup(cfg.in_volume_receivers(scene, P["n_volume"]))
    seg = cap.segments
    ex_rep = build("exact", seg)
    exact = np.asarray(ex_rep.eval(texel, depth), np.float64)
    curve = curve_values(ex_rep, seg)
    rng = np.random.default_rng([SHUFFLE_SEED, ci])
    orders = [shuffled(seg, rng) for _ in range(P["orders"])]
    k = len(orders)
    rec_t, tex_t = texel_blocks(texel, cap.width), texel_blocks(depth_grid(seg)[0], cap.width)
    store.setdefault("tiles", {})[cfg.label] = {"errors": (np.tile(rec_t, k), np.tile(tex_t, k)),
                                                "flicker": (np.tile(rec_t, k - 1), np.tile(tex_t, k - 1))}
    rows = []
    for nodes in P["nodes"]:
        for sort in (False, True):
            reps = [build("avsm", s, nodes=nodes, sort=sort) for s in orders]
            Ts = [np.asarray(rep.eval(texel, depth), np.float64) for rep in reps]
            flicker = [np.abs(Ts[j + 1] - Ts[j]) for j in range(k - 1)]
            curves = [curve_values(rep, seg) for rep in reps]
            flicker_l2 = [depth_l2(reps[j + 1], seg, exact=curves[j], per_texel=True) for j in range(k - 1)]
            l2 = [depth_l2(rep, seg, exact=curve, per_texel=True) for rep in reps]
            errs = [error_stats(T, exact) for T in Ts]
            store.setdefault((nodes, sort), {})[cfg.label] = dict(
                errors=np.concatenate([T - exact for T in Ts]).astype(np.float32),
                l2=np.concatenate(l2).astype(np.float32), flicker=np.concatenate(flicker).astype(np.float32),
                flicker_l2=np.concatenate(flicker_l2).astype(np.float32))
            fl = np.stack(flicker)
            rows.append(dict(scene=name, config=cfg.label, seed=seed, light=light, method="avsm", param=nodes,
                             sorted=sort, order="depth" if sort else "random",
                             rmse=float(np.mean([e["rmse"] for e in errs])),
                             max_error=float(np.max([e["max_error"] for e in errs])),
                             signed_mean=float(np.mean([e["mean_error"] for e in errs])),
                             leak_share=float(np.mean([e["leak_fraction"] for e in errs])),
                             depth_l2=float(np.sqrt(np.mean(np.concatenate(l2) ** 2))),
                             flicker_rms=float(np.sqrt(np.mean(fl ** 2))), flicker_max=float(np.max(fl)),
                             flicker_texels_over_1pct=float(np.mean(fl > 0.01)),
                             flicker_depth_l2=float(np.sqrt(np.mean(np.concatenate(flicker_l2) ** 2))),
                             bytes=reps[0].nbytes_sparse_per_texel, bytes_dense=reps[0].nbytes_per_texel))
    return rows


def flicker_claim(a: tuple, b: tuple, configs, blocks: tuple, n_boot: int = 1000) -> dict:
    """"a flickers less than b": ``stat(a) - stat(b) < 0`` with :func:`avsm_dr.stats.claim`
    (``compare='difference'``, RMS) on both metrics.  a, b: (receiver flicker, per-texel
    flicker L2), each a list over ``configs``; blocks: (receiver tiles, texel tiles), lists
    over ``configs``.  ``metric_dependent``: both intervals exclude 0 on opposite sides."""
    from avsm_dr import stats
    metrics = {}
    for i, name in enumerate(("receiver_rmse", "depth_l2")):
        r = stats.claim(a[i], b[i], "rmse", "difference", configs=configs, n_boot=n_boot, blocks_by_config=blocks[i])
        metrics[name] = dict(estimate=r["estimate"], low=r["low"], high=r["high"], n_configs=r["n_configs"],
                             holds_pooled=r["holds_pooled"],
                             holds_in_every_configuration=r["holds_in_every_configuration"]
                             if r["n_configs"] >= MIN_EVERY else None,
                             per_config={pc["config"]: [pc["estimate"], pc["low"], pc["high"]]
                                         for pc in r["per_config"]})
    rm = metrics["receiver_rmse"]
    return dict(estimate=rm["estimate"], low=rm["low"], high=rm["high"], n_configs=rm["n_configs"],
                indicative=rm["n_configs"] < MIN_CONFIDENT, interval_unit="configuration",
                holds_in_every_configuration=rm["holds_in_every_configuration"], metrics=metrics,
                metric_dependent=metric_dependent(rm, metrics["depth_l2"], below=0.0))


def _claims(store: dict, configs: list[str], nodes, n_boot: int) -> dict:
    """Per N: ``sorted_below_unsorted`` and ``sorting_removes_flicker`` (module docstring)."""
    out = {}
    tiles = store["tiles"]
    for n in nodes:
        s, u = store[(n, True)], store[(n, False)]
        pick = lambda d, key: [d[c][key] for c in configs]  # noqa: E731
        sides = {"a": side(pick(s, "errors")), "b": side(pick(u, "errors"))}
        common = dict(order="depth / random", sides=sides)
        err = claim((pick(s, "errors"), pick(u, "errors")), (pick(s, "l2"), pick(u, "l2")), configs,
                    ([tiles[c]["errors"][0] for c in configs], [tiles[c]["errors"][1] for c in configs]), n_boot)
        fl = flicker_claim((pick(s, "flicker"), pick(s, "flicker_l2")), (pick(u, "flicker"), pick(u, "flicker_l2")),
                           configs, ([tiles[c]["flicker"][0] for c in configs],
                                     [tiles[c]["flicker"][1] for c in configs]), n_boot)
        out[f"N={n}"] = {
            "sorted_below_unsorted": dict(err, statement=f"AVSM-{n} built sorted has lower error than unsorted "
                                                         "(ratio < 1)", **common),
            "sorting_removes_flicker": dict(fl, statement=f"AVSM-{n} built sorted flickers less than unsorted "
                                                          "(difference < 0)", **common)}
    return out


def _compute(res, params: dict) -> dict:
    """AVSM's error and frame-to-frame flicker over shuffled insertion orders, sorted or not,
    per configuration, and the claims over configurations."""
    names = params["scenes"]
    rows, found = [], {}
    for name in names:
        store: dict = {}
        for ci in tqdm(range(len(params["configs"])), desc=f"ordering {name}", unit="config"):
            rows += _config(name, ci, params, store)
        configs = list(store["tiles"])
        found[name] = dict(n_configs=len(configs), configs=configs, indicative=len(configs) < MIN_CONFIDENT,
                           claims=_claims(store, configs, params["nodes"], params["n_boot"]))
    write_data(res, dict(rows=rows, findings=found))          # before the figures
    _plot(res, rows, names)
    def mean_flicker(*key):
        return float(np.mean([r["flicker_rms"] for r in rows if (r["scene"], r["param"], r["sorted"]) == key]))

    summary = {f"{name}_N{n}_{'sorted' if sort else 'unsorted'}_flicker_rms": mean_flicker(name, n, sort)
               for name in names for n in params["nodes"] for sort in (False, True)}
    summary["n_configs"] = len(params["configs"])
    return dict(rows=rows, findings=found, summary=summary)


def _plot(res, rows: list[dict], names):
    """Mean over configurations (bars: min to max) against N, sorted and unsorted, per scene:
    error and flicker, each at the receivers and in depth L2.  One colour and marker per scene,
    sorted dashed; a flicker that is 0 in every configuration is not drawn (a log axis), but
    said in the panel."""
    import matplotlib
    matplotlib.use("Agg")
    from . import _plotstyle as plotstyle
    panels = (("rmse", "RMSE of T vs exact (receivers)"), ("depth_l2", "depth L2 of T vs exact"),
              ("flicker_rms", "flicker RMS of T (receivers)"), ("flicker_depth_l2", "flicker depth L2 of T"))
    colours = [plotstyle.PALETTE[c] for c in ("rose", "indigo", "teal", "sand", "wine", "olive", "cyan", "purple")]
    markers = ("o", "s", "^", "D", "v", "P", "<", ">")
    with plotstyle.context():
        fig, axes = plotstyle.grid(1, len(panels), panel=(3.0, 2.6), sharex=True, sharey=False)
        zero = {col: True for col, _ in panels}
        for i, name in enumerate(names):
            for sort, ls in ((False, "-"), (True, "--")):
                rs = [r for r in rows if r["scene"] == name and r["sorted"] == sort]
                ns = sorted({r["param"] for r in rs})
                for ax, (col, lab) in zip(axes[0], panels):
                    v = [np.array([r[col] for r in rs if r["param"] == n]) for n in ns]
                    if col.startswith("flicker") and sort and all(np.all(x == 0) for x in v):
                        continue
                    zero[col] &= not sort
                    v = [np.maximum(x, 1e-7) for x in v]
                    y = np.array([x.mean() for x in v])
                    ax.errorbar(ns, y, yerr=[y - [x.min() for x in v], [x.max() for x in v] - y],
                                marker=markers[i % len(markers)], color=colours[i % len(colours)], linestyle=ls,
                                capsize=2, label=f"{name} {'sorted' if sort else 'unsorted'}")
                    ax.set_yscale("log")
                    ax.set_ylabel(lab)
                    ax.set_xlabel("AVSM nodes N")
                    ax.set_xticks(ns)
        for ax, (col, _) in zip(axes[0], panels):
            plotstyle.log_ticks(ax)           # the default labels minor ticks too (overlap below 2 decades)
            if col.startswith("flicker") and zero[col]:
                ax.set_title("sorted: 0 in every configuration", fontsize=7)
        n = len({r["config"] for r in rows})
        fig.suptitle(f"mean over {n} configurations (bars: min to max)", fontsize=9)
        plotstyle.legend_below(fig, axes, ncol=3)
        res.save_figure(fig, "ordering.png")


def redraw(res, rows: list[dict]) -> None:
    """``ordering.png`` from rows read back from a table (a run's ``data.csv`` or the research
    page's ``configs.csv``, typed by :func:`experiments._replot.typed`), scenes in row order:
    ``python -m experiments._replot ordering TABLE --out DIR``."""
    _plot(res, rows, list(dict.fromkeys(r["scene"] for r in rows)))


def _headline(s: dict) -> list[str]:
    """Per scene: the flicker RMS of AVSM-N built unsorted, against sorted (0: no flicker),
    means over the configurations."""
    import re
    groups: dict = {}
    for key, v in s.items():
        m = re.match(r"(.+)_N(\d+)_(sorted|unsorted)_flicker_rms$", key)
        if m:
            groups.setdefault(m[1], {}).setdefault(int(m[2]), {})[m[3]] = v
    tail = f" ({s['n_configs']} configurations)" if s.get("n_configs") else ""
    return [line for scene, per_n in groups.items() for line in wrap(
        f"{scene}, flicker RMS unsorted / sorted{tail}: ",
        [f"N={n} {num(d.get('unsorted'))} / {num(d.get('sorted'))}" for n, d in sorted(per_n.items())])]


STUDY = Study("ordering", "Effect of insertion order on AVSM: error and flicker, sorted against unsorted",
              REPRODUCES, FULL, QUICK, _compute, writes=("data.csv", "findings.json"), headline=_headline)
run = STUDY.run

"""A depth warp learned by gradient descent, tested on held-out scenes (a new result: no paper
reports it).

The linear kinds (OSM, FOM, moments) spend their resolution uniformly over the global depth
range ``[near, far]`` of the map.  :class:`~experiments.learned_warp.depth_warp.DepthWarp` re-spends it with a
monotone piecewise-linear warp ``w`` of the normalised depth (``K`` knot intervals, softmax
increments), shared by every texel and every scene; the warp itself is ``K`` floats per
map, so the bytes per texel do not change (comparisons are at equal bytes).

Per kind (at its size, the same for every warp):

* **training** (Adam, :class:`~avsm_dr.reconstruction.ProjectedAdam` without projection):
  minimise the mean over training scenes of the mean squared error of ``T`` against the
  exact curve at receivers **uniform in depth per texel** (``R`` stratified depths over each
  non-empty texel's content ``[first entry, last exit]``, point lookups), starting from
  the identity warp; the loss of every iteration is recorded;
* **baselines**: no warp (the identity: the kind as registered) and the logarithmic warp
  ``ln(1 + (r - 1) u) / ln r`` (:func:`~experiments.learned_warp.depth_warp.log_values`, the form of Muenstermann
  et al. 2018, sec. 5), its ratio ``r`` the best of ``LOG_RATIOS`` on the training set;
* **evaluation**: RMSE at other receivers (another seed, same rule) on the training scenes
  and on held-out scenes: the same generator (procedural plume) with other seeds and a light
  not seen in training, the simulated plume (other smoke), and other scene types (hair in
  smoke, three columns, particles) to see whether a warp learned on smoke transfers.

  Where the kind has its own exact log warp (the moments kind's ``warp='log'``), it is a
  third baseline (``kind_log``).
* **the kind at its preset** (``preset``, :func:`preset_params`): no warp, the registry's
  best-practice configuration (``describe(kind)['preset']``: OSM's and FOM's per-texel depth
  range, 2 floats per texel) with the size lowered to the same bytes per texel (OSM 6 slices
  + range = 32 B, FOM 2 harmonics + range = 28 B); absent where no size fits (moments: 4
  moments at the preset take 28 B, not 20).

Two metrics, both against the exact curve of the same segments (the
compression error: the warp changes nothing else):

* ``depth_l2``: the RMSE at receivers uniform in depth over each non-empty texel's content
  (the stratified form of :func:`avsm_dr.evaluation.depth_l2`, point lookups), the metric the
  warp is trained on;
* ``receiver_rmse``: the RMSE at in-volume receivers by contribution
  (:func:`avsm_dr.receivers.in_volume`, ``n_volume`` of them, seeded by the configuration),
  bilinear lookups through the capture (:class:`avsm_dr.evaluation.Probe`), the warped kinds
  looked up at ``w(z)``; with its signed mean (``signed_mean``, > 0: light leaking) and leak
  share (``leak_share``: error > 0.02, :func:`avsm_dr.metrics.error_stats`).

Captures are front to back (``order='depth'``; the linear kinds do not depend on the order),
recorded per row (``order``), with ``bytes`` (the sparse layout of the kind at the row's
size on that scene; the warp adds none) and ``bytes_dense`` (= ``bytes_per_texel``).
Every interval is over configurations, none within a map, so none needs the 8 x 8 texel
block bootstrap used for within-map intervals.

Second part, AVSM's removal metric (:mod:`.avsm`): the blend
``(1 - beta) area + beta depth-gap`` learned through a softmin surrogate of the removal
(temperature annealed), then evaluated with the hard algorithm (the avsm kind's own steps,
equal to it at ``beta = 0``) against the paper's metric (``beta = 0``), AVSM-8 at 64 bytes;
a sweep of the hard algorithm over ``beta`` on the training scenes checks the surrogate.

``findings.json``: per kind and held-out group, per metric (:data:`METRICS`) the mean per
method and the ratio learned / each baseline (means of per-configuration values) with a
paired bootstrap 95 % interval whose unit is the configuration (scene seed x light:
:func:`avsm_dr.stats.paired_bootstrap` over the group's configurations, statistic 'mean')
and the number of configurations where the learned warp is the smaller;
``metric_dependent`` when the two metrics' intervals lie entirely on opposite sides of 1
(the rule of ``error_curves``); ``indicative`` (fewer than :data:`MIN_CONFIGS`
configurations); ``avsm_metric`` likewise for the learned beta vs the paper's metric.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
from tqdm import tqdm

from avsm_dr import allows, build, describe
from avsm_dr.stats import paired_bootstrap
from .._headline import interval
from .._study import Study, write_data
from .._two_metric import metric_dependent
from .depth_warp import DepthWarp, log_values

#: What this study reproduces (a paper's figure or table, or the guide's section).
REPRODUCES = (
    'A monotone depth warp learned by gradient descent for OSM, FOM and moments, trained on '
    'procedural smoke and tested on held-out seeds, a new light and other scene types (no paper '
    'reports it).'
)


#: (kind, parameters) learned for, about 20-36 bytes per texel each (float32).
KINDS = [("osm", {"slices": 8}), ("fom", {"harmonics": 3}), ("moments", {})]
#: Fewer configurations than this make a group's intervals ``indicative``.
MIN_CONFIGS = 4
#: The two metrics of every row and finding (module docstring).
METRICS = ("depth_l2", "receiver_rmse")
#: Ratios tried for the logarithmic baseline (the best on the training set is kept).
LOG_RATIOS = (3.0, 10.0, 30.0, 100.0)
#: Light directions as (azimuth, elevation) degrees; the last is never used in training.
LIGHTS = [(-165.0, 17.0), (-140.0, 30.0), (170.0, 10.0)]
#: AVSM removal-metric learning (see :mod:`.avsm`): nodes, Adam step on
#: phi, finite-difference step, temperature (first, last), start phi (beta = 0.2).
METRIC = dict(metric_nodes=8, metric_lr=0.3, metric_fd=0.05, metric_tau=[0.1, 0.01],
              metric_phi0=float(np.log(0.2 / 0.8)))
_COMMON = dict(kinds=[[k, p] for k, p in KINDS], log_ratios=list(LOG_RATIOS), lights=LIGHTS,
               loss_receivers="uniform in depth per non-empty texel (stratified), point lookups")

#: The spot-light configuration's light name: :func:`avsm_dr.evaluation.light_variants`
#: spot light of the scene lit from the held-out direction ``LIGHTS[2]`` (as in error_curves,
#: where 'spot' is the spot light of a scene's directional light); never used in training.
SPOT = "spot"
#: Configurations (seed, light) of each held-out scene type: error_curves' layout of 10, four
#: seeds with two directional lights and the spot light with the first two.
HELD_LAYOUT = [(s, li) for s in range(4) for li in (0, 2)] + [(s, SPOT) for s in range(2)]


def _held(group: str, name: str, layout=HELD_LAYOUT) -> list[tuple]:
    """(group, scene, seed, light) of every configuration of ``layout``."""
    return [(group, name, s, li) for s, li in layout]


#: Parameters of the full and the quick run; train / held-out: lists of (group, scene, seed,
#: light: an index into LIGHTS or SPOT).  Held out: 10 configurations per group, a spot light
#: among them; the new plume seeds keep to lights unseen in training (LIGHTS[2] and the spot).
FULL = dict(train=[("smoke", "plume", s, li) for s in (0, 1, 2, 3) for li in (0, 1)],
            held=_held("smoke_new_seeds", "plume", [(s, 2) for s in range(10, 18)] + [(10, SPOT), (11, SPOT)])
            + _held("simulated_plume", "simulated_plume") + _held("hair_and_smoke", "hair_and_smoke")
            + _held("three_columns", "three_columns") + _held("particles", "particles"),
            size=20, resolution=64, knots=16, iterations=80, lr=0.05, receivers_per_texel=8, n_volume=2048, **METRIC,
            metric_iterations=15, metric_sweep=[0.0, 0.003, 0.01, 0.03, 0.1, 0.3, 0.6, 0.9], **_COMMON)
QUICK = dict(train=[("smoke", "plume", s, 0) for s in (0, 1)],
             held=[("smoke_new_seeds", "plume", 10, 2), ("smoke_new_seeds", "plume", 11, SPOT)]
             + [("hair_and_smoke", "hair_and_smoke", s, 0) for s in (0, 1)],
             size=10, resolution=64, knots=8, iterations=12, lr=0.1, receivers_per_texel=4, n_volume=512, **METRIC,
             metric_iterations=3, metric_sweep=[], **_COMMON)


class SceneData:
    """One captured scene: segments, training and evaluation receivers (uniform in depth
    per non-empty texel, stratified) and the exact T at both; in-volume receivers by
    contribution (:attr:`probe`, seeded by the scene seed) and the exact curve's bilinear T
    there (:attr:`exact_receivers`)."""

    def __init__(self, group, name, seed, light, P):
        from avsm_dr import builtin_scenes, capture, receivers
        from avsm_dr.evaluation import Probe
        from avsm_dr.reconstruction import light_from_angles
        from avsm_dr.evaluation import light_variants
        kw = {} if name == "particles" else {"size": P["size"]}
        direction = LIGHTS[2 if light == SPOT else light]
        scene = getattr(builtin_scenes, name)(seed=seed, light=light_from_angles(*direction), **kw)
        if light == SPOT:
            scene = dataclasses.replace(scene, light=light_variants(scene)[SPOT])
        self.group, self.name, self.seed, self.light = group, name, seed, light
        cap = capture(scene, resolution=P["resolution"], order="depth")
        self.seg = cap.segments
        exact = build("exact", self.seg)
        # the truth at the points is not used (errors are against the exact curve): ones skip its quadrature
        points = receivers.in_volume(scene, P["n_volume"], seed=seed)
        self.probe = Probe(cap, scene, points, n_decomp=0, truth_at_points=np.ones(points.shape[0]))
        self.exact_receivers = self.probe.lookup(exact)
        lo, hi = self.seg.texel_bounds()
        tex = np.flatnonzero((self.seg.counts > 0) & (hi > lo))
        R = P["receivers_per_texel"]
        self.sets = {}
        for key, rs in (("train", seed), ("eval", seed + 1000)):
            rng = np.random.default_rng(rs)
            t = np.repeat(tex, R)
            z = lo[t] + (hi[t] - lo[t]) * (np.tile(np.arange(R), tex.size) + rng.random(t.size)) / R
            self.sets[key] = (t, z, exact.eval(t, z))

    def label(self) -> str:
        """scene/seed/light."""
        return f"{self.name}/s{self.seed}/l{self.light}"


def kind_log_params(kind, params) -> dict | None:
    """The kind's own logarithmic depth warp (``warp='log'``, the moments kind's option
    when it has one: Muenstermann et al. 2018, sec. 5), or None."""
    return dict(params, warp="log") if "warp" in describe(kind)["params"] else None


def preset_params(kind, params, seg) -> dict | None:
    """``kind`` at its registry preset (``describe(kind)['preset']``) with its size parameter
    lowered until ``nbytes_per_texel`` on ``seg`` equals that of ``params`` (equal bytes), or
    None when no size does (e.g. moments: the per-texel range adds 8 B to the fewest moments)."""
    d = describe(kind)
    target = build(kind, seg, **params).nbytes_per_texel
    base = {**params, **d["preset"]}
    size = d["size"]
    start = base.get(size, d["params"][size]["default"])
    for n in range(int(start), int(d["params"][size]["min"] or 1) - 1, -1):
        p = {**base, size: n}
        if not allows(kind, p):
            continue
        got = build(kind, seg, **p).nbytes_per_texel
        if got == target:
            return p
        if got < target:
            return None
    return None


def _warped_eval(data: SceneData, kind, params, theta, key):
    """T of ``kind`` built on the warped segments at the warped receivers (AD kept);
    ``theta`` None: no warp; a dict: the kind's own parameters instead (no warp here)."""
    t, z, _ = data.sets[key]
    if theta is None or isinstance(theta, dict):
        return build(kind, data.seg, **(theta or params)).eval(t, z)
    w = DepthWarp.for_segments(data.seg, theta=theta)
    return build(kind, w.segments(data.seg), near=0.0, far=1.0, **params).eval(t, w(z))


class _Warped:
    """``rep`` looked up at warped depths: ``eval(texel, z) = rep.eval(texel, warp(z))``."""

    def __init__(self, rep, warp):
        self.rep, self.warp = rep, warp

    def eval(self, texel, depth):
        return self.rep.eval(texel, self.warp(np.asarray(depth, np.float64)))


def _receiver_rep(data: SceneData, kind, params, theta):
    """What :meth:`avsm_dr.evaluation.Probe.lookup` evaluates for ``kind`` under ``theta``
    (as in :func:`_warped_eval`)."""
    if theta is None or isinstance(theta, dict):
        return build(kind, data.seg, **(theta or params))
    w = DepthWarp.for_segments(data.seg, theta=theta)
    return _Warped(build(kind, w.segments(data.seg), near=0.0, far=1.0, **params), w)


def receiver_errors(data: SceneData, rep) -> dict:
    """``receiver_rmse``, ``signed_mean`` and ``leak_share`` of ``rep`` (anything with
    ``eval(texel, depth)`` on ``data.seg``'s texels) at the in-volume receivers, against the
    exact curve's bilinear lookup there."""
    from avsm_dr.metrics import error_stats
    s = error_stats(data.probe.lookup(rep), data.exact_receivers)
    return {"receiver_rmse": s["rmse"], "signed_mean": s["mean_error"], "leak_share": s["leak_fraction"]}


def _mse(data, kind, params, theta, key):
    import drjit as dr
    T = _warped_eval(data, kind, params, theta, key)
    return dr.mean(dr.square(T - data.sets[key][2]))


def errors(data, kind, params, theta, key="eval") -> dict:
    """``depth_l2`` (RMSE uniform in depth) and max |error| there of ``kind`` under the warp
    ``theta`` (None: no warp)."""
    import drjit as dr
    T = np.asarray(dr.detach(_warped_eval(data, kind, params, theta, key)), np.float64)
    e = T - np.asarray(data.sets[key][2], np.float64)
    return {"depth_l2": float(np.sqrt(np.mean(e * e))), "max_error": float(np.abs(e).max())}


def train(scenes, kind, params, P, progress=None):
    """Learn the logits (K,) from the identity; returns (theta as NumPy, loss per iteration)."""
    import drjit as dr
    from avsm_dr import backend
    from avsm_dr.reconstruction import ProjectedAdam
    Float = backend.types().Float
    opt = ProjectedAdam(lr=P["lr"], lower=None)
    opt["theta"] = Float(np.zeros(P["knots"]))
    losses = []
    for _ in range(P["iterations"]):
        L = sum((_mse(d, kind, params, opt["theta"], "train") for d in scenes), Float(0)) / len(scenes)
        dr.backward(L)
        losses.append(float(np.asarray(dr.detach(L))[0]))
        opt.step()
        if progress is not None:
            progress.update(1)
    return np.asarray(dr.detach(opt["theta"]), np.float64), losses


def _mean_rmse(scenes, kind, params, theta, key):
    return float(np.mean([errors(d, kind, params, theta, key)["depth_l2"] for d in scenes]))


def _compute(res, P: dict) -> dict:
    """The warps trained per kind, their errors on the training and held-out scenes, and the
    AVSM removal metric."""
    train_s = [SceneData(*s, P) for s in tqdm(P["train"], desc="learned_warp: train scenes", unit="scene")]
    held_s = [SceneData(*s, P) for s in tqdm(P["held"], desc="learned_warp: held-out scenes", unit="scene")]
    rows, loss_rows, warp_rows, warps = [], [], [], {}
    bar = tqdm(total=len(KINDS) * P["iterations"], desc="learned_warp: Adam", unit="it")
    for kind, params in KINDS:
        # ---- baselines: identity (no warp) and the best log ratio on the training set
        best_r = min(LOG_RATIOS, key=lambda r: _mean_rmse(
            train_s, kind, params, DepthWarp.logits_for(log_values(P["knots"], r)), "train"))
        theta_log = DepthWarp.logits_for(log_values(P["knots"], best_r))
        theta, losses = train(train_s, kind, params, P, bar)
        warps[kind] = {"identity": None, "log": theta_log, "learned": theta}
        if (own := kind_log_params(kind, params)) is not None:
            warps[kind]["kind_log"] = own          # the kind's own exact log warp (no knots)
        if (pre := preset_params(kind, params, train_s[0].seg)) is not None:
            warps[kind]["preset"] = pre            # the kind at its preset, at equal bytes (no warp)
        loss_rows += [{"kind": kind, "iteration": i, "train_mse": v} for i, v in enumerate(losses)]
        for method, th in (("log", theta_log), ("learned", theta)):
            for k, v in enumerate(DepthWarp(0.0, 1.0, theta=th, dtype="float64").knot_values()):
                warp_rows.append({"kind": kind, "method": method, "knot": k, "u": k / P["knots"], "w": v,
                                  "log_ratio": best_r if method == "log" else ""})
        bpt = build(kind, train_s[0].seg, **params).nbytes_per_texel
        for split, scenes in (("train", train_s), ("held_out", held_s)):
            for d in scenes:
                sparse = float(build(kind, d.seg, **params).nbytes_sparse_per_texel)    # the warp stores no more
                for method, th in warps[kind].items():
                    rows.append(dict(split=split, group=d.group, scene=d.name, seed=d.seed, light=d.light, kind=kind,
                                     params=json.dumps(th if isinstance(th, dict) else params),
                                     bytes_per_texel=bpt, method=method,
                                     log_ratio=best_r if method == "log" else "", knots=P["knots"],
                                     **errors(d, kind, params, th),
                                     **receiver_errors(d, _receiver_rep(d, kind, params, th)),
                                     order="depth", bytes=sparse, bytes_dense=bpt))
    bar.close()
    metric_rows, metric_loss, sweep = _avsm_metric(train_s, held_s, P)
    summary = findings(rows)
    summary["avsm_metric"] = dict(findings(metric_rows)["avsm"], nodes=P["metric_nodes"],
                                  beta_learned=metric_loss[-1]["beta_next"],
                                  beta_best_in_sweep=min(sweep, key=lambda r: r["train_rmse"])["beta"]
                                  if sweep else None,
                                  evaluated_with="the hard algorithm (equal to the avsm kind at beta = 0)")
    tables = {"losses.csv": loss_rows, "warps.csv": warp_rows, "avsm_metric.csv": metric_rows,
              "avsm_metric_loss.csv": metric_loss, **({"avsm_metric_sweep.csv": sweep} if sweep else {})}
    write_data(res, dict(rows=rows, tables=tables, findings=summary))   # before the figures
    from .plots import plot, plot_metric
    plot(res, rows, loss_rows, warp_rows)
    plot_metric(res, metric_loss, sweep)
    return dict(rows=rows, tables=tables, findings=summary, summary=summary)


def _avsm_metric(train_s, held_s, P):
    """Learn the blend beta of AVSM's removal metric on the surrogate, sweep the hard
    algorithm over beta on the training scenes, evaluate paper (beta = 0) vs learned."""
    from .avsm import NodeLists, rmse, sigmoid, train_metric
    N = P["metric_nodes"]
    bar = tqdm(total=P["metric_iterations"], desc="learned_warp: AVSM metric", unit="it")
    phi, loss_rows = train_metric(train_s, N, P, bar)
    bar.close()
    beta = float(sigmoid(phi))
    loss_rows[-1]["beta_next"] = beta
    sweep = [{"beta": b, "train_rmse": float(np.mean([rmse(d, N, b) for d in train_s]))}
             for b in tqdm(P["metric_sweep"], desc="learned_warp: AVSM metric sweep", unit="beta")]
    rows = []
    for split, scenes in (("train", train_s), ("held_out", held_s)):
        for d in scenes:
            for method, b in (("paper", 0.0), ("learned", beta)):
                rows.append(dict(split=split, group=d.group, scene=d.name, seed=d.seed,
                                 light=d.light, kind="avsm", nodes=N, bytes_per_texel=2 * N * d.seg.itemsize,
                                 method=method, beta=b, depth_l2=rmse(d, N, b),
                                 **receiver_errors(d, NodeLists(d.seg, N, b)), order="depth",
                                 bytes=float(build("avsm", d.seg, nodes=N).nbytes_sparse_per_texel),
                                 bytes_dense=2 * N * d.seg.itemsize))
    return rows, loss_rows, sweep


def findings(rows) -> dict:
    """Per kind and group (train, each held-out group, all held-out), per metric of
    :data:`METRICS` present in the rows: the mean per method (``<method>_<metric>``) and
    ``learned_over_<method>`` for every other method (identity, log, kind_log and preset for
    the warps, the paper's metric for AVSM): per metric the ratio of means with a paired
    bootstrap 95 % interval over the group's configurations (needs >= 2) and the
    configurations where learned is the smaller; ``metric_dependent`` when the two metrics'
    intervals lie entirely on opposite sides of 1.  ``n_configs``: the group's configurations
    (scene seed x light: one ``learned`` row each); ``indicative``: fewer than
    :data:`MIN_CONFIGS` of them."""
    out = {}
    kinds = list(dict.fromkeys(r["kind"] for r in rows))
    metrics = [m for m in METRICS if rows and m in rows[0]]
    for kind in kinds:
        mine = [r for r in rows if r["kind"] == kind]
        groups = {"train": [r for r in mine if r["split"] == "train"],
                  "held_out_all": [r for r in mine if r["split"] == "held_out"]}
        other = [r for r in mine if r["split"] == "held_out" and r["group"] not in ("smoke_new_seeds",
                                                                                      "simulated_plume")]
        if other:
            groups["held_out_other_types"] = other
        for g in dict.fromkeys(r["group"] for r in mine if r["split"] == "held_out"):
            groups[g] = [r for r in mine if r["split"] == "held_out" and r["group"] == g]
        d = out.setdefault(kind, {"bytes_per_texel": mine[0]["bytes_per_texel"]})
        methods = list(dict.fromkeys(r["method"] for r in mine))
        for g, rs in ((g, rs) for g, rs in groups.items() if rs):
            n = sum(1 for r in rs if r["method"] == "learned")          # one row per configuration
            e = {"n_configs": n, "indicative": n < MIN_CONFIGS}
            by = {(m, k): np.array([r[k] for r in rs if r["method"] == m], np.float64)
                  for m in methods for k in metrics}
            e.update({f"{m}_{k}": float(v.mean()) for (m, k), v in by.items()})
            for base in (m for m in methods if m != "learned"):
                if n < 2:
                    continue
                c = {}
                for k in metrics:
                    ci = paired_bootstrap(by["learned", k], by[base, k], statistic="mean", compare="ratio")
                    c[k] = {"ratio": ci["estimate"], "low": ci["low"], "high": ci["high"],
                            "p_learned_smaller": ci["p_a_smaller"],
                            "learned_smaller_in": int(np.sum(by["learned", k] < by[base, k]))}
                c["metric_dependent"] = len(c) == 2 and metric_dependent(*c.values())
                e[f"learned_over_{base}"] = c
            d[g] = e
    return out


__all__ = ["run", "findings", "metric_dependent", "train", "errors", "receiver_errors", "kind_log_params",
           "preset_params", "SceneData", "KINDS", "LOG_RATIOS", "LIGHTS", "METRIC", "METRICS", "MIN_CONFIGS"]

def _headline(s: dict) -> list[str]:
    """Per kind and metric on the held-out scenes: the learned warp's value over each
    baseline's (ratio [interval]), the baselines whose direction is metric-dependent; the
    learned AVSM metric over the paper's likewise."""
    out = []
    for kind, d in s.items():
        h = d.get("held_out_all", {})
        cmp = {k[len("learned_over_"):]: v for k, v in h.items() if k.startswith("learned_over_")}
        where = f" at {d['bytes_per_texel']} B/texel" if "bytes_per_texel" in d else ""
        name = f"avsm-{d['nodes']} metric" if kind == "avsm_metric" and "nodes" in d else kind
        for metric, what in (("depth_l2", "depth-uniform L2"), ("receiver_rmse", "receiver RMSE")):
            ratios = [f"{b} {interval(v[metric])}" for b, v in cmp.items() if metric in v]
            if ratios:
                out.append(f"{name}{where}, {h.get('n_configs', '?')} held-out configurations, learned {what} over "
                           + ", ".join(ratios))
        dep = [b for b, v in cmp.items() if v.get("metric_dependent")]
        if dep:
            out.append(f"{name}: metric-dependent against {', '.join(dep)}")
    return out


STUDY = Study("learned_warp", "A depth warp learned by gradient descent, tested on held-out scenes", REPRODUCES,
              FULL, QUICK, _compute,
              writes=("data.csv (one row per scene, kind and warp)", "losses.csv", "warps.csv", "avsm_metric.csv",
                      "avsm_metric_loss.csv", "avsm_metric_sweep.csv (full run)", "findings.json"), headline=_headline)
run = STUDY.run

"""A memory budget instead of a node count: adaptive AVSM (``avsm_adaptive``: per-texel
node counts by complexity water-filling, CSR storage) against fixed-N AVSM, DSM and the
best breakpoint subset (``optimal``, fixed N) at equal total bytes, per built-in scene
over seeds and lights.

Per configuration (scene x :class:`avsm_dr.evaluation.Configuration`: a seed and a light
of :func:`avsm_dr.evaluation.light_variants`, the scene's directional light ``dir_a``, its
25-degree tilt ``dir_b`` or the ``spot`` light on its axis; full mode: error_curves' ten,
4 seeds x both directional lights and 2 seeds x the spot light) and per node count N of
fixed AVSM (``bytes = 2 N itemsize`` per texel, float32 captures: 8 N):

* ``avsm``: AVSM-N, N in ``nodes`` (up to 64: fixed AVSM's error-vs-bytes curve);
  at each budget N in ``budgets``: ``adaptive``: ``avsm_adaptive`` with
  ``bytes_per_texel = 8 N`` (stored bytes, offsets included, at most that);
  ``adaptive_uniform``: the same CSR storage with one node count for every non-empty
  texel (``_score='uniform'``: what skipping empty and small texels alone saves);
  ``adaptive_count``: allocation by the segment count only (``_score='count'``; full
  mode: first configuration of each scene);
* ``dsm``: deep shadow map whose tolerance is searched (regula falsi, Illinois, on log
  bytes against log tolerance in [1e-6, 0.5], :data:`DSM_STEPS` builds) so that its mean
  bytes per texel come closest to 8 N from below;
* ``optimal``: the best N-node breakpoint subset (L2, refitted; offline: N <=
  :data:`OPTIMAL_MAX_N`, and in full mode the first configuration of each scene only).

Errors against the exact curve of the same segments (the compression error: the
allocation changes nothing else): at in-volume receivers
(:func:`avsm_dr.receivers.in_volume`, bilinear lookups through the capture, depths
normalised to [0, 1]: :class:`NormalisedLookup`) the RMSE,
and uniform in depth per texel (:class:`.avsm_gap.UniformObjective`, ``depth_rms``).

Findings (``findings.json``), per scene: the RMSE ratio adaptive / fixed AVSM at equal
bytes per N (paired bootstrap over receivers per configuration, pooled over
configurations by a two-stage bootstrap: :func:`avsm_dr.stats.claim`), likewise adaptive
/ DSM and adaptive / optimal; and **bytes saved at equal error**: per configuration and
budget, the bytes fixed AVSM needs to match adaptive AVSM's error, by linear
interpolation of log error against log bytes between fixed AVSM's neighbouring N (a
budget whose adaptive error lies below fixed AVSM's at the largest N is *censored* and
counted, not interpolated); saving = ``1 - bytes_adaptive / bytes_fixed``, mean over
configurations with a bootstrap interval (:func:`avsm_dr.stats.bootstrap_ci`); the same for
``adaptive_uniform`` separates what compaction alone saves.

Insertion order: AVSM and adaptive AVSM insert each texel's segments in their stored order.
The headline rows (``order`` = ``depth``) are built front to back; the same two are built again
under every other order of ``orders`` (``submission``: the renderer's draw order, captured
again; ``reverse_depth``; ``random``, seeded by the configuration) on the same segments and
receivers, with an ``order`` column (``-`` for DSM and ``optimal``, which do not depend on
it), and ``bytes_saved_at_equal_rmse_by_order`` compares adaptive and fixed AVSM within each
order.

Interpolation: the headline AVSM rows (``interpolation`` = ``linear``) sample the node list
linearly (AVSM's registry preset, ``describe('avsm')['preset']``); its other preset variant,
``interpolation='exp'``, is built again for fixed AVSM-N and adaptive AVSM (``exp`` rows, under every order of
``orders`` like the linear rows, same segments and receivers; ``-`` for DSM and
``optimal``); findings give the exp savings (``bytes_saved_at_equal_rmse_by_order_exp`` per
order), the exp / linear RMSE ratios and adaptive / fixed within exp.

Both metrics: every row carries ``rmse``, ``signed_mean`` and ``leak_share``
(error > 0.02) at the receivers, ``depth_rms`` (the quadrature of :class:`.avsm_gap.UniformObjective`)
and ``depth_l2`` (:func:`avsm_dr.evaluation.depth_l2`, 64 midpoints: the same measure by the
harness), ``bytes`` (sparse) and ``bytes_dense``.  ``findings.json``'s ``claims``
(:func:`claims`) give adaptive / fixed AVSM (linear and exp) and exp / linear AVSM under every
order, adaptive / DSM and adaptive / optimal, each on both metrics with configuration-level
intervals, ``metric_dependent``, ``indicative`` (fewer than :data:`MIN_CONFIDENT`
configurations: always in quick mode) and each side's signed mean and leak share.  Within a
configuration every interval (``claims`` and the ``rmse_ratio_*`` keys) resamples receivers
and texels in 8 x 8 texel tiles.

Bytes of the savings: the **sparse** layout on both sides (``bytes_sparse``,
``nbytes_sparse_per_texel``: an occupancy bit per texel, then fixed AVSM-N's ``8 N`` per
non-empty texel, adaptive AVSM's nodes plus a 4-byte CSR offset per non-empty texel), so the
baseline is sparse fixed-N AVSM and the saving is the allocation's, not the compaction of
empty texels.  ``bytes_saved_at_equal_rmse_dense_baseline`` keeps the former dense baseline
(``bytes_per_texel``, fixed AVSM charged 8 N for empty texels too) for comparison.  The budgets
themselves (and so the RMSE ratios "at equal bytes") are still dense: ``8 N`` bytes per texel.
"""

from __future__ import annotations

import time

import numpy as np
from tqdm import tqdm

from avsm_dr import build
from avsm_dr.builtin_scenes import SCENES as SCENE_REGISTRY
from avsm_dr.evaluation import Configuration
from avsm_dr.stats import bootstrap_ci, claim
from .._common import front_to_back_first
from .._headline import interval, num
from .._study import Option, Study, write_data

#: What this study reproduces (a paper's figure or table, or the guide's section).
REPRODUCES = (
    'A memory budget instead of a node count (a new result: no paper reports it): adaptive '
    'AVSM (per-texel node counts by complexity water-filling, CSR storage) '
    'against fixed-N AVSM, DSM at the same bytes and the best breakpoint subset, per built-in '
    'scene over seeds and lights; bytes saved at equal error.'
)


#: Every built-in scene, registration order: ``error_curves``' list (the registry's names), so findings
#: are reported per content type on each.
SCENES = list(SCENE_REGISTRY.names())
QUICK_SCENES = ["plume"]
#: Bisection steps for the DSM tolerance matching a byte target.
DSM_STEPS = 4
#: Largest N at which the offline optimum is run.
OPTIMAL_MAX_N = 8
#: Methods compared at each byte budget (label, kind, extra parameters).
ADAPTIVE = (("adaptive", {}), ("adaptive_uniform", {"_score": "uniform"}), ("adaptive_count", {"_score": "count"}))

#: Below this many configurations a result is ``indicative`` (``error_curves``' rule).
MIN_CONFIDENT = 4
#: Insertion orders of the AVSM rows (the first is the headline's).
ORDERS = ["depth", "submission", "reverse_depth", "random"]
#: AVSM's interpolations: the headline's and registry preset's (linear) and its other preset variant (exp).
INTERPOLATIONS = ["linear", "exp"]
#: Configurations (seed, light) of the full run: error_curves' ten (4 seeds x both directional
#: lights, 2 seeds x the spot light), :class:`avsm_dr.evaluation.Configuration`.
FULL_CONFIGS = [[s, li] for s in range(4) for li in ("dir_a", "dir_b", "spot") if li != "spot" or s < 2]

#: Parameters of the full and the quick run (quick: the plume, one configuration).
FULL = dict(scenes=SCENES, configs=FULL_CONFIGS, resolution=64, nodes=[2, 4, 8, 16, 32, 64],
            budgets=[2, 4, 8, 16, 32], n_volume=2048, optimal_max_n=OPTIMAL_MAX_N, optimal_first_only=True,
            heat_nodes=4, ablations_everywhere=False, dsm_steps=DSM_STEPS, n_boot=2000, filter="bilinear",
            orders=ORDERS, interpolations=INTERPOLATIONS)
QUICK = dict(FULL, scenes=QUICK_SCENES, configs=[[0, "dir_a"]], nodes=[2, 4, 8, 16, 32], budgets=[2, 4, 8],
             n_volume=512, optimal_max_n=4, optimal_first_only=False, ablations_everywhere=True, dsm_steps=2,
             n_boot=500)


def dsm_at_bytes(seg, target: float, steps: int = DSM_STEPS, cache: dict | None = None):
    """DSM whose ``nbytes_per_texel`` is the largest found <= ``target``: regula falsi
    with the Illinois modification on ``log bytes - log target`` as a function of log
    tolerance, bracketed by [1e-6, 0.5] (``steps`` builds after the two ends, which
    ``cache`` keeps between targets; None when even tolerance 0.5 exceeds the target)."""
    cache = {} if cache is None else cache

    def at(x):
        if x not in cache:
            cache[x] = build("dsm", seg, tolerance=float(np.exp(x)))
        rep = cache[x]
        return rep, float(np.log(rep.nbytes_per_texel) - np.log(target))
    xa, xb = float(np.log(1e-6)), float(np.log(0.5))   # small tolerance: many bytes (f > 0); large: few
    rb, fb = at(xb)
    if fb > 0:
        return None
    best = rb
    ra, fa = at(xa)
    if fa <= 0:
        return ra
    side = 0
    for _ in range(steps):
        x = (xa * fb - xb * fa) / (fb - fa)
        rep, f = at(x)
        if f <= 0:
            if rep.nbytes_per_texel > best.nbytes_per_texel:
                best = rep
            xb, fb = x, f
            if side == -1:
                fa /= 2
            side = -1
        else:
            xa, fa = x, f
            if side == 1:
                fb /= 2
            side = 1
        if abs(f) < 1e-3:
            break
    return best


def bytes_to_match(bytes_fixed, err_fixed, err) -> float:
    """Bytes at which fixed AVSM's error (log-log interpolation between its neighbouring
    budgets, ``err_fixed`` decreasing in ``bytes_fixed``) equals ``err``; NaN when ``err``
    is below its error at the largest budget (censored); the smallest budget when above."""
    order = np.argsort(np.asarray(bytes_fixed, float))
    raw = np.asarray(bytes_fixed, float)[order]
    b = np.log(raw)
    # the best error reached with at most those bytes
    e = np.minimum.accumulate(np.log(np.maximum(np.asarray(err_fixed, float)[order], 1e-300)))
    x = np.log(max(err, 1e-300))
    if x < e[-1]:
        return float("nan")
    if x >= e[0]:
        return float(raw[0])
    k = int(np.flatnonzero(e <= x)[0])                    # first budget reaching the error
    if e[k] == x or e[k] == e[k - 1]:
        return float(raw[k])
    w = (x - e[k - 1]) / (e[k] - e[k - 1])
    return float(np.exp(b[k - 1] + w * (b[k] - b[k - 1])))


class NormalisedLookup:
    """A capture's segments with depths mapped to [0, 1] (``(z - near) / (far - near)``,
    global bounds; float32) and bilinear lookups at fixed receivers through them.

    Every kind sees the same affine image of the content, so errors in T are those of the
    original depths up to float32 rounding; the point: AVSM bakes its far depth into its
    kernels as a literal (measured: a recompile of several seconds per kind and N for
    every new capture), and with far = 1 every configuration reuses the compiled kernels.
    Receivers the map does not cover get T = 1 (:meth:`avsm_dr.capture.Capture.lookup`)."""

    def __init__(self, cap, points):
        from avsm_dr.segments import Segments
        h = cap.segments.numpy()
        self.lo, hi = cap.segments.bounds()
        self.span = (hi - self.lo) if hi > self.lo else 1.0
        self.segments = Segments.from_arrays(h["offsets"], (h["z0"] - self.lo) / self.span,
                                             (h["z1"] - self.lo) / self.span, optical_depth=h["optical_depth"],
                                             dtype="float32")
        self.coords, depth = cap.lookup(points, continuous=True)
        self.inside = cap.covers(points)
        self.depth = np.where(self.inside, (depth - self.lo) / self.span, -1.0)
        od = cap.opaque_depth
        self.opaque = None if od is None else (np.asarray(od, np.float64) - self.lo) / self.span
        self.width, self.height = cap.width, cap.height

    def __call__(self, rep) -> np.ndarray:
        """(K,) float64 bilinear T of ``rep`` (built on :attr:`segments`) at the receivers."""
        from avsm_dr.capture.opaque_map import compose
        T = compose(rep, self.opaque).eval(self.coords, self.depth, filter="bilinear", width=self.width,
                                           height=self.height)
        return np.where(self.inside, np.asarray(T, np.float64), 1.0)


def _configs(P):
    """(scene, Configuration) of every scene x ``P['configs']`` ([seed, light] pairs)."""
    return [(s, Configuration(seed, light)) for s in P["scenes"] for seed, light in P["configs"]]


def key(method: str, order: str = "-", interpolation: str = "-") -> str:
    """The label of a row's errors: ``method``, ``method@order`` for an insertion order other
    than front to back, ``method/exp`` for the exp interpolation."""
    return method + ("" if order in ("-", "depth") else f"@{order}") \
        + ("" if interpolation in ("-", "linear") else f"/{interpolation}")


def _config_rows(name, config, P, rows, errors, heat, l2=None, blocks=None):
    """Rows of one configuration; each row's receiver errors into ``errors[(config, key, N)]``,
    its per-texel depth L2 into ``l2`` (same keys), the 8 x 8 texel tiles of the texels and
    receivers into ``blocks[config]`` / ``blocks[(config, 'receivers')]``."""
    from avsm_dr import capture
    from avsm_dr.evaluation import curve_values, depth_grid, depth_l2
    from avsm_dr.metrics import error_stats
    from ..avsm_gap import UniformObjective
    from .._two_metric import texel_blocks
    seed, light = config.seed, config.light_label
    scene, cap = config.capture(name, P["resolution"])
    points = config.in_volume_receivers(scene, P["n_volume"])
    look = NormalisedLookup(cap, points)
    seg = look.segments
    exact_rep = build("exact", seg)
    exact = look(exact_rep)
    ex_curve = curve_values(exact_rep, seg)              # the depth L2's reference, every order
    obj = UniformObjective(seg)
    cfg = f"{name}/s{seed}/{light}"
    if blocks is not None:
        blocks[cfg] = texel_blocks(depth_grid(seg)[0], cap.width)
        blocks[(cfg, "receivers")] = texel_blocks(cap.lookup(points)[0], cap.width)
    first = [seed, light] == list(P["configs"][0])
    head = dict(scene=name, seed=seed, light=light, config=cfg, resolution=P["resolution"],
                texels=seg.n_texels, nonempty=int(np.count_nonzero(seg.counts)), max_segments=seg.max_count)

    def row(method, n, rep, build_s, budget, order="-", interpolation="-"):
        err = look(rep) - exact
        m = obj.measure(rep)
        errors[(cfg, key(method, order, interpolation), n)] = err
        per_l2 = depth_l2(rep, seg, exact=ex_curve, per_texel=True)
        if l2 is not None:
            l2[(cfg, key(method, order, interpolation), n)] = per_l2
        st = error_stats(err, np.zeros_like(err))
        r = dict(head, method=method, order=order, interpolation=interpolation, nodes=n, budget_bytes_per_texel=budget,
                 bytes_per_texel=rep.nbytes_per_texel,
                 bytes_sparse=rep.nbytes_sparse_per_texel, total_bytes=rep.nbytes_per_texel * seg.n_texels,
                 rmse=float(np.sqrt(np.mean(err ** 2))),
                 max_error=float(np.max(np.abs(err))), depth_rms=m["depth_rms"], build_s=build_s,
                 signed_mean=st["mean_error"], leak_share=st["leak_fraction"],
                 depth_l2=float(np.sqrt(np.mean(per_l2 ** 2))) if per_l2.size else float("nan"),
                 bytes=rep.nbytes_sparse_per_texel, bytes_dense=rep.nbytes_per_texel)
        rows.append(r)
        return r

    def timed_build(kind, segments=seg, **p):
        t0 = time.perf_counter()
        rep = build(kind, segments, **p)
        return rep, time.perf_counter() - t0

    reordered = {}
    for o in P.get("orders", ["depth"])[1:]:
        if o == "submission":
            sub = NormalisedLookup(capture(scene, resolution=P["resolution"], order="submission"), points)
            if not np.array_equal(sub.segments.counts, seg.counts) or (sub.lo, sub.span) != (look.lo, look.span):
                raise RuntimeError(f"{cfg}: the submission-order capture holds other segments")
            reordered[o] = sub.segments
        else:
            reordered[o] = seg.in_order(o, seed=seed if o == "random" else None)

    others = [i for i in P.get("interpolations", ["linear"]) if i != "linear"]
    dsm_cache: dict = {}
    for n in P["nodes"]:
        rep, t = timed_build("avsm", nodes=n)
        target = rep.nbytes_per_texel
        row("avsm", n, rep, t, target, "depth", "linear")
        for o, s_o in reordered.items():
            row("avsm", n, *timed_build("avsm", s_o, nodes=n), target, o, "linear")
        for i in others:                         # the preset's interpolation, under every order
            row("avsm", n, *timed_build("avsm", nodes=n, interpolation=i), target, "depth", i)
            for o, s_o in reordered.items():
                row("avsm", n, *timed_build("avsm", s_o, nodes=n, interpolation=i), target, o, i)
        if n not in P["budgets"]:
            continue
        for label, extra in ADAPTIVE:
            if label == "adaptive_count" and not (first or P["ablations_everywhere"]):
                continue
            rep, t = timed_build("avsm_adaptive", bytes_per_texel=target, **extra)
            row(label, n, rep, t, target, "depth", "linear")
            if label == "adaptive":
                for o, s_o in reordered.items():
                    row(label, n, *timed_build("avsm_adaptive", s_o, bytes_per_texel=target), target, o, "linear")
                for i in others:
                    row(label, n, *timed_build("avsm_adaptive", bytes_per_texel=target, interpolation=i), target,
                        "depth", i)
                    for o, s_o in reordered.items():
                        row(label, n, *timed_build("avsm_adaptive", s_o, bytes_per_texel=target, interpolation=i),
                            target, o, i)
            if label == "adaptive" and first and n == P["heat_nodes"]:
                heat[name] = (rep.allocated.reshape(cap.height, cap.width), target)
        t0 = time.perf_counter()
        dsm = dsm_at_bytes(seg, target, P["dsm_steps"], dsm_cache)
        if dsm is not None:
            row("dsm", n, dsm, time.perf_counter() - t0, target)
        if n <= P["optimal_max_n"] and (first or not P["optimal_first_only"]):
            rep, t = timed_build("optimal", nodes=n)
            row("optimal", n, rep, t, target)


# ==================================================================== findings
def savings(rows, metric: str = "rmse", method: str = "adaptive", key: str = "bytes_sparse") -> dict:
    """Per scene and budget: bytes fixed AVSM needs for ``method``'s error (module
    docstring), ``saving = 1 - bytes_adaptive / bytes_fixed`` per configuration, its mean
    over the uncensored configurations with a 95% bootstrap interval, the censored count
    and, for those, the least saving (against fixed AVSM's largest budget).  ``key``: the
    bytes column of both sides, ``'bytes_sparse'`` (the sparse layout, the headline) or
    ``'bytes_per_texel'`` (dense: fixed AVSM charged 8 N for its empty texels too)."""
    out = {}
    for scene in sorted({r["scene"] for r in rows}):
        cfgs = sorted({r["config"] for r in rows if r["scene"] == scene})
        per_n: dict = {}
        for cfg in cfgs:
            fx = sorted((r for r in rows if r["config"] == cfg and r["method"] == "avsm"), key=lambda r: r["nodes"])
            bf, ef = [r[key] for r in fx], [r[metric] for r in fx]
            for r in rows:
                if r["config"] == cfg and r["method"] == method:
                    need = bytes_to_match(bf, ef, r[metric])
                    # censored: fixed AVSM never reaches the error; the saving is at least
                    # that against its largest budget
                    per_n.setdefault((r["nodes"], r["budget_bytes_per_texel"]), []).append(
                        (1 - r[key] / need, False) if np.isfinite(need)
                        else (1 - r[key] / max(bf), True))
        d = {}
        for (n, budget), vals in sorted(per_n.items()):
            v = np.array([x for x, c in vals if not c])
            cens = [x for x, c in vals if c]
            e = {"budget_bytes_per_texel": budget, "configs": len(vals), "censored": len(cens),
                 "indicative": len(vals) < MIN_CONFIDENT}
            if cens:
                e["censored_saving_at_least"] = float(min(cens))
            if v.size >= 2:
                ci = bootstrap_ci(v, "mean", n_boot=2000)
                e.update(saving=ci["estimate"], low=ci["low"], high=ci["high"])
            elif v.size == 1:
                e.update(saving=float(v[0]))
            d[f"N={n}"] = e
        out[scene] = d
    return out


def ratios(rows, errors, a: str, b: str, n_boot: int, blocks: dict | None = None) -> dict:
    """Per scene and N: RMSE(a) / RMSE(b) at the same receivers, per configuration and
    pooled (:func:`avsm_dr.stats.claim`); within a configuration the receivers are resampled
    in 8 x 8 texel tiles when ``blocks`` has them (:func:`_config_rows`); ``indicative`` below
    :data:`MIN_CONFIDENT` configurations."""
    out = {}
    for scene in sorted({r["scene"] for r in rows}):
        for n in sorted({r["nodes"] for r in rows if r["scene"] == scene}):
            cfgs = sorted({c for (c, m, k) in errors if k == n and m == a and c.startswith(scene + "/")
                           and (c, b, n) in errors})
            if not cfgs:
                continue
            xa = [errors[(c, a, n)] for c in cfgs]
            xb = [errors[(c, b, n)] for c in cfgs]
            if any(np.sqrt(np.mean(x ** 2)) == 0 for x in xb):
                continue
            blk = [(blocks or {}).get((c, "receivers")) for c in cfgs]
            blk = None if any(x is None for x in blk) else blk
            if len(cfgs) == 1:
                from avsm_dr.stats import paired_bootstrap
                r = paired_bootstrap(xa[0], xb[0], "rmse", "ratio", n_boot=n_boot,
                                     blocks=None if blk is None else blk[0])
                e = dict(estimate=r["estimate"], low=r["low"], high=r["high"], n_configs=1)
            else:
                r = claim(xa, xb, "rmse", "ratio", configs=cfgs, n_boot=n_boot, blocks_by_config=blk)
                e = dict(estimate=r["estimate"], low=r["low"], high=r["high"], n_configs=r["n_configs"],
                         below_1_in_every_config=r["holds_in_every_configuration"])
            e["indicative"] = e["n_configs"] < MIN_CONFIDENT
            out.setdefault(scene, {})[f"N={n}"] = e
    return out


def claims(errors: dict, l2: dict, blocks: dict | None = None, n_boot: int = 1000, orders=ORDERS) -> dict:
    """Per scene and N, ``a`` below ``b`` on both metrics (:func:`experiments._two_metric.claim`:
    receiver RMSE and depth L2 ratios, configuration-level intervals, 8 x 8 texel tiles within a
    configuration, ``metric_dependent``, ``indicative``, each side's signed mean and leak share;
    ``preset``: whether each side is at its kind's preset, :func:`_at_preset`):
    adaptive over fixed AVSM, adaptive over fixed and fixed exp over linear AVSM, each under
    every insertion order, and adaptive over DSM and over the optimum (front to back)."""
    from .._two_metric import claim as two_metric
    pairs = []
    for o in orders:
        pairs += [(key("adaptive", o), key("avsm", o), o), (key("adaptive", o, "exp"), key("avsm", o, "exp"), o),
                  (key("avsm", o, "exp"), key("avsm", o), o)]
    pairs += [("adaptive", "dsm", "depth"), ("adaptive", "optimal", "depth")]
    out: dict = {}
    for scene in sorted({c.split("/")[0] for c, _, _ in errors}):
        for n in sorted({k for c, _, k in errors if c.split("/")[0] == scene}):
            for a, b, o in pairs:
                used = sorted(c for c, m, k in errors if k == n and m == a and c.split("/")[0] == scene
                              and all((c, x, n) in store for x in (a, b) for store in (errors, l2))
                              and np.any(errors[(c, b, n)] != 0) and np.any(l2[(c, b, n)] > 0))
                if not used:
                    continue
                pair = lambda store: tuple([store[(c, x, n)] for c in used] for x in (a, b))  # noqa: E731
                tiles = tuple(None if any((blocks or {}).get(k) is None for k in ks) else [blocks[k] for k in ks]
                              for ks in ([(c, "receivers") for c in used], used))
                out.setdefault(scene, {}).setdefault(f"N={n}", {})[f"{a}_over_{b}"] = dict(
                    order=o, interpolation="exp" if "/exp" in b else "exp / linear" if "/exp" in a else "linear",
                    preset={k: _at_preset(m, n) for k, m in (("a", a), ("b", b))},
                    **two_metric(pair(errors), pair(l2), used, tiles, n_boot))
    return out


def _at_preset(label: str, n: int) -> bool:
    """Whether the method of an errors label (:func:`key`) is at its kind's preset
    (``describe(kind)['preset']``: AVSM's is the linear interpolation; adaptive AVSM, DSM and
    optimal have none beyond the settings searched here)."""
    from ..error_curves.findings import preset_differences
    kind = {"avsm": "avsm", "adaptive": "avsm_adaptive", "dsm": "dsm", "optimal": "optimal"}[
        label.split("@")[0].split("/")[0]]
    variant = f"{kind}-{n}" + ("/interpolation=exp" if label.endswith("/exp") else "")
    return not preset_differences(dict(variant=variant, opaque="inline"), False)


def _linear(r) -> bool:
    return r.get("interpolation", "-") in ("-", "linear")


def findings(rows, errors, n_boot: int, l2: dict | None = None, blocks: dict | None = None) -> dict:
    """``findings.json``: savings at equal error (receivers and uniform in depth) and the
    RMSE ratios of adaptive AVSM to the others at equal bytes, front to back with linear
    interpolation; the savings again within each insertion order, with either interpolation;
    with the exp interpolation (AVSM's other preset variant) the savings, adaptive / fixed and exp / linear;
    with ``l2`` the two-metric claims of :func:`claims` under ``claims``."""
    orders = list(dict.fromkeys(r.get("order", "depth") for r in rows if r.get("order", "-") != "-"))
    by_order = {o: savings([r for r in rows if r.get("order", "-") == o and _linear(r)], "rmse") for o in orders}
    by_order_exp = {o: savings(x, "rmse") for o in orders
                    if (x := [r for r in rows if r.get("order", "-") == o and r.get("interpolation") == "exp"])}
    front = [r for r in rows if r.get("order", "-") in ("-", "depth")]
    exp = [r for r in front if r.get("interpolation") == "exp"]
    rows = [r for r in front if _linear(r)]
    out_exp = {}
    if exp:
        out_exp = {
            "bytes_saved_at_equal_rmse_exp": savings(exp, "rmse"),
            "bytes_saved_at_equal_depth_rms_exp": savings(exp, "depth_rms"),
            "rmse_ratio_adaptive_over_avsm_exp": ratios(rows, errors, "adaptive/exp", "avsm/exp", n_boot, blocks),
            "rmse_ratio_avsm_exp_over_linear": ratios(rows, errors, "avsm/exp", "avsm", n_boot, blocks),
            "rmse_ratio_adaptive_exp_over_linear": ratios(rows, errors, "adaptive/exp", "adaptive", n_boot, blocks),
            "bytes_saved_at_equal_rmse_by_order_exp": by_order_exp,
        }
    if l2:
        out_exp["claims"] = claims(errors, l2, blocks, n_boot, orders)
    return {
        "avsm_order": "depth",
        "avsm_interpolation": "linear, the preset (headline keys); exp: keys ending in _exp",
        "bytes_saved_at_equal_rmse_by_order": by_order,
        "bytes_saved_at_equal_rmse": savings(rows, "rmse"),
        "bytes_saved_at_equal_depth_rms": savings(rows, "depth_rms"),
        # compaction alone (one node count for all non-empty texels): what skipping saves
        "bytes_saved_at_equal_rmse_uniform_allocation": savings(rows, "rmse", "adaptive_uniform"),
        # the former baseline: both sides dense (fixed AVSM pays 8 N bytes for an empty texel)
        "bytes_saved_at_equal_rmse_dense_baseline": savings(rows, "rmse", key="bytes_per_texel"),
        "rmse_ratio_adaptive_over_avsm": ratios(rows, errors, "adaptive", "avsm", n_boot, blocks),
        "rmse_ratio_adaptive_over_adaptive_uniform": ratios(rows, errors, "adaptive", "adaptive_uniform", n_boot,
                                                            blocks),
        "rmse_ratio_adaptive_over_dsm": ratios(rows, errors, "adaptive", "dsm", n_boot, blocks),
        "rmse_ratio_adaptive_over_optimal": ratios(rows, errors, "adaptive", "optimal", n_boot, blocks),
        "rmse_ratio_optimal_over_avsm": ratios(rows, errors, "optimal", "avsm", n_boot, blocks),
        **out_exp,
    }


# ========================================================================= run
def _compute(res, P: dict) -> dict:
    """Every configuration's rows, the findings and the figures."""
    rows: list[dict] = []
    errors, l2, blocks, heat = {}, {}, {}, {}
    for name, config in tqdm(_configs(P), desc="memory_budget", unit="config"):
        _config_rows(name, config, P, rows, errors, heat, l2, blocks)
    summary = findings(rows, errors, P["n_boot"], l2, blocks)
    write_data(res, dict(rows=rows, findings=summary))        # before the figures
    from .plots import plot_curves, plot_heat
    plot_curves(res, [r for r in rows if r["order"] in ("-", "depth")], P["scenes"])
    plot_heat(res, heat)
    return dict(rows=rows, findings=summary, summary=summary)


def redraw(res, rows) -> None:
    """The error figures (:func:`.plots.plot_curves`) from a run's rows read back
    (``python -m experiments._replot memory_budget DATA_CSV --out DIR``); the allocation map
    needs the run itself."""
    from .plots import plot_curves
    plot_curves(res, [r for r in rows if r["order"] in ("-", "depth")], list(dict.fromkeys(r["scene"] for r in rows)))


def _resolve(P: dict, quick: bool) -> dict:
    """Scenes and orders checked; front to back first (the headline's); configurations checked."""
    P["scenes"] = list(P["scenes"])
    for s in P["scenes"]:
        if s not in SCENE_REGISTRY:
            raise ValueError(f"scenes: unknown scene {s!r}; known: {list(SCENE_REGISTRY.names())}")
    P["orders"] = front_to_back_first(P.get("orders"), ORDERS)
    for seed, light in P["configs"]:
        Configuration(seed, light)               # ValueError naming seed / light
    return P

def _headline(s: dict) -> list[str]:
    """Per scene and budget: adaptive AVSM's RMSE over fixed AVSM's, DSM's and the optimum's
    at equal bytes (ratio [interval]), and the bytes fixed AVSM needs more at equal RMSE."""
    out = []
    for scene, per_n in s.get("rmse_ratio_adaptive_over_avsm", {}).items():
        for n, r in per_n.items():
            sv = s.get("bytes_saved_at_equal_rmse", {}).get(scene, {}).get(n, {})
            line = f"{scene} {n}"
            if sv:
                line += f" ({sv['budget_bytes_per_texel']} B/texel)"
            line += f": adaptive RMSE over AVSM {interval(r)}"
            for other in ("dsm", "optimal"):
                o = s.get(f"rmse_ratio_adaptive_over_{other}", {}).get(scene, {}).get(n)
                if o:
                    line += f", over {other} {interval(o)}"
            if sv.get("saving") is not None:
                pct = {("estimate" if k == "saving" else k): 100 * sv[k] for k in ("saving", "low", "high") if k in sv}
                line += f"; bytes saved at equal RMSE {interval(pct, 2) if 'low' in pct else num(pct['estimate'], 2)}%"
            if sv.get("censored"):
                line += f" ({sv['censored']} of {sv['configs']} configurations censored)"
            out.append(line)
    for scene, per_n in s.get("rmse_ratio_adaptive_over_avsm_exp", {}).items():
        for n, r in per_n.items():
            line = f"{scene} {n}, exp interpolation (AVSM's preset): adaptive RMSE over AVSM {interval(r)}"
            e = s.get("rmse_ratio_avsm_exp_over_linear", {}).get(scene, {}).get(n)
            if e:
                line += f"; AVSM exp over linear {interval(e)}"
            sv = s.get("bytes_saved_at_equal_rmse_exp", {}).get(scene, {}).get(n, {})
            if sv.get("saving") is not None:
                pct = {("estimate" if k == "saving" else k): 100 * sv[k] for k in ("saving", "low", "high") if k in sv}
                line += f"; bytes saved {interval(pct, 2) if 'low' in pct else num(pct['estimate'], 2)}%"
            out.append(line)
    dep = [f"{scene} {n} {c}" for scene, per_n in s.get("claims", {}).items() for n, cs in per_n.items()
           for c, v in cs.items() if v.get("metric_dependent")]
    if dep:
        out.append("metric-dependent (receiver RMSE and depth L2 disagree): " + ", ".join(dep))
    return out


STUDY = Study("memory_budget", "A memory budget instead of a node count: every kind at equal bytes per texel",
              REPRODUCES, FULL, QUICK, _compute, resolve=_resolve, writes=("data.csv", "findings.json"),
              options=(Option("scenes", "built-in scenes to run (default: the mode's)", nargs="+", metavar="SCENE"),
                       Option("orders", "insertion orders AVSM is built under besides front to back "
                                        "(default: submission reverse_depth random)", nargs="+", metavar="ORDER"),),
              headline=_headline)
run = STUDY.run

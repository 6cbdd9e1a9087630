"""16-bit storage of 4 power moments: the optimised quantisation of Peters and Klein,
"Moment Shadow Mapping", I3D 2015, sec. 5 (``quantization='msm'``: 4 codes of the
transformed moments, ``b_0`` in float32, 12 bytes) against per-texel scaling
(``'scaled'``: 5 codes over a float32 scale, 14 bytes), in 'float16' and 'unorm16', with
float32 storage (20 bytes) as the reference; per built-in scene over seeds and lights.

Error: the compression error at in-volume receivers (:func:`avsm_dr.receivers.receiver_sets`),
bilinear lookups through the capture, ``T_variant - T_exact`` against the exact curve of
the same segments (capture error cancels).  Every variant is measured twice: with its
default bias alpha and with alpha tuned per variant on a held-out seed (``tune_seed``, never
evaluated; lights ``tune_lights``): the alpha of ``alphas`` minimising the squared error
summed over the scenes.  On scenes with opaque blockers the same is repeated with
``capture(..., opaque='separate')`` (blockers in a depth map, not in the moments; tuned
apart), the control separating what the inline blocker's step costs the 16-bit codes.

``findings.json``, per scene and opaque mode, from :func:`avsm_dr.stats.claim` (RMSE ratio
over the configurations seed x light, paired per receiver; pooled estimate = geometric
mean of the per-configuration ratios, 95 % two-stage bootstrap interval):

* ``<variant>/<default|tuned> vs float32``: each 16-bit variant against float32 at its
  tuned alpha (float32's best configuration), and float32 at its default alpha;
* ``<precision> msm vs scaled (<default|tuned>)``: the transform against scaling at equal
  precision (``holds_in_every_configuration``: msm lower in every configuration's interval);

with ``bytes_per_texel`` per variant and the tuned alphas.  ``data.csv``: one row per
scene, opaque mode, configuration, variant and alpha choice (RMSE, max and mean error);
``tuning.csv``: the held-out seed's RMSE per alpha.

Both metrics: each row also carries ``signed_mean`` and ``leak_share`` (error >
0.02) at the receivers, ``depth_l2`` (:func:`avsm_dr.evaluation.depth_l2` against the exact
curve, per texel then RMS), ``bytes`` (sparse layout) and ``bytes_dense``, and ``order``
(``-``: moments do not depend on the insertion order).  Every claim carries, besides the
receiver RMSE fields above, ``metrics`` (receiver RMSE and depth-L2 ratio, each with its
configuration-level interval), ``metric_dependent``, ``indicative`` (fewer than 4
configurations) and each side's signed mean and leak share
(:func:`experiments._two_metric.claim`); within a configuration receivers and texels are
resampled in 8 x 8 texel tiles.  The tuning criterion stays the receivers' squared error.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from tqdm import tqdm

from avsm_dr import build
from .._headline import interval, num, wrap
from .._study import Option, Study, write_data

#: What this study reproduces (a paper's figure or table, or the guide's section).
REPRODUCES = (
    '16-bit storage of 4 power moments (no paper reports it): the optimised quantisation of '
    'Peters and Klein, "Moment Shadow Mapping", I3D 2015, sec. 5 (\'msm\', 12 bytes) against '
    "per-texel scaling ('scaled', 14 bytes) in float16 and unorm16, vs float32 (20 bytes); "
    'alpha tuned per variant on a held-out seed, RMSE ratios with 95 % intervals over seeds x '
    "lights, and the opaque='separate' capture as the control for the inline blocker."
)


SCENES = ["plume", "hair_and_smoke", "smoke_over_table"]
#: (precision, quantization) of 4 power moments; float32 is the reference.
VARIANTS = (("float32", None), ("float16", "scaled"), ("float16", "msm"), ("unorm16", "scaled"),
            ("unorm16", "msm"))
REFERENCE = "float32"
#: Bias alphas the tuning tries.
ALPHAS = (5e-7, 2e-6, 5e-6, 1e-5, 2e-5, 4e-5, 6e-5, 1e-4, 2e-4, 4e-4, 1e-3)
TAGS = ("default", "tuned")

#: Parameters of the full and the quick run (quick: one scene with a blocker, 64^2 (the least
#: capture resolution), 256 receivers, 2 configurations, 3 alphas).
FULL = dict(scenes=SCENES, resolution=64, n_volume=2048,
            configs=[[s, li] for s in range(4) for li in ("dir_a", "dir_b", "spot") if li != "spot" or s < 2],
            tune_seed=4, tune_lights=["dir_a", "spot"], alphas=list(ALPHAS), separate=True, n_boot=1000)
QUICK = dict(FULL, scenes=["smoke_over_table"], n_volume=256, configs=[[0, "dir_a"], [1, "dir_b"]],
             tune_lights=["dir_a"], alphas=[5e-7, 6e-5, 1e-3], n_boot=200)


def label(precision: str, quantization: str | None) -> str:
    """'float32', 'float16/scaled', 'unorm16/msm', ..."""
    return precision if quantization is None else f"{precision}/{quantization}"


def build_variant(segments, precision: str, quantization: str | None, alpha: float | None = None):
    """4 power moments of ``segments`` stored as (``precision``, ``quantization``); ``alpha``
    None = the kind's default bias.  float32 = the segments' own dtype (no requantisation)."""
    kw = {} if quantization is None else dict(precision=precision, quantization=quantization)
    if alpha is not None:
        kw["bias"] = float(alpha)
    return build("moments", segments, moments=4, **kw)


@dataclasses.dataclass
class _View:
    """One capture seen at the receivers: probe, the exact curve's lookups, its values on the
    depth-L2 grid (:func:`avsm_dr.evaluation.curve_values`) and the 8 x 8 texel tiles of the
    receivers (nearest tap) and of the depth-L2 texels (None when not needed)."""
    probe: object
    segments: object
    exact: np.ndarray
    curve: np.ndarray | None = None
    tiles: tuple | None = None

    def error(self, precision, quantization, alpha=None):
        """(signed per-receiver compression error (K,), representation)."""
        rep = build_variant(self.segments, precision, quantization, alpha)
        return self.probe.lookup(rep) - self.exact, rep

    def l2(self, rep) -> np.ndarray:
        """Per-texel depth-uniform L2 of ``rep`` (:func:`avsm_dr.evaluation.depth_l2`)."""
        from avsm_dr.evaluation import depth_l2
        return depth_l2(rep, self.segments, exact=self.curve, per_texel=True)


def views(name: str, seed: int, light: str, P: dict, curves: bool = False) -> dict:
    """{'inline': _View, 'separate': _View (scenes with blockers, when ``P['separate']``)} of
    one configuration (scene, seed, light); ``curves``: with the depth-L2 reference and tiles."""
    from avsm_dr import capture, receivers
    from avsm_dr import scenes as scene_lib
    from avsm_dr.evaluation import Probe, light_variants
    sc0 = scene_lib.get(name, seed=seed)
    scene = dataclasses.replace(sc0, light=light_variants(sc0)[light])
    pts = receivers.receiver_sets(scene, P["n_volume"], 16, seed=seed)["in_volume"]
    caps = {"inline": capture(scene, resolution=P["resolution"], order="depth")}
    if P["separate"] and scene.blockers:
        caps["separate"] = capture(scene, resolution=P["resolution"], opaque="separate", order="depth")
    probe = Probe(caps["inline"], scene, pts, 0, truth_at_points=np.zeros(len(pts)))  # truth unused
    out = {}
    for mode, cap in caps.items():
        pr = probe.with_capture(cap)
        exact = build("exact", cap.segments)
        v = _View(pr, cap.segments, pr.lookup(exact))
        if curves:
            from avsm_dr.evaluation import curve_values, depth_grid
            from .._two_metric import texel_blocks
            nearest = pr.tex[np.argmax(pr.weights, axis=0), np.arange(pr.k)]
            v.curve = curve_values(exact, cap.segments)
            v.tiles = (texel_blocks(nearest, cap.width), texel_blocks(depth_grid(cap.segments)[0], cap.width))
        out[mode] = v
    return out


def tune(P: dict, progress: bool = True) -> tuple[dict, list]:
    """Best alpha per opaque mode and variant on the held-out seed: ``({mode: {label:
    alpha}}, tuning rows)``; criterion: mean squared error summed over scenes and lights."""
    sse: dict = {}
    rows = []
    jobs = [(n, li) for n in P["scenes"] for li in P["tune_lights"]]
    for name, light in tqdm(jobs, desc="moment_storage tune", unit="config", disable=not progress):
        for mode, v in views(name, P["tune_seed"], light, P).items():
            for prec, q in VARIANTS:
                for i, a in enumerate(P["alphas"]):
                    e, _ = v.error(prec, q, a)
                    mse = float(np.mean(e ** 2))
                    sse.setdefault(mode, {}).setdefault(label(prec, q), np.zeros(len(P["alphas"])))[i] += mse
                    rows.append(dict(scene=name, opaque=mode, seed=P["tune_seed"], light=light,
                                     variant=label(prec, q), alpha=a, rmse=float(np.sqrt(mse))))
    best = {mode: {lab: float(P["alphas"][int(np.argmin(s))]) for lab, s in d.items()} for mode, d in sse.items()}
    return best, rows


def evaluate(P: dict, best: dict, progress: bool = True) -> tuple[list, dict, dict, dict, dict]:
    """(rows, errors {(scene, mode, config, variant, tag): (K,) signed errors}, bytes per
    texel {variant: bytes}, per-texel depth L2 {same keys}, tiles {(scene, mode, config):
    (receiver tiles, texel tiles)}) over the evaluation configurations."""
    from avsm_dr.metrics import THRESHOLD, summary as error_summary
    rows, errs, nbytes, l2s, tiles = [], {}, {}, {}, {}
    jobs = [(n, s, li) for n in P["scenes"] for s, li in P["configs"]]
    for name, seed, light in tqdm(jobs, desc="moment_storage", unit="config", disable=not progress):
        config = f"s{seed}-{light}"
        for mode, v in views(name, seed, light, P, curves=True).items():
            tiles[(name, mode, config)] = v.tiles
            for prec, q in VARIANTS:
                lab = label(prec, q)
                for tag in TAGS:
                    e, rep = v.error(prec, q, best[mode][lab] if tag == "tuned" else None)
                    errs[(name, mode, config, lab, tag)] = e
                    l2 = l2s[(name, mode, config, lab, tag)] = v.l2(rep)
                    nbytes[lab] = float(rep.nbytes_per_texel)
                    st = error_summary(e, THRESHOLD)           # avsm_dr.metrics' statistics of the signed errors
                    rows.append(dict(scene=name, opaque=mode, config=config, seed=seed, light=light, variant=lab,
                                     precision=prec, quantization=q or "", tag=tag,
                                     alpha=float(rep.params["bias"]), bytes_per_texel=float(rep.nbytes_per_texel),
                                     n=int(e.size), rmse=st["rmse"], max_error=st["max_error"],
                                     mean_error=st["mean_error"], order="-", signed_mean=st["mean_error"],
                                     leak_share=st["leak_fraction"],
                                     depth_l2=float(np.sqrt(np.mean(l2 ** 2))) if l2.size else float("nan"),
                                     bytes=float(rep.nbytes_sparse_per_texel), bytes_dense=float(rep.nbytes_per_texel)))
    return rows, errs, nbytes, l2s, tiles


def _claim(a, b, configs, n_boot, l2=None, tiles=None) -> dict:
    """The receiver RMSE claim (:func:`avsm_dr.stats.claim`), and with ``l2`` = (a, b) per-texel
    depth L2 the two-metric fields of :func:`experiments._two_metric.claim` (``metrics``,
    ``metric_dependent``, ``indicative``, ``sides``, ...); ``tiles``: per configuration the
    (receiver, texel) 8 x 8 tiles of the within-configuration resampling."""
    from avsm_dr import stats
    blocks = (None, None) if tiles is None else tuple(list(x) for x in zip(*tiles))
    r = stats.claim(a, b, statistic="rmse", compare="ratio", configs=configs, n_boot=n_boot,
                    blocks_by_config=blocks[0])
    out = dict(estimate=r["estimate"], low=r["low"], high=r["high"], level=r["level"], n_configs=r["n_configs"],
               holds_in_every_configuration=r["holds_in_every_configuration"],
               point_holds_in_every_configuration=r["point_holds_in_every_configuration"],
               holds_pooled=r["holds_pooled"],
               per_config={pc["config"]: [pc["estimate"], pc["low"], pc["high"]] for pc in r["per_config"]})
    if l2 is not None:
        from .._two_metric import claim as two_metric
        both = two_metric((a, b), l2, configs, blocks, n_boot)
        out.update(order="-", **{k: both[k] for k in ("indicative", "interval_unit", "within_configuration",
                                                      "metrics", "metric_dependent", "sides")})
    return out


def findings(errs: dict, nbytes: dict, best: dict, n_boot: int = 1000, l2s: dict | None = None,
             tiles: dict | None = None) -> dict:
    """Claims per scene and opaque mode (module docstring), bytes and tuned alphas; with
    ``l2s`` (and ``tiles``) every claim on both metrics."""
    out: dict = {"bytes_per_texel": nbytes, "best_alpha": best, "claims": {}}
    keys = sorted({(k[0], k[1]) for k in errs})
    for scene, mode in keys:
        configs = sorted({k[2] for k in errs if k[:2] == (scene, mode)})
        til = None if tiles is None else [tiles[(scene, mode, c)] for c in configs]

        def side(lab, tag, store=errs):
            return [store[(scene, mode, c, lab, tag)] for c in configs]

        def cl(a, b):
            l2 = None if l2s is None else (side(*a, store=l2s), side(*b, store=l2s))
            return _claim(side(*a), side(*b), configs, n_boot, l2, til)
        ref = (REFERENCE, "tuned")
        d = out["claims"].setdefault(scene, {}).setdefault(mode, {})
        d[f"{REFERENCE}/default vs {REFERENCE}"] = cl((REFERENCE, "default"), ref)
        for prec, q in VARIANTS:
            if q is None:
                continue
            for tag in TAGS:
                d[f"{label(prec, q)}/{tag} vs {REFERENCE}"] = cl((label(prec, q), tag), ref)
        for prec in sorted({p for p, q in VARIANTS if q == "msm"}):
            for tag in TAGS:
                d[f"{prec} msm vs scaled ({tag})"] = cl((f"{prec}/msm", tag), (f"{prec}/scaled", tag))
    return out


def _resolve(P: dict, quick: bool) -> dict:
    """The tuning seed checked held out; the variants' labels."""
    if P["tune_seed"] in {s for s, _ in P["configs"]}:
        raise ValueError(f"tune_seed: {P['tune_seed']} is also evaluated; the tuning seed must be held out")
    return dict(P, scenes=list(P["scenes"]), variants=[label(*v) for v in VARIANTS])


def _compute(res, P: dict) -> dict:
    """The clamping strength tuned on the held-out seed, every variant's errors, the figure."""
    best, tune_rows = tune(P)
    rows, errs, nbytes, l2s, tiles = evaluate(P, best)
    summary = findings(errs, nbytes, best, n_boot=P["n_boot"], l2s=l2s, tiles=tiles)
    write_data(res, dict(rows=rows, tables={"tuning.csv": tune_rows}, findings=summary))   # before the figures
    from .plots import plot_ratios
    plot_ratios(res, summary, [label(*v) for v in VARIANTS], TAGS, REFERENCE)
    return dict(rows=rows, tables={"tuning.csv": tune_rows}, findings=summary,
                summary={"best_alpha": best, "bytes_per_texel": nbytes, "claims": _intervals(summary["claims"])},
                result={"summary": summary})


def _intervals(claims: dict) -> dict:
    """The claims' ``{estimate, low, high}`` alone (meta.json's summary, the run's headline)."""
    return {scene: {mode: {k: {x: c[x] for x in ("estimate", "low", "high")} for k, c in cs.items()}
                    for mode, cs in modes.items()} for scene, modes in claims.items()}

def _headline(s: dict) -> list[str]:
    """Bytes per texel of each storage, and per scene and opaque mode each variant's RMSE over
    float32's (ratio [interval], tuned clamping)."""
    out = wrap("bytes per texel: ", [f"{k} {num(v)}" for k, v in s.get("bytes_per_texel", {}).items()])
    for scene, modes in s.get("claims", {}).items():
        for mode, claims in modes.items():
            out += wrap(f"{scene} ({mode} opaque), RMSE over float32: ",
                        [f"{k.split(' vs ')[0]} {interval(v)}" for k, v in claims.items() if "/tuned vs" in k])
    return out


STUDY = Study("moment_storage", "16-bit storage of 4 power moments against float32", REPRODUCES, FULL, QUICK,
              _compute, resolve=_resolve, writes=("data.csv", "tuning.csv", "findings.json"),
              options=(Option("scenes", "built-in scenes to run (default: the mode's)", nargs="+", metavar="SCENE"),),
              headline=_headline)
run = STUDY.run

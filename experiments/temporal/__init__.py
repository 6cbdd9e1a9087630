"""Temporal stability of every representation under animation: error per frame and flicker.

Animations (:mod:`.scenes`): the stable-fluids smoke plume stepping
(:func:`avsm_dr.fluid.simulate_plume_sequence`, Stam, "Stable Fluids", SIGGRAPH 1999),
a light turning slowly (the map swims over still content), a camera orbiting (receivers
that move over the content) and hair swaying through still smoke.  Every frame is captured
anew (light map fitted to a fixed box; the ``light`` animation refits it per direction),
every representation rebuilt on it.

Representations: every registered kind in its headline configuration
(``describe(kind)['headline']``), and AVSM twice (Salvi et al., "Adaptive Volumetric
Shadow Maps", EGSR 2010, sec. 4.1 on insertion order): ``unsorted``, its segments inserted in
a fresh random order per frame, as an unordered on-device capture delivers them, and
``sorted`` (``sort=True``, depth order), and so is each of AVSM's other insertion variants
(:func:`insertion_variants`, rows ``avsm-8 <insertion> unsorted|sorted``; the unsorted ones see
the same random order per frame as unsorted AVSM).  Last, ``avsm-8 submission`` and
``avsm-8 <insertion> submission``: unsorted, on a second capture in ``order="submission"``
(:data:`avsm_dr.capture.ORDERS`: a renderer's draw order, the same primitives in the same order
every frame), so only the content's and the light's motion re-orders a texel's segments.
``avsm_march`` is the engine-style AVSM that re-allocates its nodes as it marches.  Other kinds
are built on the capture's depth-sorted segments; all builds cover only the texels the
receivers' bilinear taps touch, with the whole map's depth range.

Configurations (seed x light; the full run: seeds 0-3 under ``dir_a`` and ``dir_b``, seeds 0-1
also under ``spot``, :func:`avsm_dr.evaluation.light_variants`, 10 in all): a seed draws the
fluid simulation (its source's density factors and wobble), the plume's receivers, the hair
strands, the hair scene's smoke and the strands' sway phases, so every animation's content
differs between seeds (the camera's receivers are pixels, the same in every seed).  The full run
trades frames for configurations (12 frames each): flicker is a frame-to-frame difference per
receiver, so every frame pair adds to it, and 10 configurations x 11 pairs x 1024 receivers are
more differences than the previous 2 x 47 x 1024, on 10 independent contents instead of 2.

Per representation, animation and configuration, at fixed receivers,
against the exact curve of the same map and filter (``vs='exact'``: the representation's own
error; ``exact`` has none, so no flicker) and against the true transmittance (``vs='truth'``,
float64 ray march, step 1/8 voxel: adds the map's own sampling, which swims): error and
flicker per frame and pooled, as defined in :mod:`.metrics`::

    e[t, i] = T_rep[t, i] - T_ref[t, i]
    flicker = sqrt(mean_{t >= 1, i} (e[t, i] - e[t-1, i])^2)       content = same with T_ref for e
    flicker_index = flicker / (sqrt(2) error)                       (0 frozen, 1 uncorrelated)

Metrics: flicker and error are measured at the fixed receivers, the
study's subject (what a viewer sees move); a depth-uniform flicker is not defined, as the
map's texels and depth ranges move between frames.  Every row also records the capture's
insertion ``order`` (``'depth'``, ``'random'``: a fresh order per frame, ``'submission'``),
``bytes`` (sparse layout) and ``bytes_dense``, the receivers' ``signed_mean`` and
``leak_share`` (error > 0.02), and ``depth_l2``, the frame's depth-uniform L2 of the curve
against the exact one (:func:`avsm_dr.evaluation.depth_l2` on the texels built); error
claims (sorted vs unsorted AVSM, each insertion variant vs stream AVSM) carry both metrics
and ``metric_dependent`` (their intervals on opposite sides of 1: ``error_curves``' rule).

Intervals: the configuration is the unit.  Per method, each configuration's statistic first
(over its receivers and frames), then their mean with a bootstrap 95 % interval over the
configurations (:func:`.metrics.config_ci`; ``python -m experiments.temporal.recompute`` redoes
this from a run's ``data.csv``); paired comparisons (unsorted vs sorted AVSM, ``avsm_march``
vs sorted AVSM, each insertion variant vs sorted and vs same-order stream AVSM, submission-order
rows also vs random-order stream AVSM: :func:`insertion_claims`) by :func:`avsm_dr.stats.claim`
(configurations, then within each whole 8 x 8 texel tiles of
receivers x frames; for ``depth_l2`` each frame's texels by their tile), each ``indicative``
below :data:`MIN_CONFIDENT` configurations and ``holds_in_every_configuration`` only in at least
:data:`MIN_EVERY` of them.
"""

from __future__ import annotations

import copy
import time

import numpy as np
from tqdm import tqdm

from avsm_dr import builtin_scenes, capture, describe, kinds, procedural
from avsm_dr.metrics import THRESHOLD
from . import scenes as S
from .._headline import num
from .._study import Option, Study, write_data
from avsm_dr.evaluation import Probe, SubsetBuilder, curve_values, depth_grid, depth_l2, light_variants, truth
from .metrics import config_ci, per_frame, pooled, receiver_sums
from .._two_metric import texel_blocks
from ..ordering import shuffled

#: What this study reproduces (a paper's figure or table, or the guide's section).
REPRODUCES = (
    'Temporal stability under animation (a new result: no paper reports it): error per frame '
    'and flicker of every representation, at fixed receivers, while the '
    'stable-fluids smoke steps, the light turns, the camera orbits and hair sways; unsorted vs '
    'sorted AVSM and the engine-style avsm_march; GIFs of the shadow and its error.'
)


#: Animations, in the order of the tables and figures.
SETTINGS = ("smoke", "light", "camera", "hair")
#: Lights of the configurations (:func:`avsm_dr.evaluation.light_variants`; the index seeds the
#: insertion orders, so new names go last).
LIGHTS = ("dir_a", "dir_b", "spot")
#: (kind, variant) drawn in the animated images, where registered.
GIF_METHODS = (("avsm", "unsorted"), ("avsm_march", ""), ("fom", ""))
#: Kinds of the quick run (the test suite's time budget); the full run takes every registered kind
#: but those of :data:`SKIP_KINDS`.
QUICK_KINDS = ("exact", "avsm", "avsm_march", "fom", "moments")
#: Below this many configurations (seed x light) a claim is ``indicative``.
MIN_CONFIDENT = 4
#: Configurations needed before a claim ``holds_in_every_configuration``.
MIN_EVERY = 8
#: A receiver's error above this (in T) counts as leaking light (:data:`avsm_dr.metrics.THRESHOLD`).
LEAK = THRESHOLD
#: How findings.json's intervals are made (its ``intervals`` entry).
INTERVALS = ("per method (per_setting): each configuration's statistic (over its receivers and frames), then "
             "the mean over configurations with a 95 % bootstrap percentile interval over the configurations "
             "(none with one); claims: avsm_dr.stats.claim, configurations, then within each whole 8 x 8 texel "
             "tiles (receivers x frames, each receiver's tile in frame 0; depth_l2: each frame's texels by "
             "their tile)")
#: Left out: the offline best-subset oracle costs 3.5-4 s per frame on the receivers' texels
#: at 128^2 (measured, 2 shared cores), 30 min for the full run's 480 frames, and is no
#: real-time method.
SKIP_KINDS = ("optimal",)


def insertion_variants() -> list[str]:
    """AVSM's ``insertion`` choices (``describe("avsm")["params"]["insertion"]``) but the
    paper's ``stream``, whose rows are ``avsm-8 unsorted`` and ``avsm-8 sorted``."""
    return [c for c in describe("avsm")["params"]["insertion"]["choices"] if c != "stream"]


def methods(quick: bool = False) -> list[tuple[str, str, dict, str]]:
    """(label, kind, params, order) of every representation measured: each registered kind
    but :data:`SKIP_KINDS` (``quick``: those of :data:`QUICK_KINDS`) at its headline parameters; AVSM unsorted
    (``order`` ``'random'``: a fresh random insertion order per frame) and sorted; then the same
    two for each of :func:`insertion_variants` (``params['insertion']`` set); last, stream AVSM
    and each variant unsorted in the capture's ``'submission'`` order (the same draw order every
    frame).  Other rows: ``order`` ``'depth'`` (the depth-order capture).  Labels:
    ``kind-<size value>`` plus the variant (``avsm-8 refit_l2 sorted``, ``avsm-8 submission``)."""
    out, variants, submitted = [], [], []
    for kind in kinds():
        if kind in SKIP_KINDS or quick and kind not in QUICK_KINDS:
            continue
        d = describe(kind)
        p = dict(d["headline"])
        name = f"{kind}-{p[d['size']]}" if d["size"] and d["size"] in p else kind
        if kind == "avsm":
            out.append((f"{name} unsorted", kind, dict(p, sort=False), "random"))
            out.append((f"{name} sorted", kind, dict(p, sort=True), "depth"))
            submitted.append((f"{name} submission", kind, dict(p, sort=False), "submission"))
            for ins in insertion_variants():
                variants.append((f"{name} {ins} unsorted", kind, dict(p, sort=False, insertion=ins), "random"))
                variants.append((f"{name} {ins} sorted", kind, dict(p, sort=True, insertion=ins), "depth"))
                submitted.append((f"{name} {ins} submission", kind, dict(p, sort=False, insertion=ins),
                                  "submission"))
        else:
            out.append((name, kind, p, "depth"))
    return out + variants + submitted      # appended: the other rows keep their order


def _gif_labels(ms) -> list[str]:
    out = []
    for kind, variant in GIF_METHODS:
        for label, k, _, _ in ms:
            if k == kind and (not variant or label.endswith(variant)):
                out.append(label)
                break
    return out


#: Parameters of the full and the quick run (``methods``: the compared labels, filled in).
FULL = dict(frames=12, configs=[[s, li] for s in range(4) for li in LIGHTS if li != "spot" or s < 2],
            settings=list(SETTINGS), size=32, hair_size=24, hair_strands=300, resolution=128, n_receivers=1024,
            camera_pixels=24, image=32, start_steps=40,
            density_scale=40.0, light_step=0.25, camera_step=0.5, gif_settings=["smoke", "light", "hair"],
            hair_amplitude=0.06, hair_period=24, filter="bilinear", truth="raymarch, step 1/8 voxel, float64",
            n_boot=1000, methods=None)
QUICK = dict(FULL, frames=5, configs=[[0, "dir_a"]], size=16, hair_size=12, hair_strands=60, resolution=64,
             n_receivers=256, camera_pixels=12, image=16, start_steps=20, light_step=1.0, camera_step=1.0,
             gif_settings=["smoke"], hair_period=6, n_boot=200)


def _resolve(P: dict, quick: bool) -> dict:
    """``methods``: every label of :func:`methods` (``None``), or the given subset, checked."""
    bad = [s for s in P["settings"] if s not in SETTINGS]
    if bad or not P["settings"]:
        raise ValueError(f"settings: expected animations among {list(SETTINGS)}, got {bad or P['settings']}")
    labels = [m[0] for m in methods(quick)]
    if P["methods"] is None:
        return dict(P, methods=labels)
    unknown = [m for m in P["methods"] if m not in labels]
    if unknown or not P["methods"]:
        raise ValueError(f"methods: expected labels among {labels}, got {unknown or P['methods']}")
    return dict(P, methods=[m for m in labels if m in P["methods"]])


# ======================================================================= frames
def _animations(P, seed, light_names):
    """{(setting, light name): frame function} for one seed and the named lights."""
    from avsm_dr.fluid import simulate_plume_sequence
    nz, ny, nx = procedural.grid_box(*S.PLUME_BOX, P["size"])[0]
    seq = simulate_plume_sequence((nz, ny, nx), frames=P["frames"], start=P["start_steps"], seed=seed,
                                  progress=True) * np.float32(P["density_scale"])
    base0 = S.plume_scene(seq.max(axis=0), builtin_scenes.DirectionalLight(direction=(1.0, -0.3, 0.25)),
                          P["n_receivers"], seed)
    hair0 = builtin_scenes.hair_and_smoke(size=P["hair_size"], seed=seed, n_strands=P["hair_strands"],
                                          n_receivers=P["n_receivers"])
    lights = {"plume": light_variants(base0), "hair": light_variants(hair0)}
    out = {}
    for lname in light_names:
        base = copy.copy(base0)
        base.light = lights["plume"][lname]
        hb = copy.copy(hair0)
        hb.light = lights["hair"][lname]
        anim = {"smoke": S.smoke(base, seq, P["image"]),
                "light": S.light(base, seq[-1], P["light_step"], P["image"]),
                "camera": S.camera(base, seq[-1], P["camera_step"], P["camera_pixels"]),
                "hair": S.hair(hb, P["hair_amplitude"], P["hair_period"], P["image"], seed)}
        for s in P["settings"]:
            out[(s, lname)] = anim[s]
    return out


def _evaluate(frame, P, ms, rng, gif: bool):
    """Lookups of every method in one frame: (exact (K,), truth (K,), {label: (K,)},
    {label: (dense, sparse) bytes per texel}, {label: (T',) float32 per-texel depth-uniform
    L2}, image dict or None).  Rows in ``'submission'`` order are built on a second capture of
    the same frame in that order (the same texels' segments).  The L2 is
    :func:`avsm_dr.evaluation.depth_l2` (``per_texel``) of the build against the exact curve of
    the depth-order capture, on the grid of the segments it was built on (the same texels and
    depth ranges in every order: a texel's range does not depend on its segments' order)."""
    cap = capture(frame.scene, resolution=P["resolution"], bounds=frame.bounds, order="depth")
    probe = Probe(cap, frame.scene, frame.receivers, 0, truth_at_points=truth(frame.scene, frame.receivers))
    img = Probe(cap, frame.scene, frame.image, 0, truth_at_points=np.ones(len(frame.image))) \
        if gif and frame.image is not None else None
    taps = np.concatenate([probe.tex.ravel()] + ([img.tex.ravel()] if img is not None else []))
    sub = SubsetBuilder(cap.segments, taps)
    mixed = copy.copy(sub)
    mixed.segments = shuffled(sub.segments, rng)           # an unordered capture: new order every frame
    builders = {"depth": sub, "random": mixed}
    if any(m[3] == "submission" for m in ms):              # a renderer's draw order: the same every frame
        drawn = capture(frame.scene, resolution=P["resolution"], bounds=frame.bounds, order="submission")
        if not np.array_equal(drawn.segments.counts, cap.segments.counts):
            raise RuntimeError("the submission-order capture has other segment counts than the depth-order one")
        builders["submission"] = SubsetBuilder(drawn.segments, taps)
    exact = sub.build("exact", {})
    ex = probe.lookup(exact)
    tiles = texel_blocks(probe.tex[0], cap.width)           # each receiver's 8 x 8 texel tile
    ex_curve = {}                                          # order -> exact curve on that order's grid

    counted = depth_grid(sub.segments)[0]                   # the texels of the per-texel L2, in order
    l2_tiles = texel_blocks(sub.texels[counted], cap.width)

    def l2(order, rep) -> np.ndarray:
        seg = builders[order].segments
        if order not in ex_curve:
            ex_curve[order] = curve_values(exact.rep, seg)
        return depth_l2(rep, seg, exact=ex_curve[order], per_texel=True).astype(np.float32)
    est, nbytes, l2s, image = {}, {}, {}, None
    if img is not None:
        image = {"exact": img.lookup(exact)}
    gl = set(_gif_labels(ms))
    for label, kind, params, order in ms:
        rep = exact if kind == "exact" else builders[order].build(kind, params)
        est[label] = ex if kind == "exact" else probe.lookup(rep)
        nbytes[label] = (float(rep.rep.nbytes_per_texel), float(rep.rep.nbytes_sparse_per_texel))
        l2s[label] = l2(order, rep.rep)
        if image is not None and label in gl:
            image[label] = img.lookup(rep)
    return ex, probe.truth, est, nbytes, l2s, image, (tiles, l2_tiles)


# ========================================================================== run
def _compute(res, P: dict) -> dict:
    """Every animation, configuration and method, frame by frame; the findings, figures and GIFs."""
    ms = [m for m in methods(res.quick) if m[0] in P["methods"]]
    t0 = time.perf_counter()
    F = P["frames"]
    series = {}     # (setting, config) -> dict(exact (F,K), truth (F,K), est {label: (F,K)}, bytes, image)
    bar = tqdm(total=len(P["configs"]) * len(P["settings"]) * F, desc="temporal", unit="frame")
    for seed in sorted({c[0] for c in P["configs"]}):
        names = [li for s, li in P["configs"] if s == seed]
        anims = _animations(P, seed, names)
        for li in names:
            cfg = f"s{seed}-{li}"
            for setting in P["settings"]:      # seeded by the animation's name: a narrowed run draws the same orders
                rng = np.random.default_rng([seed, SETTINGS.index(setting), LIGHTS.index(li)])
                gif = [seed, li] == list(P["configs"][0]) and setting in P["gif_settings"]
                acc = dict(exact=[], truth=[], est={m[0]: [] for m in ms}, bytes={m[0]: [] for m in ms},
                           l2={m[0]: [] for m in ms}, image=[])
                for t in range(F):
                    ex, tr, est, nbytes, l2s, image, tiles = _evaluate(anims[(setting, li)](t), P, ms, rng, gif)
                    if t == 0:
                        acc["blocks"] = tiles[0]
                    acc.setdefault("l2_blocks", []).append(tiles[1])
                    acc["exact"].append(ex)
                    acc["truth"].append(tr)
                    for k, v in est.items():
                        acc["est"][k].append(v)
                        acc["bytes"][k].append(nbytes[k])
                        acc["l2"][k].append(l2s[k])
                    if image is not None:
                        acc["image"].append(image)
                    bar.update(1)
                series[(setting, cfg)] = dict(exact=np.stack(acc["exact"]), truth=np.stack(acc["truth"]),
                                              est={k: np.stack(v) for k, v in acc["est"].items()},
                                              bytes={k: float(np.mean([b[0] for b in v]))
                                                     for k, v in acc["bytes"].items()},
                                              sparse_bytes={k: float(np.mean([b[1] for b in v]))
                                                            for k, v in acc["bytes"].items()},
                                              l2=acc["l2"], image=acc["image"], blocks=acc["blocks"],
                                              l2_blocks=acc["l2_blocks"])
    bar.close()
    rows = _rows(series, ms)
    summary = findings(series, ms, P)
    summary["run_seconds"] = time.perf_counter() - t0
    from . import plots as _temporal_plots
    write_data(res, dict(rows=rows, findings=summary))        # before the figures
    _temporal_plots.plot_all(res, rows, summary, series, P, _gif_labels(ms))
    return dict(rows=rows, findings=summary, summary={k: summary[k] for k in ("headline", "run_seconds")},
                result={"summary": summary["headline"]})


def _rows(series, ms) -> list[dict]:
    """data.csv: per animation, configuration, method, reference (``vs``) and frame the
    receiver RMS error, flicker and content change (:mod:`.metrics`), then the
    capture's insertion ``order``, ``bytes`` (sparse layout, mean over frames, of the texels
    built) and ``bytes_dense`` (= ``bytes_per_texel``), the error's ``signed_mean`` and
    ``leak_share`` at the receivers against ``vs``, and ``depth_l2``: the frame's
    depth-uniform L2 of the curve against the exact curve (:func:`avsm_dr.evaluation.depth_l2`
    over the texels the receivers' taps touch; the same value in both ``vs`` rows)."""
    rows = []
    for (setting, cfg), s in series.items():
        for label, kind, _, order in ms:
            l2 = [float(np.sqrt(np.mean(np.square(x, dtype=np.float64)))) if x.size else float("nan")
                  for x in s["l2"][label]]
            for vs in ("exact", "truth"):
                pf = per_frame(s["est"][label], s[vs])
                for t in range(pf["error"].size):
                    rows.append(dict(setting=setting, config=cfg, method=label, kind=kind, vs=vs, frame=t,
                                     bytes_per_texel=s["bytes"][label], error_rms=pf["error"][t],
                                     flicker_rms=pf["flicker"][t], content_rms=pf["content"][t], order=order,
                                     bytes=s["sparse_bytes"][label], bytes_dense=s["bytes"][label],
                                     signed_mean=pf["signed_mean"][t], leak_share=pf["leak_share"][t],
                                     depth_l2=l2[t]))
    return rows


# ===================================================================== findings
def findings(series, ms, P) -> dict:
    """Per animation, reference and method the statistics over configurations with their
    intervals and per-configuration values, and the headline (:func:`per_setting`), the
    paired AVSM comparisons and, under ``insertion``, those of :func:`insertion_claims`."""
    from avsm_dr.stats import claim
    F = P["frames"]
    base = [m for m in ms if "insertion" not in m[2] and m[3] != "submission"]
    settings = sorted({k[0] for k in series}, key=list(SETTINGS).index)
    out = {"definition": "e = T_rep - T_ref at fixed receivers; flicker = sqrt(mean_{t>=1,i} (e_t - e_{t-1})^2); "
                         "content = the same for T_ref; flicker_index = flicker / (sqrt(2) error)",
           "frames": F, "configs": sorted({k[1] for k in series}), "per_setting": {}, "claims": {}, "headline": {},
           "insertion": {}, "curves": {},
           "intervals": INTERVALS,
           "metrics": "flicker and error: RMS at fixed receivers (the study's subject: a depth-uniform flicker "
                      "is undefined when the map's texels and depth ranges move between frames); error claims "
                      "also under the depth-uniform L2 of the curve (depth_l2), metric_dependent when the two "
                      "disagree"}
    per_config = {(s, vs, label): {c: pooled(receiver_sums(series[(s, c)]["est"][label], series[(s, c)][vs]), F)
                                   for c in sorted(c for s2, c in series if s2 == s)}
                  for s in settings for vs in ("exact", "truth") for label, _, _, _ in ms}
    out["per_setting"], out["headline"] = per_setting(per_config, settings, ms, P["n_boot"])
    for setting in settings:
        cfgs = sorted(c for s, c in series if s == setting)
        out["claims"][setting] = _claims(series, setting, cfgs, base, claim, P["n_boot"])
        out["insertion"][setting] = insertion_claims(series, setting, cfgs, ms, claim, P["n_boot"])
        out["curves"][setting] = curves(series, setting, cfgs, ms)
    return out


def per_setting(per_config: dict, settings, ms, n_boot: int) -> tuple[dict, dict]:
    """(``per_setting``, ``headline``) of the findings from ``per_config``: {(setting, vs,
    label): {configuration: :func:`.metrics.pooled` dict}} (from the series, or from a run's
    ``data.csv``: :func:`.metrics.per_config_from_rows`).  per_setting[setting][vs][label]:
    :func:`.metrics.config_ci` (each configuration's statistic first, then the mean and its
    interval over configurations); headline: the kind (one row per kind: insertion variants
    and submission-order rows left out) that flickers most, absolute and relative to its
    error, and the one that flickers least relative to its error."""
    kinds_ = {m[0] for m in ms if "insertion" not in m[2] and m[3] != "submission"}
    blocks, headline = {}, {}
    for setting in settings:
        block = blocks[setting] = {vs: {label: config_ci(per_config[(setting, vs, label)], n_boot)
                                        for label, _, _, _ in ms} for vs in ("exact", "truth")}
        rel = {m: v["flicker_index"]["estimate"] for m, v in block["exact"].items()
               if m in kinds_ and v["error"]["estimate"] > 0}
        absf = {m: v["flicker"]["estimate"] for m, v in block["exact"].items() if m in kinds_}
        top_rel = max(rel, key=rel.get) if rel else None
        top_abs = max(absf, key=absf.get)
        headline[setting] = dict(
            content_change=block["exact"][ms[0][0]]["content"]["estimate"],
            most_flicker=top_abs, most_flicker_value=absf[top_abs],
            most_flicker_vs_error=top_rel, most_flicker_index=rel.get(top_rel),
            least_flicker_vs_error=min(rel, key=rel.get) if rel else None)
    return blocks, headline


def curves(series, setting, cfgs, ms) -> dict:
    """Per label: the capture's insertion ``order``, ``bytes`` (sparse) and ``bytes_dense``
    per texel (mean over configurations), ``depth_l2`` (the depth-uniform L2 of the curve
    against the exact one, RMS over the configurations' frames and texels, and per
    configuration), and the receivers' ``signed_mean`` and ``leak_share`` per reference,
    pooled over configurations, frames and receivers (no intervals: the claims carry them)."""
    out = {}
    for label, _, _, order in ms:
        per = {c: _pooled_l2(series[(setting, c)]["l2"][label]) for c in cfgs}
        allv = [x for c in cfgs for x in series[(setting, c)]["l2"][label]]
        rec = dict(order=order, bytes=float(np.mean([series[(setting, c)]["sparse_bytes"][label] for c in cfgs])),
                   bytes_dense=float(np.mean([series[(setting, c)]["bytes"][label] for c in cfgs])),
                   depth_l2=_pooled_l2(allv), depth_l2_per_config=per)
        for vs in ("exact", "truth"):
            e = np.concatenate(_errors(series, setting, cfgs, label, vs))
            rec[f"signed_mean_vs_{vs}"] = float(np.mean(e))
            rec[f"leak_share_vs_{vs}"] = float(np.mean(e > LEAK))
        out[label] = rec
    return out


def _pooled_l2(per_frame_texels) -> float:
    """RMS over every frame's per-texel L2 (the depth-uniform L2 of the frames pooled)."""
    x = np.concatenate([np.asarray(v, np.float64).ravel() for v in per_frame_texels]) if per_frame_texels else []
    return float(np.sqrt(np.mean(np.square(x)))) if np.size(x) else float("nan")


def _claims(series, setting, cfgs, ms, claim, n_boot) -> dict:
    """Paired flicker comparisons (ratio of RMS frame-to-frame error changes, vs exact) in
    every configuration and pooled: sorted / unsorted AVSM, avsm_march / sorted AVSM."""
    labels = {(k, lab.split(" ")[-1] if k == "avsm" else ""): lab for lab, k, _, _ in ms}
    order = {lab: o for lab, _, _, o in ms}
    pairs = {"avsm_sorted_vs_unsorted": (labels.get(("avsm", "sorted")), labels.get(("avsm", "unsorted"))),
             "avsm_march_vs_avsm_sorted": (labels.get(("avsm_march", "")), labels.get(("avsm", "sorted")))}
    out = {}
    for name, (a, b) in pairs.items():
        if a is None or b is None:
            continue
        if all(np.all(x == 0) for x in _changes(series, setting, cfgs, b, "exact")):
            continue
        ca = _changes(series, setting, cfgs, a, "exact")
        out[name] = _paired(claim, ca, _changes(series, setting, cfgs, b, "exact"), cfgs, n_boot, a, b,
                            "flicker_ratio", _blocks_for(series, setting, cfgs, ca))
        out[name]["order"] = [order[a], order[b]]
    # the error (not flicker) of sorted vs unsorted AVSM under both metrics
    a, b = labels.get(("avsm", "sorted")), labels.get(("avsm", "unsorted"))
    if a is not None and b is not None:
        c = _error_claim(claim, series, setting, cfgs, a, b, "exact", n_boot)
        if c is not None:
            out["avsm_sorted_vs_unsorted_error"] = dict(c, order=[order[a], order[b]])
    return out


def _error_claim(claim, series, setting, cfgs, a, b, vs, n_boot) -> dict | None:
    """The RMS error ratio ``a`` / ``b`` at the receivers (against ``vs``) with
    ``metrics``: ``receiver_rmse`` and ``depth_l2`` (per-texel L2 of every frame, paired:
    the same texels; against the exact curve whatever ``vs``), and ``metric_dependent``
    (:func:`experiments._two_metric.metric_dependent`: the two intervals on opposite sides
    of 1).  None when ``b`` has no error."""
    from .._two_metric import metric_dependent
    ea, eb = _errors(series, setting, cfgs, a, vs), _errors(series, setting, cfgs, b, vs)
    if all(np.all(x == 0) for x in eb):
        return None
    out = _paired(claim, ea, eb, cfgs, n_boot, a, b, "ratio", _blocks_for(series, setting, cfgs, ea))
    la = [np.concatenate(series[(setting, c)]["l2"][a]).astype(np.float64) for c in cfgs]
    lb = [np.concatenate(series[(setting, c)]["l2"][b]).astype(np.float64) for c in cfgs]
    m = {"receiver_rmse": {k: out[k] for k in ("low", "high", "n_configs", "indicative")} | {"estimate": out["ratio"]}}
    if all(x.size == y.size and x.size >= 2 and np.any(y > 0) for x, y in zip(la, lb)):
        tb = [np.concatenate(series[(setting, c)]["l2_blocks"]) if "l2_blocks" in series[(setting, c)] else None
              for c in cfgs]
        tb = None if any(t is None or t.size != x.size for t, x in zip(tb, la)) else tb
        d = _paired(claim, la, lb, cfgs, n_boot, a, b, "ratio", tb)
        m["depth_l2"] = {k: d[k] for k in ("low", "high", "n_configs", "indicative")} | {"estimate": d["ratio"]}
    out["metrics"] = m
    out["metric_dependent"] = len(m) == 2 and metric_dependent(*m.values())
    return out


def _errors(series, setting, cfgs, label, vs) -> list[np.ndarray]:
    """Per configuration, the errors e[t, i] of ``label`` against ``vs``, raveled."""
    return [(series[(setting, c)]["est"][label] - series[(setting, c)][vs]).ravel() for c in cfgs]


def _changes(series, setting, cfgs, label, vs) -> list[np.ndarray]:
    """Per configuration, the frame-to-frame changes e[t, i] - e[t-1, i] of ``label``'s error."""
    return [np.diff(series[(setting, c)]["est"][label] - series[(setting, c)][vs], axis=0).ravel() for c in cfgs]


def _blocks_for(series, setting, cfgs, values) -> list | None:
    """Per configuration the 8 x 8 texel tile of each of its values (receivers x frames,
    raveled frame by frame: each receiver's frame-0 tile); None where a series has no tiles."""
    out = []
    for c, v in zip(cfgs, values):
        t = series[(setting, c)].get("blocks")
        if t is None or t.size == 0 or v.size % t.size:
            return None
        out.append(np.tile(t, v.size // t.size))
    return out


def _paired(claim, a, b, cfgs, n_boot, la, lb, key, blocks=None) -> dict:
    """RMS ratio ``la`` / ``lb`` by :func:`avsm_dr.stats.claim`: pooled over configurations
    (the interval's unit), ``indicative`` with fewer than :data:`MIN_CONFIDENT` of them,
    ``holds_in_every_configuration`` (every configuration's interval below 1) only in at least
    :data:`MIN_EVERY`;
    within each configuration whole ``blocks`` (8 x 8 texel tiles) are resampled when given."""
    cl = claim(a, b, statistic="rmse", configs=cfgs, n_boot=n_boot, blocks_by_config=blocks)
    return {"a": la, "b": lb, key: cl["estimate"], "low": cl["low"], "high": cl["high"],
            "holds_in_every_configuration": cl["holds_in_every_configuration"] and cl["n_configs"] >= MIN_EVERY,
            "holds_pooled": cl["holds_pooled"],
            "n_configs": cl["n_configs"], "indicative": cl["n_configs"] < MIN_CONFIDENT,
            "interval_unit": "configuration"}


def insertion_claims(series, setting, cfgs, ms, claim, n_boot) -> dict:
    """Per AVSM insertion variant (label ``avsm-8 <insertion> <order>``) and submission-order
    row (``avsm-8 [<insertion>] submission``), and per reference (``exact``, ``truth``), paired
    ratios by :func:`avsm_dr.stats.claim` (RMS, configurations then receivers x frames):
    ``flicker_vs_sorted`` (its flicker over sorted stream AVSM's: the moonshot's bar),
    ``flicker_vs_stream`` and ``error_vs_stream`` (over stream AVSM's in the same order: the
    variant's own gain; not for ``avsm-8 submission`` itself), for submission-order rows
    ``flicker_vs_unsorted`` (over stream AVSM's in a fresh random order per frame);
    ``verdict``: the flicker-vs-sorted interval lies below 1 (``less``), above it (``more``)
    or across it (``indistinguishable``).  A comparison whose stream row was not run is left out.
    ``error_vs_stream`` also carries ``metrics`` (receiver RMSE and depth-uniform L2) and
    ``metric_dependent`` (:func:`_error_claim`); every ratio ``n_configs`` and ``indicative``."""
    stream = {order: lab for lab, k, p, order in ms if k == "avsm" and "insertion" not in p and not p.get("sort")}
    stream["depth"] = next((lab for lab, k, p, _ in ms if k == "avsm" and "insertion" not in p and p.get("sort")),
                           None)
    sorted_ = stream["depth"]
    out = {}
    for label, kind, p, order in ms:
        if kind != "avsm" or sorted_ is None or label in (sorted_, stream.get("random")):
            continue
        same = None if label == stream.get(order) else stream.get(order)
        rec = {}
        for vs in ("exact", "truth"):
            ch = lambda lab: _changes(series, setting, cfgs, lab, vs)          # noqa: E731
            fl = ch(label)
            fb = _blocks_for(series, setting, cfgs, fl)
            r = {"flicker_vs_sorted": _paired(claim, fl, ch(sorted_), cfgs, n_boot, label, sorted_, "ratio", fb)}
            if same is not None:
                r["flicker_vs_stream"] = r["flicker_vs_sorted"] if same == sorted_ else \
                    _paired(claim, fl, ch(same), cfgs, n_boot, label, same, "ratio", fb)
                r["error_vs_stream"] = _error_claim(claim, series, setting, cfgs, label, same, vs, n_boot) or \
                    _paired(claim, _errors(series, setting, cfgs, label, vs), _errors(series, setting, cfgs, same, vs),
                            cfgs, n_boot, label, same, "ratio",
                            _blocks_for(series, setting, cfgs, _errors(series, setting, cfgs, label, vs)))
            if order == "submission" and stream.get("random") is not None:
                r["flicker_vs_unsorted"] = _paired(claim, fl, ch(stream["random"]), cfgs, n_boot, label,
                                                   stream["random"], "ratio", fb)
            f = r["flicker_vs_sorted"]
            r["verdict"] = "less" if f["high"] < 1 else "more" if f["low"] > 1 else "indistinguishable"
            rec[vs] = r
        out[label] = rec
    return out


def _headline(s: dict) -> list[str]:
    """Per animation: how much the true shadow changes per frame, the kind that flickers most
    (absolute, and relative to its error) and the one that flickers least relative to its error."""
    return [f"{a}: content change {num(h['content_change'])}/frame; most flicker {h['most_flicker']} "
            f"({num(h['most_flicker_value'])}); relative to error most {h['most_flicker_vs_error']} "
            f"(index {num(h['most_flicker_index'])}), least {h['least_flicker_vs_error']}"
            for a, h in s.get("headline", {}).items()] + [f"run time {num(s.get('run_seconds'))} s"]


STUDY = Study("temporal", "Temporal stability of every representation under animation: error per frame and flicker",
              REPRODUCES, FULL, QUICK, _compute, resolve=_resolve,
              writes=("data.csv (one row per animation, configuration, method, reference and frame)",
                      "findings.json", "GIFs"), headline=_headline,
              options=(Option("methods", "only these labels (default: all; 'avsm-8 refit_l2 sorted', "
                                         "'avsm-8 submission', ...)", nargs="+", metavar="LABEL"),
                       Option("settings", f"only these animations (default: all of {', '.join(SETTINGS)})",
                              nargs="+", metavar="ANIMATION")))
run = STUDY.run

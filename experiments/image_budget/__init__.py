"""How many bytes per texel a viewer needs, judged on rendered images.  Single-scattering
images rendered with the Mitsuba integrator ``avsm_single_scatter`` for every kind at its
preset, across byte budgets and shadow-map resolutions, on frames of the temporal study's
animations, against a converged ``volpath`` reference; per animation and resolution the
smallest budget beyond which compression is no longer visible, and the cheapest kind reaching it.

Configurations (the unit of every interval): scene seed x light, ``configs`` (full:
:data:`FULL_CONFIGS`, the other studies' ten: seeds 0-3 under ``dir_a`` and ``dir_b``, seeds 0-1
under ``spot``, :func:`avsm_dr.evaluation.light_variants` of the temporal study's light
:data:`LIGHT`).  The seed is the plume simulation's (it changes the density of every frame).
Frames (:mod:`experiments.temporal.scenes`), per configuration: ``smoke``, the stable-fluids
plume stepping with the light fixed; ``light``, its last frame with the light turning about the
vertical axis through the plume box's centre (:func:`turning`: a spot light turns its position
and direction).  The ``light`` animation's frame 0 is the ``smoke`` animation's last frame (same
density, light not yet turned): it is rendered once (:func:`frame_key`), and both animations'
rows carry it.  Scene, camera and tonemap: :mod:`.render`.

Size candidates: each kind of ``kinds`` at its preset (``describe(kind)['preset']``) merged
with its size parameter (``describe(kind)['size']``); the candidate sizes are the kind's sweep
(budget kinds, sized in bytes per texel: the budgets themselves; tolerance-sized kinds: the
sweep and :data:`EXTRA_SIZES`), each built on the configuration's frame-0 capture at each
resolution (whole map, as the integrator builds it) to read ``nbytes_per_texel``; at budget B
a kind takes its candidate with the most bytes <= B (``fits``), or, when none is within B, its
cheapest candidate (rendered, ``fits`` False, never chosen for that budget).  ``exact`` is the
compression baseline and a candidate where its bytes fit.  Every candidate chosen at some
budget is rendered in every frame; ``bytes_per_texel`` in the table is what that frame's map
stored.

Full-run settings and what was traded for ten configurations.  The previous full run (one
configuration, 6 frames, 64/128/256^2 maps, budgets up to 256 B) took 2,064 s on 2 shared
cores.  Profile of one animation with 2 frames of those settings (626 s on 2 cores at load
about 8): the kinds' renders 286 s (256^2: 154 s, 128^2: 77 s, 64^2: 56 s; the captures and
builds inside them 185 s), the curve metrics 131 s (each curve was evaluated twice, now once),
the references 97 s, the size calibration 65 s (DSM's builds the costliest), FLIP 40 s.

* ``frames`` 6 -> 3 per animation: the interval's unit is now the configuration, and consecutive
  frames of one simulation are strongly correlated; on the previous run's table, frames 0-2 give
  the same threshold, kind and size as all six in both animations and at every resolution, the
  threshold kind's compression / noise ratio within 0.03 of the six-frame one;
* ``resolutions`` 64/128/256^2 -> 64/128^2: the 256^2 captures and builds cost the most, and
  128^2 and 256^2 had the same threshold, kind and size in both animations (ratios within 0.02);
* ``budgets`` up to 256 -> up to 128 B (and :data:`EXTRA_SIZES` without DSM's 0.0002 and
  0.0001, which only reached 256 B): every threshold was 32 B, and the 128 B and 256 B cells
  had the same best kind and size;
* no trade: the frame both animations share is rendered once (a sixth of the renders with 3
  frames per animation);
* kept: ``image`` 48 x 48, ``spp`` 32 and ``reference_spp`` 1024 per half.  The reference's
  Monte Carlo noise is the bar every compression FLIP is ranked against (below); at 1024 spp per
  half it was FLIP 0.0099-0.0102 (mean over frames), while the threshold kinds' compression
  FLIPs sat at 0.45-0.99x of it and the best 16 B kind's at 1.4-2.3x: fewer samples would raise the
  bar (one development frame: 0.016 at 256 spp, 0.0093 at 1024, 0.0056 at 4096) and move the
  threshold, so it stays.  The bar is now the mean over configurations of each configuration's
  mean over frames; ``findings.json['reference']`` gives it per configuration.

Per frame and resolution (display white S fixed per animation and configuration, :mod:`.render`):

* ``flip``: FLIP of the render against the reference (the mean of two independent
  ``volpath`` renders, max_depth 2, ``reference_spp`` each);
* ``flip_compression``: FLIP of the render against ``exact``'s at the same resolution and
  seed (the camera samples are the same: the difference is the shadow map's representation
  alone; 0 for ``exact``);
* ``flip_spatial``: FLIP of ``exact`` at this resolution against the reference (the map's
  spatial sampling and capture, plus the render's own Monte Carlo noise at ``spp``);
  ``flip_resolution``: ``exact`` here against ``exact`` at the finest resolution, same seed
  (the map's resolution alone);
* ``flip_render_noise``: ``exact`` against ``exact`` with another seed (the renders' noise);
  ``flip_reference_noise``: FLIP between the reference's two halves (its noise; the mean of
  the halves has half that standard deviation), and ``reference_se``: the RMS over pixels
  of the reference's per-pixel standard error ``|a - b| / 2``, over S;
* flicker (frames t >= 1): ``flicker`` = mean over pixels of ``|e_t - e_{t-1}|`` / S with
  ``e`` = render - reference; ``flicker_compression`` the same with ``e`` = render - exact
  (every render of every frame uses the same seed, so the camera noise is a fixed pattern
  and cancels from the compression term).

Curve metrics of the map that made each image, per row: ``order``
('depth': the integrator's capture), ``bytes`` (sparse layout, ``nbytes_sparse_per_texel``)
and ``bytes_dense`` (= ``bytes_per_texel``, the budgets' unit), and against the exact curve
of the same capture ``depth_l2`` (:func:`avsm_dr.evaluation.depth_l2`), ``curve_signed_mean``
and ``curve_leak_share`` (> 0.02) over the same depth grid (:func:`.render.curve_metrics`).
The claims use FLIP of rendered frames only: the study asks what a viewer sees, and the
receiver RMSE does not apply (an image integrates the light's T along every pixel's view
ray, there are no receivers); the curve metrics are reported beside them
(``findings.json['curves']``, ``best_depth_l2`` in ``map.csv``), not used to decide.

Answer (:mod:`.analysis`): per configuration the mean over its frames, then the mean over
configurations; a kind's compression is invisible at a budget when its mean compression FLIP
is below the mean reference-noise FLIP; the map (``map.csv``) gives per (animation,
resolution, budget) the cheapest invisible kind, or the least visible one; ``findings.json``
the threshold budget per animation and resolution with a bootstrap interval over
configurations, each configuration's own threshold (``per_config``, ``agreement``: "the same
in every configuration" only from :data:`MIN_EVERY` configurations), and ``claim``: the
threshold kind's compression below the noise at the threshold budget,
:func:`avsm_dr.stats.claim` (ratio of means, configurations resampled then frames within each;
``verdict`` "holds in every configuration" only from :data:`MIN_EVERY`); every threshold and
claim carries ``n_configs`` and ``indicative`` (fewer than :data:`MIN_CONFIGS`).  The same
against the renders' own noise (``flip_render_noise``) instead of the reference's.
"""
from __future__ import annotations

import dataclasses
import hashlib
import time
from collections import Counter

import numpy as np
from tqdm import tqdm

from avsm_dr import capture, describe, kinds as registered_kinds
from avsm_dr.capture import RESOLUTION_RANGE
from avsm_dr.evaluation import LIGHTS, Configuration, light_variants
from avsm_dr.scene import DirectionalLight, Scene
from avsm_dr.stats import claim
from . import analysis as A
from . import render as R
from .._headline import num
from .._study import Option, Study, write_data
from ..temporal import scenes as S

#: What this study reproduces (a paper's figure or table, or the guide's section).
REPRODUCES = (
    "How many bytes per texel a viewer needs (a new result): Mitsuba single-scattering images of every kind "
    "across byte budgets and shadow-map resolutions on the temporal study's animated plume, FLIP against a "
    "converged volpath reference, split into compression, spatial and Monte Carlo error; the budget map."
)

#: Animations rendered (the temporal study's with a density grid only: Mitsuba's medium holds no hair,
#: and the orbiting camera leaves the shadow map unchanged).
SETTINGS = ("smoke", "light")
#: Left out of the default kinds: the offline references, no real-time methods, and the costliest
#: builds: the best-subset oracle (1-5 s per build at 128^2-256^2 on 2 cores) and greedy
#: Visvalingam-Whyatt (measured: 28 s of a 256^2 frame's 70 s for its 5 sizes, renders included).
SKIP_KINDS = ("optimal", "greedy")
#: Candidate sizes beyond a kind's sweep, by size parameter (finer tolerances reach larger budgets:
#: DSM at 0.0005 stores about 88 B per texel, within the full run's largest budget, 128).
EXTRA_SIZES = {"tolerance": (0.001, 0.0005)}
#: The temporal study's light ('dir_a' of every configuration; 'dir_b' and 'spot' follow from it).
LIGHT = (1.0, -0.3, 0.25)
#: Fewer configurations (scene seed x light) than this make a claim ``indicative``.
MIN_CONFIGS = 4
#: "In every configuration" is said only of at least this many configurations.
MIN_EVERY = 8
#: Configurations of the full run (the other studies' ten: seeds 0-3 under both directional
#: lights, seeds 0-1 under the spot light).
FULL_CONFIGS = [[s, li] for s in range(4) for li in LIGHTS if li != "spot" or s < 2]
#: Per-row curve metrics of the map that made the image, averaged per configuration in
#: ``findings.json['curves']``.
CURVE_COLUMNS = ("depth_l2", "curve_signed_mean", "curve_leak_share", "bytes", "bytes_dense")

#: Parameters of the full and the quick run (``kinds`` None: every registered kind but
#: :data:`SKIP_KINDS`, filled in; ``exact`` always first).
FULL = dict(settings=list(SETTINGS), configs=FULL_CONFIGS, frames=3, size=32, start_steps=40, density_scale=40.0,
            light_step=1.0, image=48, spp=32, march_steps=32, reference_spp=1024, render_seed=0,
            resolutions=[64, 128], budgets=[16, 32, 64, 128], kinds=None, n_boot=1000)
QUICK = dict(FULL, settings=["smoke"], configs=[[0, "dir_a"], [1, "spot"]], frames=2, size=16, start_steps=20,
             image=32, spp=16, reference_spp=256, resolutions=[64], budgets=[16, 32, 64],
             kinds=["avsm", "fom", "moments", "beer"], n_boot=200)


def _resolve(P: dict, quick: bool) -> dict:
    """Kinds filled in (``exact`` first), and the parameters checked."""
    known = registered_kinds()
    ks = [k for k in known if k not in SKIP_KINDS] if P["kinds"] is None else list(P["kinds"])
    bad = [k for k in ks if k not in known]
    if bad:
        raise ValueError(f"kinds: unknown kind {bad[0]!r}; known: {known}")
    lo, hi = RESOLUTION_RANGE
    if not P["resolutions"] or any(type(r) is not int or not lo <= r <= hi for r in P["resolutions"]):
        raise ValueError(f"resolutions: expected integers in [{lo}, {hi}], got {P['resolutions']!r}")
    if not P["budgets"] or any(not float(b) > 0 for b in P["budgets"]):
        raise ValueError(f"budgets: expected positive bytes per texel, got {P['budgets']!r}")
    if not P["settings"] or any(s not in SETTINGS for s in P["settings"]):
        raise ValueError(f"settings: expected some of {list(SETTINGS)}, got {P['settings']!r}")
    if P["frames"] < 2:
        raise ValueError(f"frames: expected at least 2 (flicker and the claims need them), got {P['frames']!r}")
    if not isinstance(P["configs"], (list, tuple)) or len(P["configs"]) < 2 or any(
            not isinstance(c, (list, tuple)) or len(c) != 2 for c in P["configs"]):
        raise ValueError(f"configs: expected at least 2 [seed, light] pairs (the intervals resample them), "
                         f"got {P['configs']!r}")
    configs = [Configuration(s, li) for s, li in P["configs"]]     # ValueError naming seed / light
    if len({c.label for c in configs}) != len(configs):
        raise ValueError(f"configs: repeated configurations in {P['configs']!r}")
    return dict(P, kinds=["exact"] + [k for k in ks if k != "exact"], resolutions=sorted(P["resolutions"]),
                budgets=sorted(float(b) for b in P["budgets"]), configs=[[c.seed, c.light] for c in configs])


# ================================================================ configurations
def candidates(kind: str, budgets) -> list[tuple[object, dict]]:
    """(size value or None, build parameters) of each candidate configuration of ``kind``:
    its preset merged with each size (module docstring)."""
    d = describe(kind)
    size, preset = d["size"], dict(d["preset"])
    if size is None:
        return [(None, preset)]
    if size == "bytes_per_texel":
        values = [float(b) for b in budgets]
    else:
        values = list(d["sweep"]) + [v for v in EXTRA_SIZES.get(size, ()) if v not in d["sweep"]]
    return [(v, dict(preset, **{size: v})) for v in values]


def label(kind: str, value) -> str:
    """``kind-<size>`` (``kind`` alone for kinds without a size)."""
    return kind if value is None else f"{kind}-{value:g}"


def calibrate(kind: str, segments, budgets) -> list[tuple[object, dict, float]]:
    """(size, parameters, bytes per texel) of every candidate that builds on ``segments``
    (a candidate the kind refuses there, e.g. a budget below two nodes per texel, is dropped)."""
    from avsm_dr import build
    out = []
    for value, params in candidates(kind, budgets):
        try:
            rep = build(kind, segments, **params)
        except ValueError:
            continue
        out.append((value, params, float(rep.nbytes_per_texel)))
    if not out:
        raise ValueError(f"kinds: {kind!r} builds at none of its candidate sizes")
    return out


def choose(calibrated, budget: float) -> tuple[object, dict, float, bool]:
    """(size, parameters, calibrated bytes, fits) of a kind at ``budget``: its candidate with
    the most bytes within the budget, else its cheapest (``fits`` False)."""
    within = [c for c in calibrated if c[2] <= budget]
    if within:
        return (*max(within, key=lambda c: c[2]), True)
    return (*min(calibrated, key=lambda c: c[2]), False)


def plume_shape(size: int) -> tuple[int, int, int]:
    """(nz, ny, nx) of the plume grid over :data:`experiments.temporal.scenes.PLUME_BOX` with
    ``size`` voxels per unit length (the temporal study's grid)."""
    lo, hi = S.PLUME_BOX
    nx, ny, nz = np.maximum(np.round((np.asarray(hi) - np.asarray(lo)) * size).astype(int), 2)
    return int(nz), int(ny), int(nx)


def animations(P, seed: int, light: str) -> dict:
    """{setting: frame function} of the temporal study's plume animations for ``P`` in one
    configuration: the plume simulated with ``seed`` (the seed changes the density), lit by
    ``light`` (:func:`avsm_dr.evaluation.light_variants` of the :data:`LIGHT` scene)."""
    from avsm_dr.fluid import simulate_plume_sequence
    seq = simulate_plume_sequence(plume_shape(P["size"]), frames=P["frames"], start=P["start_steps"],
                                  seed=seed) * np.float32(P["density_scale"])
    base = S.plume_scene(seq.max(axis=0), DirectionalLight(direction=LIGHT), 2, seed)
    base = dataclasses.replace(base, light=light_variants(base)[light])
    anim = {"smoke": lambda: S.smoke(base, seq, 0), "light": lambda: turning(base, seq[-1], P["light_step"])}
    return {s: anim[s]() for s in P["settings"]}


def turning(base: Scene, density, step: float):
    """``frame(t)`` of the ``light`` animation: the light turned by ``t * step`` degrees about
    the vertical axis through the plume box's centre (a directional light: its direction, as
    :func:`experiments.temporal.scenes.light`; a spot light: its position and direction)."""
    if isinstance(base.light, DirectionalLight):
        return S.light(base, density, step, 0)
    c = 0.5 * (np.asarray(S.PLUME_BOX[0], np.float64) + np.asarray(S.PLUME_BOX[1], np.float64))
    li = base.light

    def frame(t):
        a = t * step
        spot = dataclasses.replace(li, position=c + S.rotate_y(li.position - c, a),
                                   direction=S.rotate_y(li.direction, a))
        return S.Frame(dataclasses.replace(base, density=density, light=spot), base.bbox, base.receivers, None)
    return frame


# ========================================================================== run
def _render_setting(mi, cls, frame_fn, P, bar, cache: dict):
    """Every size in every frame of one animation: images, bytes, times, choices; ``cache``
    (:func:`frame_key` -> renders) holds the configuration's renders across its animations."""
    F, budgets = P["frames"], P["budgets"]
    f0 = frame_fn(0)
    choices, configs = {}, {}          # res -> {kind: [choice per budget]}, res -> {label: (kind, params)}
    for res in P["resolutions"]:
        sc = Scene("calibration", f0.scene.light, np.zeros((0, 3)), density=f0.scene.density, bbox=S.PLUME_BOX)
        seg = capture(sc, resolution=res, method="march", order="depth").segments
        choices[res], configs[res] = {}, {}
        for kind in P["kinds"]:
            cal = calibrate(kind, seg, budgets)
            choices[res][kind] = [choose(cal, b) for b in budgets]
            for value, params, _, _ in choices[res][kind]:
                configs[res].setdefault(label(kind, value), (kind, params))
    bar.total += F * (1 + sum(len(c) + 1 for c in configs.values()))
    bar.refresh()
    integs = {(res, lab): R.integrator(mi, cls, kind, params, res, P["march_steps"])
              for res in P["resolutions"] for lab, (kind, params) in configs[res].items()}
    noise_integ = {res: R.integrator(mi, cls, "exact", {}, res, P["march_steps"]) for res in P["resolutions"]}
    imgs, nbytes, sparse, curves, secs, refs = {}, {}, {}, {}, {}, []
    for t in range(F):
        frame = frame_fn(t)
        done = cache.setdefault(frame_key(frame), {})      # this scene's renders so far, in any animation
        scene = R.load_scene(mi, frame, P["image"])
        if "reference" not in done:
            done["reference"] = R.reference_halves(mi, scene, P["reference_spp"], (10_000 + 2 * t, 10_001 + 2 * t))
        refs.append(done["reference"])
        bar.update(1)
        for res in P["resolutions"]:
            for lab in configs[res]:           # exact first (``kinds`` starts with it): the curves' reference
                if (res, lab) not in done:
                    done[(res, lab)] = _render_one(mi, scene, integs[(res, lab)], P, done, res, lab)
                imgs[(t, res, lab)], nbytes[(t, res, lab)], sparse[(t, res, lab)], curves[(t, res, lab)], \
                    secs[(t, res, lab)] = done[(res, lab)]
                bar.update(1)
            if (res, "exact@seed2") not in done:
                done[(res, "exact@seed2")] = R.render(mi, scene, noise_integ[res], P["spp"], P["render_seed"] + 1)
            imgs[(t, res, "exact@seed2")] = done[(res, "exact@seed2")]
            bar.update(1)
    return dict(choices=choices, configs=configs, imgs=imgs, nbytes=nbytes, sparse=sparse, curves=curves, secs=secs,
                refs=refs)


def _render_one(mi, scene, integ, P, done: dict, res: int, lab: str) -> tuple:
    """(image, dense and sparse bytes per texel, curve metrics, seconds) of one render; the
    first render of a resolution is ``exact``'s, whose curve (kept in ``done``) the others'
    curve metrics compare against."""
    t0 = time.perf_counter()
    img = R.render(mi, scene, integ, P["spp"], P["render_seed"])
    sec = time.perf_counter() - t0
    seg, rep = integ.last_map
    integ.last_map = None
    if ("curve", res) not in done:
        if integ.kind != "exact":
            raise RuntimeError("image_budget: exact must be the first configuration of a resolution")
        done[("curve", res)] = (R.exact_curve(mi, seg, rep), seg.counts)
        return img, integ.bytes_per_texel, integ.sparse_bytes, R.curve_metrics(mi, seg, rep, None), sec
    ref_curve, ref_counts = done[("curve", res)]
    if not np.array_equal(seg.counts, ref_counts):
        raise RuntimeError(f"image_budget: {lab}'s capture differs from exact's at {res}^2")
    return img, integ.bytes_per_texel, integ.sparse_bytes, R.curve_metrics(mi, seg, rep, ref_curve), sec


def frame_key(frame) -> tuple:
    """Identity of a frame's scene: its density's digest and its light's class and numbers
    (to 1e-12).  The ``light`` animation's frame 0 is the ``smoke`` animation's last frame
    (same density, light not yet turned): :func:`_render_setting` renders it once."""
    li = frame.scene.light
    nums = np.concatenate([np.atleast_1d(np.asarray(v, np.float64)).ravel() for v in dataclasses.astuple(li)])
    digest = hashlib.sha1(np.ascontiguousarray(frame.scene.density).tobytes()).hexdigest()
    return digest, type(li).__name__, tuple(np.round(nums, 12).tolist())


def _rows(setting, config, out, P):
    """data.csv rows of one animation in one configuration (label ``config``; module
    docstring) and its display white."""
    F, budgets, resolutions = P["frames"], P["budgets"], P["resolutions"]
    imgs, refs = out["imgs"], out["refs"]
    ref = [0.5 * (a + b) for a, b in refs]
    white = R.white(ref[0])
    finest = resolutions[-1]
    noise = [R.flip(a, b, white) for a, b in refs]
    se = [float(np.sqrt(np.mean(((a - b) / 2) ** 2)) / white) for a, b in refs]
    flips = {}

    def f(key_a, img_a, key_b, img_b):
        k = (key_a, key_b)
        if k not in flips:
            flips[k] = R.flip(img_a, img_b, white)
        return flips[k]
    rows = []
    for t in range(F):
        for res in resolutions:
            ex = imgs[(t, res, "exact")]
            spatial = f(("ref", t), ref[t], (t, res, "exact"), ex)
            resolution = f((t, finest, "exact"), imgs[(t, finest, "exact")], (t, res, "exact"), ex)
            rnoise = f((t, res, "exact"), ex, (t, res, "exact@seed2"), imgs[(t, res, "exact@seed2")])
            for bi, budget in enumerate(budgets):
                for kind in P["kinds"]:
                    value, params, cal_bytes, fits = out["choices"][res][kind][bi]
                    lab = label(kind, value)
                    img = imgs[(t, res, lab)]
                    row = dict(setting=setting, config=config, frame=t, resolution=res, budget=budget, kind=kind,
                               label=lab,
                               size_param=describe(kind)["size"] or "", size=value if value is not None else "",
                               fits=fits, calibrated_bytes=cal_bytes, bytes_per_texel=out["nbytes"][(t, res, lab)],
                               flip=f(("ref", t), ref[t], (t, res, lab), img),
                               flip_compression=f((t, res, "exact"), ex, (t, res, lab), img),
                               flip_spatial=spatial, flip_resolution=resolution, flip_render_noise=rnoise,
                               flip_reference_noise=noise[t], reference_se=se[t],
                               mean_signed_compression=float(np.mean(img - ex) / white))
                    if t == 0:
                        row.update(flicker=float("nan"), flicker_compression=float("nan"))
                    else:
                        prev, prev_ex = imgs[(t - 1, res, lab)], imgs[(t - 1, res, "exact")]
                        row.update(flicker=float(np.mean(np.abs((img - ref[t]) - (prev - ref[t - 1]))) / white),
                                   flicker_compression=float(np.mean(np.abs((img - ex) - (prev - prev_ex)))) / white)
                    row["render_s"] = out["secs"][(t, res, lab)]
                    row.update(order="depth", bytes=out["sparse"][(t, res, lab)],
                               bytes_dense=out["nbytes"][(t, res, lab)], **out["curves"][(t, res, lab)])
                    rows.append(row)
    return rows, white


def findings(rows, P, whites=None) -> tuple[dict, list[dict]]:
    """findings.json and map.csv's rows from data.csv's rows (:mod:`.analysis`): per animation
    and resolution the arrays of :mod:`.analysis` with one entry per configuration (its mean
    over frames), the threshold with its interval over configurations, and the claim that the
    threshold kind's compression is below the noise (:func:`avsm_dr.stats.claim`).  A kind's
    size at a budget can differ between configurations (its bytes follow the content); the
    ``label`` of a threshold or map cell is the most common one.  ``whites``: the display white
    per (configuration, animation), reported under ``reference`` (None: not reported, as when
    the findings are recomputed from data.csv, which does not hold it)."""
    budgets, ks, T, r0 = P["budgets"], P["kinds"], P["frames"], P["resolutions"][0]
    cfgs = [Configuration(s, li).label for s, li in P["configs"]]
    out = {"definition": ("compression invisible at a budget: FLIP(render with the kind, render with exact; same "
                          "resolution and seed) below the FLIP between the reference's two independent halves, each a "
                          "mean over frames, then over configurations; threshold: the smallest budget at which some "
                          "kind is invisible there and at every larger budget of the grid, and the cheapest such kind "
                          "(least stored bytes)"),
           "tonemap": f"sRGB(min(I / S, 1)), S = the {R.WHITE_PERCENTILE}th percentile of frame 0's reference per "
                      f"animation and configuration; FLIP LDR, 67 pixels per degree",
           "intervals": ("threshold: bootstrap 95 % percentile over configurations (each one's mean over its frames); "
                         "claim: avsm_dr.stats.claim, ratio of mean compression FLIP to mean noise FLIP, "
                         "configurations resampled, then frames within each"),
           "reference": {}, "thresholds": {}, "thresholds_vs_render_noise": {}, "flicker": {}, "curves": {},
           "metrics": ("claims (thresholds, the map): FLIP of rendered frames, the study's subject (receiver RMSE "
                       "does not apply: the image integrates the light's T over every pixel's view ray); the "
                       "maps' curve metrics (depth_l2, curve_signed_mean, curve_leak_share vs the exact curve) "
                       "per row and under 'curves', not used by the claims"),
           "configurations": cfgs, "n_configs": len(cfgs), "indicative": len(cfgs) < MIN_CONFIGS}
    cells = []
    for setting in P["settings"]:
        idx = {(r["config"], r["resolution"], r["kind"], r["budget"], r["frame"]): r
               for r in rows if r["setting"] == setting}

        def frames(c, res, k, b, key):
            return np.array([idx[(c, res, k, b, t)][key] for t in range(T)], np.float64)
        ref_noise = np.array([frames(c, r0, ks[0], budgets[0], "flip_reference_noise") for c in cfgs])   # (C, T)
        ref_se = np.array([frames(c, r0, ks[0], budgets[0], "reference_se") for c in cfgs])
        out["reference"][setting] = dict(
            integrator="volpath, max_depth 2", spp_per_half=P["reference_spp"],
            white=None if whites is None else {c: whites[(c, setting)] for c in cfgs},
            noise_flip_mean=float(ref_noise.mean()),
            noise_flip_per_config=dict(zip(cfgs, ref_noise.mean(axis=1).tolist())),
            se_rms_over_white=float(ref_se.mean()))
        for key in ("thresholds", "thresholds_vs_render_noise", "flicker", "curves"):
            out[key][setting] = {}
        for res in P["resolutions"]:
            comp = np.array([[[frames(c, res, k, b, "flip_compression").mean() for c in cfgs] for b in budgets]
                             for k in ks])
            nb = np.array([[[frames(c, res, k, b, "bytes_per_texel").mean() for c in cfgs] for b in budgets]
                           for k in ks])
            fits = np.array([[[idx[(c, res, k, b, 0)]["fits"] for c in cfgs] for b in budgets] for k in ks], bool)
            labels = [[Counter(idx[(c, res, k, b, 0)]["label"] for c in cfgs).most_common(1)[0][0] for b in budgets]
                      for k in ks]
            for key, col in (("thresholds", "flip_reference_noise"),
                             ("thresholds_vs_render_noise", "flip_render_noise")):
                noise = np.array([frames(c, res, ks[0], budgets[0], col).mean() for c in cfgs])
                s = A.summarise(comp, nb, fits, noise, budgets, ks, labels, P["n_boot"], MIN_CONFIGS)
                out[key][setting][str(res)] = _threshold(s["threshold"], cfgs, ks, budgets, frames, res, col, P)
                if key == "thresholds":
                    summary = s
            once = {(r["config"], r["label"], r["frame"]): r for r in idx.values() if r["resolution"] == res}
            by_label = {}
            for (_, lab, _), r in once.items():       # a configuration's rows agree at every budget
                by_label.setdefault(lab, []).append(r)
            cur = {lab: {k: float(np.mean([r[k] for r in v])) for k in CURVE_COLUMNS} for lab, v in by_label.items()}
            fl = {lab: float(np.mean([r["flicker_compression"] for r in v if r["frame"] > 0]))
                  for lab, v in by_label.items()}
            out["curves"][setting][str(res)], out["flicker"][setting][str(res)] = cur, fl
            for c in summary["cells"]:
                cells.append(dict(setting=setting, resolution=res, **c, n_configs=len(cfgs),
                                  best_flicker_compression=fl.get(c["best_label"], float("nan")),
                                  threshold=c["budget"] == summary["threshold"]["bytes"],
                                  best_depth_l2=cur.get(c["best_label"], {}).get("depth_l2", float("nan"))))
    out["map"] = cells
    out["headline"] = {f"{s} {res}^2": _threshold_line(out["thresholds"][s][str(res)])
                       for s in P["settings"] for res in P["resolutions"]}
    return out, cells


def _threshold(thr: dict, cfgs, ks, budgets, frames, res, noise_col: str, P) -> dict:
    """A threshold of :func:`.analysis.summarise` with its configurations named, how many of
    them have the same threshold on their own (``agreement``; "every configuration" only from
    :data:`MIN_EVERY` of them) and ``claim``: whether the threshold kind's compression FLIP is
    below the noise FLIP at the threshold budget, :func:`avsm_dr.stats.claim` of the per-frame
    values (mean / mean, ratio < 1; None when not reached or the kind is ``exact``)."""
    own = dict(zip(cfgs, thr["per_config"]))
    same = sum(v == thr["bytes"] for v in own.values())
    agreement = ("the same in every configuration" if same == len(cfgs) and len(cfgs) >= MIN_EVERY
                 else f"the same in {same} of {len(cfgs)} configurations")
    cl = None
    if thr["reached"] and thr["kind"] != "exact":
        k, b = thr["kind"], budgets.index(thr["bytes"])
        r = claim([frames(c, res, k, budgets[b], "flip_compression") for c in cfgs],
                  [frames(c, res, ks[0], budgets[0], noise_col) for c in cfgs], statistic="mean", compare="ratio",
                  configs=cfgs, n_boot=P["n_boot"])
        cl = {key: r[key] for key in ("estimate", "low", "high", "holds_pooled", "holds_in_every_configuration",
                                      "n_configs")}
        cl.update(per_config={p["config"]: p["estimate"] for p in r["per_config"]}, verdict=_verdict(r),
                  indicative=r["n_configs"] < MIN_CONFIGS, statistic="mean compression FLIP / mean noise FLIP")
    return dict(thr, per_config=own, agreement=agreement, claim=cl, interval_unit="configuration")


def _verdict(r: dict) -> str:
    """A claim's verdict (the rule of ``error_curves``): "every configuration" only from
    :data:`MIN_EVERY` configurations."""
    if r["holds_in_every_configuration"] and r["n_configs"] >= MIN_EVERY:
        return "holds in every configuration"
    if r["holds_pooled"]:
        return "holds pooled"
    return "does not hold" if r["low"] > r["below"] else "inconclusive"


def _threshold_line(thr: dict) -> str:
    """findings.json's headline line of a threshold: budget, label, stored bytes and interval."""
    ci = thr["interval"]

    def b(v):
        return "beyond the grid" if v is None else f"{v:g}"
    note = ", indicative" if thr["indicative"] else ""
    n = f"{thr['n_configs']} configurations"
    if not thr["reached"]:
        return f"compression visible at every budget (interval [{b(ci['low'])}, {b(ci['high'])}], {n}{note})"
    cl = f"; below the noise: {thr['claim']['verdict']}" if thr["claim"] else ""
    return (f"{thr['bytes']:g} B/texel, {thr['label']} ({thr['stored_bytes']:.1f} B stored) "
            f"[{b(ci['low'])}, {b(ci['high'])}] over {n}{note}; {thr['agreement']}{cl}")


def _compute(res, P: dict) -> dict:
    t_start = time.perf_counter()
    mi = R.mitsuba()
    cls = R.recording_class(mi)
    rows, whites, frames0 = [], {}, {}
    bar = tqdm(total=0, desc="image_budget", unit="render")     # grows as each animation's configurations are known
    for ci, (seed, light) in enumerate(P["configs"]):
        cfg = Configuration(seed, light).label
        anims, cache = animations(P, seed, light), {}
        for setting in P["settings"]:
            bar.set_description(f"image_budget {cfg} {setting} ({ci + 1}/{len(P['configs'])})")
            out = _render_setting(mi, cls, anims[setting], P, bar, cache)
            r, whites[(cfg, setting)] = _rows(setting, cfg, out, P)
            rows += r
            if ci == 0:                  # the figures' images: the first configuration's frame 0
                finest = P["resolutions"][-1]
                frames0[setting] = dict(reference=0.5 * (out["refs"][0][0] + out["refs"][0][1]),
                                        images={lab: out["imgs"][(0, finest, lab)] for lab in out["configs"][finest]})
    bar.close()
    found, cells = findings(rows, P, whites)
    first = Configuration(*P["configs"][0]).label
    res.write_npz("frame0.npz", **{f"{s}__{k}": v.astype(np.float32) for s, d in frames0.items()
                                   for k, v in [("reference", d["reference"])] + list(d["images"].items())})
    write_data(res, dict(rows=rows, tables={"map.csv": cells}, findings=found))   # before the figures
    from . import plots
    plots.plot_all(res, rows, found, cells, frames0, {s: whites[(first, s)] for s in P["settings"]}, P)
    found["run_seconds"] = time.perf_counter() - t_start
    summary = dict(found["headline"], reference_noise_flip={s: round(v["noise_flip_mean"], 4)
                                                           for s, v in found["reference"].items()},
                   run_seconds=round(found["run_seconds"], 1))
    return dict(rows=rows, tables={"map.csv": cells}, findings=found, summary=summary)

def params_from_rows(rows: list[dict]) -> dict:
    """The parameters :func:`findings` and the figures read, from ``data.csv``'s rows (typed,
    :func:`experiments._replot.typed`): animations, configurations and kinds in row order,
    ``frames``, sorted ``resolutions`` and ``budgets``; ``n_boot`` of the full run."""
    import re
    if not rows:
        raise ValueError("rows: expected data.csv's rows, got none")
    configs = []
    for c in dict.fromkeys(r["config"] for r in rows):
        m = re.fullmatch(r"s(\d+)-(\w+)", str(c))
        if not m or Configuration(int(m[1]), m[2]).label != c:
            raise ValueError(f"rows: config {c!r} is not a configuration label (s<seed>-<light>)")
        configs.append([int(m[1]), m[2]])
    return dict(settings=list(dict.fromkeys(r["setting"] for r in rows)), configs=configs,
                frames=max(int(r["frame"]) for r in rows) + 1,
                resolutions=sorted({int(r["resolution"]) for r in rows}),
                budgets=sorted({r["budget"] for r in rows}), kinds=list(dict.fromkeys(r["kind"] for r in rows)),
                n_boot=FULL["n_boot"], reference_spp=None)


def redraw(res, rows: list[dict]) -> None:
    """``budget_map.png`` and ``flip_vs_bytes.png`` from a run's ``data.csv`` rows (typed by
    :func:`experiments._replot.typed`; the map recomputed by :func:`findings`), as the run drew
    them: ``python -m experiments._replot image_budget data.csv --out DIR`` (the committed full
    run: ``docs/research/image_budget/run/data.csv.gz``).  ``frames.png`` needs the run's images
    (``frame0.npz``) and is not redrawn."""
    from . import plots
    P = params_from_rows(rows)
    _, cells = findings(rows, P)
    plots.budget_map(res, cells, P)
    plots.flip_vs_bytes(res, rows, P)


def _headline(s: dict) -> list[str]:
    """Per animation and resolution: the budget from which compression is not visible (FLIP
    within the reference's noise) with its interval; the reference's own noise."""
    out = [f"{k}: compression invisible from {v}" if "B/texel" in v else f"{k}: {v}"
           for k, v in s.items() if isinstance(v, str)]
    noise = s.get("reference_noise_flip", {})
    if noise:
        out.append("reference noise (FLIP): " + ", ".join(f"{k} {num(v)}" for k, v in noise.items()))
    return out + [f"run time {num(s.get('run_seconds'))} s"]


def _config_arg(text: str) -> list:
    """``SEED:LIGHT`` of the command line as ``[seed, light]``."""
    seed, _, light = str(text).partition(":")
    if not seed.isdigit() or not light:
        raise ValueError(f"configs: expected SEED:LIGHT (e.g. 0:dir_a), got {text!r}")
    return [int(seed), light]


STUDY = Study("image_budget", "How many bytes per texel a viewer needs: Mitsuba images per kind, budget and "
              "resolution against a converged reference, FLIP and flicker", REPRODUCES, FULL, QUICK, _compute,
              resolve=_resolve,
              writes=("data.csv (one row per animation, configuration, frame, resolution, budget and kind)",
                      "map.csv (best kind per animation, resolution and budget)", "findings.json", "frame0.npz"),
              options=(Option("kinds", "kinds compared (exact is always added)", nargs="+", metavar="KIND"),
                       Option("resolutions", "shadow-map resolutions", type=int, nargs="+", metavar="N"),
                       Option("settings", "animations: smoke, light", nargs="+", metavar="NAME"),
                       Option("configs", "configurations SEED:LIGHT (e.g. 0:dir_a 1:spot; lights: "
                              + ", ".join(LIGHTS) + ")", type=_config_arg, nargs="+", metavar="SEED:LIGHT")),
              headline=_headline)
run = STUDY.run

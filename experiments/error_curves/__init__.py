"""Error of every representation against the true transmittance, decomposed, per built-in
scene, over seeds and lights, with the papers' claims tested (``findings.json``).

What is measured (module :mod:`avsm_dr.evaluation.probe` states the formulas):

* **Decomposition** of each receiver's error ``T_rep - T`` into compression (the
  representation vs the exact curve of the same segments, same bilinear lookup), capture
  (the exact curve vs the true integral along the texel's own ray) and spatial (texel rays
  and the filter vs the receiver's own light path); ``T`` is a float64 quadrature of the
  same density plus the analytic particles, hair and blockers.  Mitsuba ratio tracking
  (``spp`` paths, standard error) checks the truth in the base configuration.
* **Signed and tail errors** (:func:`avsm_dr.metrics.error_stats`): mean signed error
  (> 0: light leaking), the shares leaking / over-darkening by > 0.02, p99 / p99.9 of
  |error| over thousands of receivers, and the optical-depth error
  (:func:`experiments._tau.optical_depth_error`).
* **Receiver sets** (:mod:`avsm_dr.receivers`): in-volume receivers drawn by contribution,
  surface receivers (wall / ground / table top), and the scene's own uniform set (base
  configuration only), in separate rows (column ``receivers``).
* **Configurations**: every registered kind (``ad.kinds()``); in the base configuration
  (first seed, the scene's light) each kind's whole size sweep (``ad.configurations``),
  next to per-texel depth ranges for the kinds whose schema has ``depth_range``; in every
  configuration (4 seeds x 2 directional lights, and a spot light with 2 seeds) the headline
  sizes and the sizes the claims name, each with every value of its tuning parameters
  (choice parameters of the schema, and :data:`TUNING`); scenes with opaque blockers
  twice, ``opaque='inline'`` and ``'separate'`` (:mod:`avsm_dr.capture.opaque_map`).
* **Depth range** (scene :data:`RANGE_SCENE`): the global range stretched 8x, and a faint
  segment behind the content of every texel (depth spread within the texel 8x / 32x).
* **Claims** (:mod:`.findings`): paired bootstrap intervals per configuration and
  pooled (:func:`avsm_dr.stats.claim`), and whether each holds in every configuration.
"""

from __future__ import annotations

import dataclasses
import itertools
import shutil
import time

import numpy as np

from avsm_dr import allows, build, configurations, describe
from avsm_dr import kinds as all_kinds
from avsm_dr.metrics import error_stats
from avsm_dr.segments import Segments
from . import findings as F
from .cost import BUILD_WORK
from .._study import Option, Study, write_data
from .._tau import optical_depth_error
from .._two_metric import texel_blocks
from .labels import ORDERS, PRECISIONS, TUNING, with_size, label, order_dependent, tuned  # noqa: F401  (re-exported)
from avsm_dr.evaluation import Built, Probe, SubsetBuilder, curve_values, depth_l2, light_variants

#: What this study reproduces (a paper's figure or table, or the guide's section).
REPRODUCES = (
    'Salvi et al., "Adaptive Volumetric Shadow Maps", EGSR 2010, figures 5-6 and the claims of '
    'sections 3-5: error of AVSM, FOM, OSM, DSM, moments against node / coefficient count and '
    'bytes per texel on the built-in scenes, the depth-range sweep, and findings.json.'
)


SCENES = list(F.SCENE_NAMES)
QUICK_SCENES = ["plume", "hair_and_smoke", "smoke_over_table"]
#: Scene of the depth-range study, its global-range stretches and faint-segment stretches.
RANGE_SCENE = "plume"
RANGE_STRETCH = (8,)
FAINT_STRETCH = (8, 32)
LIGHTS = ("dir_a", "dir_b", "spot")
#: The spot light runs with the first SPOT_SEEDS seeds (the directional lights with all four).
SPOT_SEEDS = 2
#: Work estimate above which one build marks a kind slow (offline references such as a
#: dynamic-programming optimum): for the rest of that configuration (one cell of the sweep)
#: it is built only at its headline setting, in the base configuration (``slow_kinds`` in
#: findings.json: the largest estimate per kind).  The estimate is the kind's declared cost
#: model in :data:`.cost.BUILD_WORK` on the segments built, never a clock, so the rows do not
#: depend on the machine's load; 3.6e8 units (about 2.6 CPU seconds on the development
#: machine) selects the rows an idle run selected with its former 3 CPU-second limit.
#: Kinds whose schema says ``offline`` run in the base configuration of each scene only.
SLOW_WORK = 3.6e8
#: Mitsuba runs in float32: a path that meets no tentative collision returns T = 1 exactly
#: (standard error 0) where the truth is 1 - 1e-9; differences below this are rounding.
MITSUBA_FLOOR = 1e-6
#: Largest |T| difference between a build on the probes' texels and one on the whole map
#: (float32 kernels on the same segments: rounding only).
SUBSET_TOLERANCE = 1e-5
#: Parameters of the full and the quick run (``scenes`` / ``kinds``: options; ``kinds`` None:
#: every registered kind; ``variants`` is filled in from the kinds).
FULL = dict(scenes=SCENES, resolution=256,
            configs=[[s, li] for s in range(4) for li in LIGHTS if li != "spot" or s < SPOT_SEEDS], kinds=None,
            n_volume=4096, n_surface=1024, n_decomp=512, spp=256, filter="bilinear",
            truth="raymarch, step 1/8 voxel, float64", tuning={k: list(v) for k, v in TUNING.items()},
            variants=None, range_stretch=list(RANGE_STRETCH), faint_stretch=list(FAINT_STRETCH), n_boot=1000)
QUICK = dict(FULL, scenes=QUICK_SCENES, resolution=64, configs=[[0, "dir_a"], [1, "spot"]], n_volume=512,
             n_surface=256, n_decomp=128, spp=32, n_boot=200)


def march_step(scene, fraction):
    """``fraction`` of the smallest voxel side of the scene's grid (None without a grid);
    used by :mod:`.curves` for its march captures."""
    if scene.density is None:
        return None
    lo, hi = (np.asarray(b, float) for b in scene.bbox)
    return float(np.min((hi - lo) / np.asarray(scene.density.shape[::-1]))) * fraction


# =================================================================== variants
def variants(kind: str, quick: bool, sweep: bool) -> list[tuple[dict, bool]]:
    """(parameters, in_sweep) of ``kind`` to build, the headline first: the headline size and
    the sizes the claims name, each with every valid combination of :func:`tuned` values (in
    quick mode only the combinations the claims name), and the headline in each storage
    precision of :data:`PRECISIONS` the kind offers; with ``sweep`` also every size of
    ``ad.configurations(kind, quick)`` at default tuning and with ``depth_range='texel'``
    where the schema has it (``in_sweep`` True: built on the whole map, for the bytes)."""
    d = describe(kind)
    size = d["size"]
    head = with_size(kind, d["headline"].get(size) if size else None)
    out = [(head, sweep)]
    if sweep:
        for p in configurations(kind, quick):
            out.append((dict(p), True))
            if "depth_range" in d["params"]:
                out.append((dict(p, depth_range="texel"), True))
    sizes = [d["headline"].get(size)] if size else [None]
    sizes += [v for v in F.claim_sizes().get(kind, ()) if v not in sizes]
    grid = tuned(kind)
    named = F.claim_settings()
    for v in sizes:
        for combo in itertools.product(*grid.values()):
            p = dict(with_size(kind, v), **dict(zip(grid, combo)))
            if not allows(kind, p):
                continue                                   # e.g. 6 trigonometric moments
            if not quick or label(kind, p) in named or not any(p[k] != head.get(k) for k in grid):
                out.append((p, False))
    for prec in PRECISIONS:                                # storage precision at the headline size
        if prec in d["precisions"]:
            out.append((dict(head, precision=prec), False))
    seen, uniq = set(), []
    for p, full in out:
        key = label(kind, p)
        if key not in seen:
            seen.add(key)
            uniq.append((p, full))
    return uniq


# ======================================================================= rows
def _stats_row(est, exact, truth) -> dict:
    """Compression statistics (vs the exact curve; the historical column names), total ones
    (vs the truth, prefix ``total_``) and optical-depth errors vs the truth (``tau_*``)."""
    r = error_stats(est, exact)
    r["compression_tau_rmse"] = optical_depth_error(est, exact)["tau_rmse"]
    r.update({f"total_{k}": v for k, v in error_stats(est, truth).items()
              if k not in ("nan_count", "inf_count", "bounds_violations", "n")})
    r.update({k: v for k, v in optical_depth_error(est, truth).items() if k != "tau_floor"})
    return r


def _rms(x) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if np.size(x) else float("nan")


def _row(head, probe, est, exact, mitsuba) -> dict:
    t = probe.terms(est, exact)
    r = dict(head, **_stats_row(est, exact, probe.truth))
    r.update(compression_rms=_rms(t["compression"]), capture_rms=_rms(t["capture"]),
             spatial_rms=_rms(t["spatial"]), total_rms_decomp=_rms(t["total_decomp"]),
             capture_mean=float(np.mean(t["capture"])) if t["capture"].size else float("nan"),
             spatial_mean=float(np.mean(t["spatial"])) if t["spatial"].size else float("nan"),
             decomp_n=probe.n_decomp)
    if mitsuba is not None:
        mean, se = mitsuba
        r.update(total_rmse_vs_mitsuba=_rms(est - mean), reference_se_rms=_rms(se))
    return r


def _reference_row(head, probe, mitsuba) -> dict:
    """The truth against Mitsuba ratio tracking (rms difference, rms standard error, the
    share within 3 standard errors)."""
    mean, se = mitsuba
    diff = probe.truth - mean
    return dict(head, method="truth_vs_mitsuba", param="", rmse=_rms(diff), reference_se_rms=_rms(se),
                mean_error=float(np.mean(diff)),
                within_3_stderr=float(np.mean(np.abs(diff) <= 3 * np.maximum(se, MITSUBA_FLOOR))))


# ===================================================================== config
@dataclasses.dataclass
class _Config:
    scene_name: str
    scene: object
    label: str          # e.g. "s0-dir_a"
    base: bool          # the first seed with the scene's own light: size sweep, Mitsuba, uniform set


def _run_config(cfg: _Config, P: dict, rows: list, store: dict, quick: bool, state: dict):
    from avsm_dr import capture, groundtruth, receivers
    scene = cfg.scene
    seed = int(cfg.label.split("-")[0][1:])
    sets = receivers.receiver_sets(scene, P["n_volume"], P["n_surface"], seed=seed)
    if not cfg.base:
        sets.pop("uniform", None)
    caps = {"inline": capture(scene, resolution=P["resolution"], order="depth")}
    if scene.blockers:
        caps["separate"] = capture(scene, resolution=P["resolution"], opaque="separate", order="depth")
    probes = {s: Probe(caps["inline"], scene, p, P["n_decomp"]) for s, p in sets.items()}
    mitsuba = {}
    if cfg.base and scene.density is not None:
        for s, p in sets.items():
            mitsuba[s] = groundtruth.transmittance(scene, p, spp=P["spp"], seed=1)
    head0 = dict(scene=cfg.scene_name, config=cfg.label, seed=seed, light=cfg.label.split("-", 1)[1],
                 base=cfg.base, resolution=P["resolution"], study="main")
    for mode, cap in caps.items():
        pr = {s: probe.with_capture(cap) for s, probe in probes.items()}
        sub = SubsetBuilder(cap.segments, np.concatenate([p.tex.ravel() for p in pr.values()]),
                            cap.opaque_depth)
        exact_rep = build("exact", cap.segments)
        ex = {s: p.lookup(exact_rep) for s, p in pr.items()}
        # depth-uniform L2 on the non-empty texels built (the probes' texels), 8 x 8 tiles
        ex_curve = curve_values(build("exact", sub.segments), sub.segments)
        l2_texels = sub.texels[sub.segments.counts > 0]
        state["blocks"][(cfg.scene_name, cfg.label, mode)] = texel_blocks(l2_texels, cap.width)
        for s, p in pr.items():
            nearest = p.tex[np.argmax(p.weights, axis=0), np.arange(p.k)]
            state["blocks"][(cfg.scene_name, cfg.label, mode, s)] = texel_blocks(nearest, cap.width)
            if s in mitsuba and mode == "inline":
                rows.append(_reference_row(dict(head0, receivers=s, n=p.k, opaque=mode, order="-"), p,
                                           mitsuba[s]))
        base = cfg.base and mode == "inline"

        def one(kind, i, params, whole, order, segments, subb):
            """Build one variant on ``segments`` (insertion order ``order``), its rows and errors."""
            size = describe(kind)["size"]
            name = label(kind, params)
            whole = whole or kind in state["whole_map"]
            c0 = time.process_time()
            rep = exact_rep if kind == "exact" else build(kind, segments, **params) if whole \
                else subb.build(kind, params)
            est = {s: p.lookup(rep) for s, p in pr.items()}
            cpu = time.process_time() - c0
            if order == "depth":
                work = BUILD_WORK[kind](segments if whole else subb.segments, params) if kind in BUILD_WORK else 0.0
                if work > SLOW_WORK:
                    state["slow"][kind] = max(work, state["slow"].get(kind, 0.0))
                elif base and i == 0 and kind != "exact":
                    _check_subset(kind, params, est, subb, pr, cfg.scene_name, state)
            brep = rep.rep if isinstance(rep, Built) else rep
            l2 = depth_l2(brep, subb.segments, exact=ex_curve, per_texel=True) if isinstance(rep, Built) else \
                depth_l2(rep, segments, exact=ex_curve, texels=subb.texels, per_texel=True)
            head = dict(head0, method=kind, param=params.get(size, "") if size else "", setting=name,
                        opaque=mode, precision=params.get("precision") or "native",
                        bytes_per_texel=brep.nbytes_per_texel,
                        bytes_sparse=sparse_bytes(brep, segments), build_lookup_cpu_s=cpu,
                        texels_built=brep.n_texels,
                        **{_column(k): params.get(k, "") for k in _tuning_columns(P["kinds"])})
            head.update(order=order if order_dependent(kind) else "-", bytes=head["bytes_sparse"],
                        bytes_dense=head["bytes_per_texel"], depth_l2=_rms(l2))
            curve = base and whole and order == "depth" and name == label(kind, with_size(kind, params.get(size)))
            for s, p in pr.items():
                rows.append(_row(dict(head, receivers=s, n=p.k, curve=curve and s == "in_volume"),
                                 p, est[s], ex[s], mitsuba.get(s) if mode == "inline" else None))
                if s != "uniform":
                    store[(cfg.scene_name, cfg.label, name, mode, s, "main", order)] = \
                        (np.float32(est[s] - ex[s]), np.float32(est[s] - p.truth))
            state["l2"][(cfg.scene_name, cfg.label, name, mode, order)] = np.float32(l2)

        for kind in P["kinds"]:
            if describe(kind)["offline"] and not base:
                continue                                   # offline references: base configuration only
            for i, (params, whole) in enumerate(variants(kind, quick, sweep=base)):
                if kind in state["slow"] and not (base and i == 0):
                    continue                               # slow kinds: headline, base configuration only
                one(kind, i, params, whole, "depth", cap.segments, sub)
        dependent = [k for k in P["kinds"] if order_dependent(k) and k not in state["slow"]
                     and not (describe(k)["offline"] and not base)]
        for order in ORDERS[1:] if dependent else ():
            segs = _in_order(cap, order, scene, P["resolution"], mode, seed, cfg, state)
            subb = SubsetBuilder(segs, sub.texels, cap.opaque_depth)
            for kind in dependent:
                for i, (params, whole) in enumerate(variants(kind, quick, sweep=base)):
                    if (i == 0 or not quick) and params.get("precision") is None:
                        one(kind, i, params, whole, order, segs, subb)
        if cfg.scene_name == RANGE_SCENE and mode == "inline" and "in_volume" in pr:
            _depth_range(cap, sub, pr["in_volume"], ex["in_volume"], head0, rows, store, cfg, P["kinds"])


def _in_order(cap, order, scene, resolution, mode, seed, cfg, state):
    """The segments of ``cap`` in insertion order ``order`` (:data:`ORDERS`): reordered, or
    for 'submission' captured again in draw order; its segments per texel must be those of
    ``cap`` (the largest depth difference after sorting goes into ``state``)."""
    from avsm_dr import capture
    if order != "submission":
        return cap.segments.in_order(order, seed=seed if order == "random" else None)
    segs = capture(scene, resolution=resolution, opaque=mode, order="submission").segments
    if not np.array_equal(segs.counts, cap.segments.counts):
        raise RuntimeError(f"{cfg.scene_name}/{cfg.label}: the submission-order capture has other segment counts")
    a, b = cap.segments.sorted().numpy(), segs.sorted().numpy()
    state.setdefault("submission_check", {})[f"{cfg.scene_name}/{cfg.label}/{mode}"] = max(
        (float(np.max(np.abs(a[k] - b[k]))) if a[k].size else 0.0) for k in ("z0", "z1", "optical_depth"))
    return segs


def sparse_bytes(rep, segments) -> float:
    """Sparse bytes per texel of the whole map ``segments`` (``nbytes_sparse_per_texel``,
    docs/concepts.md "Bytes") for ``rep`` built on it or on a subset of its texels: a
    fixed-size kind's payload is the same in every texel, so ``1/8 + occupied share x
    payload``; a variable-size kind built on a subset: over the texels built (as
    ``bytes_per_texel``)."""
    if rep.n_texels == segments.n_texels or rep.variable_size:
        return float(rep.nbytes_sparse_per_texel)
    return 1 / 8 + float(np.count_nonzero(segments.counts)) / segments.n_texels * float(rep.texel_payload_bytes())


def _check_subset(kind, params, est, sub, probes, scene_name, state):
    """In the base configuration: a build on the probes' texels must give the whole-map
    lookups ``est`` (else the kind is built on the whole map from now on)."""
    b = sub.build(kind, params)
    diff = max(float(np.max(np.abs(p.lookup(b) - est[s]))) for s, p in probes.items())
    state["subset_check"][f"{scene_name}/{kind}"] = diff
    if diff > SUBSET_TOLERANCE:
        state["whole_map"].add(kind)


#: Row columns of the experiment itself; a tuning parameter of the same name becomes ``param_<name>``.
RESERVED = {"scene", "config", "seed", "light", "base", "resolution", "study", "method", "param", "setting",
            "opaque", "precision", "bytes_per_texel", "bytes_sparse", "build_lookup_cpu_s", "texels_built", "receivers",
            "n", "curve", "stretch", "order", "bytes", "bytes_dense", "depth_l2"}


def _column(name: str) -> str:
    return f"param_{name}" if name in RESERVED else name


def _tuning_columns(kind_names) -> list[str]:
    cols = []
    for k in kind_names:
        for name in tuned(k):
            if name not in cols:
                cols.append(name)
    return cols


def with_faint_segments(segments, stretch: float, optical_depth: float = 0.01):
    """Segments with one faint segment appended to every non-empty texel, at
    ``near_t + stretch (far_t - near_t)`` (its own bounds), of length ``0.01 (far_t - near_t)``
    and optical depth ``optical_depth``: the depth spread *within* a texel grows
    ``stretch`` times while T in front of ``far_t`` does not change."""
    h = segments.numpy()
    off, c = h["offsets"], segments.counts
    near, far = segments.texel_bounds()
    nz = np.nonzero(c > 0)[0]
    span = far[nz] - near[nz]
    z0f = near[nz] + stretch * span
    ins = off[1:][nz]                                   # insert at the end of each texel
    z0 = np.insert(h["z0"], ins, z0f)
    z1 = np.insert(h["z1"], ins, z0f + 0.01 * span)
    tau = np.insert(h["optical_depth"], ins, optical_depth)
    add = np.zeros(segments.n_texels + 1, np.int64)
    add[1:] = np.cumsum(c > 0)
    return Segments.from_arrays(off + add, z0, z1, optical_depth=tau, dtype=segments.dtype)


def _depth_range(cap, sub, probe, exact, head0, rows, store, cfg, kind_names):
    """Global range stretched (``study='global_range'``) and a faint segment behind every
    texel's content (``study='faint_segment'``), for the kinds the depth-range claims name
    (built on the probe's texels, global ranges from the whole map)."""
    near, far = cap.segments.bounds()
    todo = [(k, v) for k, v in F.RANGE_KINDS if k in kind_names]
    for stretch in RANGE_STRETCH:
        for kind, v in todo:
            p = dict(with_size(kind, v), near=near, far=near + (far - near) * stretch)
            _range_row(kind, p, sub, probe, exact, head0, rows, store, cfg, "global_range", stretch, cap.segments)
    for stretch in FAINT_STRETCH:
        faint = with_faint_segments(cap.segments, stretch)
        sub_f = SubsetBuilder(faint, sub.texels)
        ex_f = probe.lookup(sub_f.build("exact", {}))
        for kind, v in todo:
            ranges = ["global", "texel"] if "depth_range" in describe(kind)["params"] else [None]
            for dr_ in ranges:
                p = with_size(kind, v) if dr_ is None else dict(with_size(kind, v), depth_range=dr_)
                _range_row(kind, p, sub_f, probe, ex_f, head0, rows, store, cfg, "faint_segment", stretch, faint)


def _range_row(kind, p, subb, probe, exact, head0, rows, store, cfg, study, stretch, whole):
    """One row of the depth-range study: ``kind`` with ``p`` built by ``subb`` (a
    :class:`SubsetBuilder` of the segments ``whole``), in depth order."""
    rep = subb.build(kind, p)
    est = probe.lookup(rep)
    name = label(kind, p)
    size = describe(kind)["size"]
    r = dict(head0, study=study, stretch=stretch, method=kind, param=p.get(size, ""), setting=name,
             opaque="inline", receivers="in_volume", n=probe.k, bytes_per_texel=rep.rep.nbytes_per_texel,
             bytes_sparse=sparse_bytes(rep.rep, whole), depth_range=p.get("depth_range", ""))
    r.update(order="depth" if order_dependent(kind) else "-", bytes=r["bytes_sparse"], bytes_dense=r["bytes_per_texel"],
             depth_l2=depth_l2(rep.rep, subb.segments))
    r.update(error_stats(est, exact))
    rows.append(r)
    store[(cfg.scene_name, cfg.label, name, "inline", "in_volume", f"{study}_x{stretch}", "depth")] = \
        (np.float32(est - exact), np.float32(est - probe.truth))


# ======================================================================== run
def _cell(job: dict) -> dict:
    """One configuration (scene x seed x light) as an independent cell of the sweep
    (:func:`experiments._sweep.run_cells`): its rows, its error store and its state."""
    from avsm_dr import scenes as scene_lib
    P = job["P"]
    sc0 = scene_lib.get(job["scene"], seed=job["seed"])
    scene = dataclasses.replace(sc0, light=light_variants(sc0)[job["light"]])
    cfg = _Config(job["scene"], scene, f"s{job['seed']}-{job['light']}", job["base"])
    rows: list[dict] = []
    store: dict = {}
    state = {"slow": {}, "whole_map": set(job["whole_map"]), "subset_check": {}, "l2": {}, "blocks": {},
             "submission_check": {}}
    _run_config(cfg, P, rows, store, job["quick"], state)
    return dict(rows=rows, store=store, slow=state["slow"], whole_map=sorted(state["whole_map"]),
                subset_check=state["subset_check"], l2=state["l2"], blocks=state["blocks"],
                submission_check=state["submission_check"])


def _resolve(P: dict, quick: bool, **_) -> dict:
    """The scenes and kinds checked (kinds None: every registered kind), the variant labels."""
    from avsm_dr import scenes as scene_lib
    known = getattr(scene_lib, "SCENES", {})
    P["scenes"] = list(P["scenes"])
    for n in P["scenes"]:
        if n not in known:
            raise ValueError(f"scenes: unknown scene {n!r}; known: {sorted(known)}")
    P["kinds"] = list(all_kinds()) if P["kinds"] is None else list(P["kinds"])
    for k in P["kinds"]:
        if k not in all_kinds():
            raise ValueError(f"kinds: unknown kind {k!r}; known: {all_kinds()}")
    P["variants"] = {k: [label(k, p) for p, _ in variants(k, quick, True)] for k in P["kinds"]}
    return P


def _compute(res, P: dict, workers=None, address=None) -> dict:
    """The configurations as cells (through Ray with ``workers`` / ``address``, results equal
    the serial run's; finished cells cached under ``<out>/cells/`` so an interrupted run
    resumes), their rows, ``findings.json`` and the figures."""
    from .. import _sweep as sweep
    from .._common import cache_key
    quick, names, configs = res.quick, P["scenes"], P["configs"]
    if res.force:
        shutil.rmtree(res.dir / "cells", ignore_errors=True)
    t0 = time.perf_counter()
    jobs = [dict(scene=n, seed=s, light=li, base=[s, li] == configs[0], quick=quick, P=P)
            for n in names for s, li in configs]
    run_opts = dict(cache_dir=res.dir / "cells", key=dict(P=P, cache=cache_key()), workers=workers,
                    address=address)
    with sweep.pool(workers, address):
        # base configurations first: their subset checks decide which kinds the others build on the whole map
        base = sweep.run_cells(_cell, [dict(j, whole_map=[]) for j in jobs if j["base"]],
                               desc="error_curves (base)", **run_opts)
        whole = {j["scene"]: r["whole_map"] for j, r in zip([j for j in jobs if j["base"]], base)}
        rest = sweep.run_cells(_cell, [dict(j, whole_map=whole[j["scene"]]) for j in jobs if not j["base"]],
                               desc="error_curves", **run_opts)
    it_base, it_rest = iter(base), iter(rest)
    cells = [next(it_base) if j["base"] else next(it_rest) for j in jobs]
    rows = [r for c in cells for r in c["rows"]]
    store = {k: v for c in cells for k, v in c["store"].items()}
    l2 = {k: v for c in cells for k, v in c["l2"].items()}
    blocks = {k: v for c in cells for k, v in c["blocks"].items()}
    slow: dict = {}
    for c in cells:
        for k, v in c["slow"].items():
            slow[k] = max(v, slow.get(k, 0.0))
    elapsed = time.perf_counter() - t0
    summary = F.findings(store, rows, n_boot=P["n_boot"], l2=l2, blocks=blocks)
    summary.update(run_seconds=elapsed, slow_kinds=slow,
                   submission_max_difference={k: v for c in cells for k, v in c["submission_check"].items()},
                   whole_map_kinds={n: w for n, w in whole.items() if w},
                   subset_max_difference={k: v for c in base for k, v in c["subset_check"].items()})
    from . import plots as _error_plots
    write_data(res, dict(rows=rows, findings=summary))        # before the figures
    _error_plots.plot_all(res, rows, names)
    # the whole computation: cells, findings and figures (cells_seconds: the cells alone)
    summary.update(cells_seconds=elapsed, run_seconds=time.perf_counter() - t0)
    verdicts = F.summary_lines(summary)
    shutil.rmtree(res.dir / "cells", ignore_errors=True)     # complete: nothing left to resume
    return dict(rows=rows, findings=summary, summary=verdicts)

def _headline(s: dict) -> list[str]:
    """How many claims got each verdict, then one line per claim (findings.summary_lines):
    receiver-RMSE ratio ``estimate [low, high]``, depth-uniform L2 beside it, verdict,
    configurations and order; ids as in findings.json."""
    import collections
    import re
    verdicts = collections.Counter(m[1] for line in s.values()
                                   if (m := re.search(r": ([^:,]+), \d+ configs", line)))
    tally = ", ".join(f"{n} {v}" for v, n in verdicts.most_common())
    return ([f"{len(s)} claims: {tally}; per claim: receiver-RMSE ratio [95 % interval], depth-uniform L2, verdict"]
            + [f"{cid}: {line}" for cid, line in s.items()])


STUDY = Study(
    "error_curves", "Error of every representation against the true transmittance, decomposed, per scene",
    REPRODUCES, FULL, QUICK, _compute, resolve=_resolve, sweep=True,
    writes=("data.csv (one row per scene, configuration, receiver set and variant)", "findings.json (the claims)"),
    options=(Option("scenes", "built-in scenes to run (default: the mode's)", nargs="+", metavar="SCENE"),
             Option("kinds", "representation kinds to build (default: every registered one)", nargs="+",
                    metavar="KIND")), headline=_headline)
run = STUDY.run

"""The papers' claims and the reviewers' objections, tested on the errors of ``error_curves``.

Each claim compares two arrays of per-receiver signed errors, paired (same receivers),
in every configuration (seed x light) where both exist, with
:func:`avsm_dr.stats.claim`: the per-configuration bootstrap intervals, the pooled
effect (geometric mean of ratios, or mean of differences) with its two-stage interval,
and whether it holds in every configuration.  The unit of every pooled interval is the
configuration (scene seed x light); within a configuration receivers are resampled in tiles
of 8 x 8 texels of the map they are looked up in (:func:`experiments._two_metric.texel_blocks`), as
are the texels of the depth-uniform L2.  Verdicts:

* ``holds in every configuration``: every per-configuration 95 % interval is below the
  bound, in at least :data:`MIN_EVERY` configurations;
* ``holds pooled``: the pooled interval is below it (not every configuration's, or fewer
  than :data:`MIN_EVERY` of them);
* ``does not hold``: the pooled interval is entirely above it (the opposite holds);
* ``inconclusive``: otherwise;
* ``metric-dependent``: the receiver RMSE and the depth-uniform L2 of the curve
  (:func:`avsm_dr.evaluation.depth_l2`) point in opposite directions (their pooled
  intervals entirely on opposite sides of the bound); each metric's own verdict is kept
  under ``metrics``.

Every claim records its insertion order (``order``: the AVSM family's is 'depth'; under
``by_order`` the claim again with the AVSM side built in each other order, on the same
receivers), whether each side is its kind's preset (``preset``), both metrics, the signed
mean and leak share of each side, and ``indicative``: true when it rests on fewer than
:data:`MIN_CONFIDENT` configurations.

The AVSM paper: Salvi, Vidimce, Lauritzen and Lefohn, "Adaptive Volumetric Shadow Maps",
EGSR 2010 (sec. 5: AVSM-12 against FOM-16 and OSM-32 on hair and smoke, and the claim of
insensitivity to the depth range); Fourier opacity maps: Jansen and Bavoil, I3D 2010;
moments: Peters and Klein, "Moment Shadow Mapping", I3D 2015 (overestimation beta).
"""
from __future__ import annotations

import numpy as np

from avsm_dr import describe, kinds, stats
from avsm_dr.builtin_scenes import SCENES
from .._two_metric import metric_dependent, side as side_summary
from .labels import ORDERS, label, order_dependent, with_size

#: Every scene ``error_curves`` can run (claims about scenes not run are left out).
#: The scenes of the study, registration order: every built-in scene (the six core ones and
#: the new content types: cumulus, fog bank, Gaussian blobs, tall smoke column).
SCENE_NAMES = SCENES.names()
#: Moment variants and the FOM of the same bytes (float32): 5, 7 and 9 stored floats.
MOMENTS_VS_FOM = (("moments-4", "fom-2"), ("moments-2/family=trigonometric", "fom-2"),
                  ("moments-6", "fom-3"), ("moments-3/family=trigonometric", "fom-3"),
                  ("moments-8", "fom-4"), ("moments-4/family=trigonometric", "fom-4"))
#: Headline settings compared in float16 and 8-bit storage against float32 (the segments' dtype).
PRECISION_SETTINGS = ("avsm-8", "fom-4", "moments-4", "osm-32", "dsm-0.01")
#: A storage precision "costs nothing" when the RMSE ratio to float32 stays below this.
PRECISION_BOUND = 1.01

#: Configurations needed before "holds in every configuration" is claimed.
MIN_EVERY = 8
#: Below this many configurations a claim is ``indicative``.
MIN_CONFIDENT = 4

#: (kind, size) of the depth-range study (the AVSM paper's comparison).
RANGE_KINDS = (("avsm", 8), ("fom", 8), ("osm", 32))
H, P, T, S, C = "hair_and_smoke", "plume", "smoke_over_table", "surface", "in_volume"


def _side(variant, term="compression", opaque="inline", rset=C, study="main", order="depth"):
    return dict(variant=variant, term=term, opaque=opaque, set=rset, study=study, order=order)


def _claims() -> list[dict]:
    """The claims: id, statement, scene, a, b (:func:`_side`), statistic, compare."""
    out = [
        dict(id="avsm12_vs_fom16_hair_smoke_compression", scene=H, a=_side("avsm-12"), b=_side("fom-16"),
             statement="AVSM-12 compresses hair + smoke better than FOM-16 (RMSE ratio < 1, vs the exact curve)"),
        dict(id="avsm12_vs_osm32_hair_smoke_compression", scene=H, a=_side("avsm-12"), b=_side("osm-32"),
             statement="AVSM-12 compresses hair + smoke better than OSM-32 (vs the exact curve)"),
        dict(id="avsm12_vs_fom16_hair_smoke_total", scene=H, a=_side("avsm-12", "total"),
             b=_side("fom-16", "total"),
             statement="AVSM-12 is closer to the true transmittance than FOM-16 on hair + smoke"),
        dict(id="avsm8_vs_fom8_global_range_x8", scene=P, a=_side("avsm-8", study="global_range_x8"),
             b=_side("fom-8", study="global_range_x8"),
             statement="with the global depth range stretched 8x, AVSM-8 beats FOM-8"),
        dict(id="avsm8_vs_osm32_global_range_x8", scene=P, a=_side("avsm-8", study="global_range_x8"),
             b=_side("osm-32", study="global_range_x8"),
             statement="with the global depth range stretched 8x, AVSM-8 beats OSM-32"),
        dict(id="avsm8_vs_fom8_texel_range", scene=P, a=_side("avsm-8"), b=_side("fom-8/depth_range=texel"),
             statement="AVSM-8 beats FOM-8 with per-texel depth ranges (no stretch)"),
        dict(id="fom16_vs_avsm16_three_columns", scene="three_columns", a=_side("fom-16"), b=_side("avsm-16"),
             statement="on smooth smoke FOM-16 compresses better than AVSM-16 (about equal bytes)"),
        dict(id="avsm16_exp_vs_linear_particles", scene="particles", a=_side("avsm-16/interpolation=exp"),
             b=_side("avsm-16"), statement="inside thick uniform particles AVSM-16 with exponential "
                                           "interpolation beats linear"),
    ]
    for st in (8, 32):
        for other in ("fom-8", "osm-32"):
            out.append(dict(id=f"avsm8_vs_{other.replace('-', '')}_texel_faint_x{st}", scene=P,
                            a=_side("avsm-8", study=f"faint_segment_x{st}"),
                            b=_side(f"{other}/depth_range=texel", study=f"faint_segment_x{st}"),
                            statement=f"with a faint segment {st}x behind each texel's content (depth spread "
                                      f"within the texel), AVSM-8 beats {other.upper()} even with per-texel ranges"))
    for other in ("fom-16", "osm-32", "moments"):
        for mode in ("inline", "separate"):
            out.append(dict(id=f"{other.replace('-', '')}_table_top_worse_than_map_{mode}", scene=T,
                            a=_side("exact", "total", mode, S), b=_side(other, "total", mode, S), below=0.9,
                            statement=f"{other.upper()}'s table-top error exceeds the exact map's own by more "
                                      f"than 10 % (RMSE ratio map / method < 0.9; opaque {mode})"))
    out.append(dict(id="fom16_separate_vs_inline_in_smoke", scene=T, a=_side("fom-16", opaque="separate"),
                    b=_side("fom-16", opaque="inline"),
                    statement="a separate opaque depth map lowers FOM-16's error inside the smoke"))
    for beta, sign in (("0.0", "leak"), ("", "leak"), ("1.0", "dark")):
        v = "moments-4" + (f"/overestimation={beta}" if beta else "")
        z = _side(v, "zero")
        a, b = (z, _side(v)) if sign == "leak" else (_side(v), z)
        out.append(dict(id=f"moments_beta{beta or '0.25'}_{sign}s_plume", scene=P, a=a, b=b, statistic="mean",
                        compare="difference",
                        statement=f"4 power moments (beta = {beta or '0.25'}) "
                                  + ("leak light: mean signed error > 0" if sign == "leak"
                                     else "over-darken: mean signed error < 0")))
    for sc in SCENE_NAMES:                                 # today's representations
        for v, b in (("beer", "12 B"), ("beer/variant=two_node", "16 B")):
            out.append(dict(id=f"avsm8_vs_{v.replace('/variant=', '_')}_{sc}", scene=sc, a=_side("avsm-8"),
                            b=_side(v), statement=f"AVSM-8 (64 B) compresses better than the Beer shadow map "
                                                  f"({v.split('=')[-1] if '=' in v else 'cloud'}, {b}): RMSE "
                                                  "ratio < 1 vs the exact curve"))
        for m, f in MOMENTS_VS_FOM:
            out.append(dict(id=f"{m.replace('/family=trigonometric', '_trig').replace('-', '')}_vs_"
                               f"{f.replace('-', '')}_{sc}", scene=sc, a=_side(m), b=_side(f),
                            statement=f"{m} compresses better than {f} at equal bytes (RMSE ratio < 1)"))
        for v in PRECISION_SETTINGS:
            for prec in ("float16", "unorm8"):
                out.append(dict(id=f"{v.replace('-', '').replace('.', '')}_{prec}_vs_float32_{sc}", scene=sc,
                                a=_side(f"{v}/precision={prec}"), b=_side(v), below=PRECISION_BOUND,
                                statement=f"{v} stored in {prec} loses under 1 % RMSE against float32 "
                                          f"(ratio < {PRECISION_BOUND})"))
    return _with_preset_companions(out)


#: Claims that compare two kinds and get a companion ``<id>_at_preset`` with both sides at
#: their kinds' presets (``describe(kind)['preset']``, opaque content as ``preset_capture``
#: says where the scene has any): the fair form of the comparison.
PRESET_COMPANIONS = ("avsm12_vs_fom16_hair_smoke_compression", "avsm12_vs_osm32_hair_smoke_compression",
                     "avsm12_vs_fom16_hair_smoke_total", "fom16_vs_avsm16_three_columns")


def at_preset(variant: str, also: str | None = None) -> str:
    """``variant`` with its kind's preset applied (same size and other settings), e.g.
    ``'fom-16'`` -> ``'fom-16/depth_range=texel'``, then the kind's preset variant ``also``
    (a key of ``describe(kind)['preset_variants']``) when given; non-kinds unchanged."""
    kind = _kind(variant)
    if kind not in kinds():
        return variant
    base, *extra = variant.split("/")
    d = describe(kind)
    size = base.split("-", 1)[1] if "-" in base else None
    value = None if size is None else int(size) if size.isdigit() else float(size)
    params = dict(with_size(kind, value))
    for x in extra:
        k, v = x.split("=", 1)
        params[k] = v
    params.update(d["preset"])
    if also is not None:
        params.update(d["preset_variants"][also])
    return label(kind, params)


def _at_preset_side(side, also: str | None = None) -> dict:
    """``side`` with its variant at its kind's preset (then its preset variant ``also`` where
    the kind has it) and the capture's opaque mode the preset's."""
    kind = _kind(side["variant"])
    if kind not in kinds():
        return dict(side)
    also = also if also in describe(kind)["preset_variants"] else None
    opaque = describe(kind)["preset_capture"].get("opaque", side["opaque"])
    return dict(side, variant=at_preset(side["variant"], also), opaque=opaque)


def _with_preset_companions(claims: list[dict]) -> list[dict]:
    """Each claim comparing two kinds, again with both at their presets (``<id>_at_preset``),
    and once per preset variant that departs from a side's preset (``<id>_at_preset_<variant>``,
    e.g. AVSM with ``interpolation='exp'``: both interpolations reported)."""
    out = list(claims)
    for c in claims:
        if c["id"] in PRESET_COMPANIONS or c["id"].startswith("avsm8_vs_beer") \
                or (c["id"].startswith("moments") and "_vs_fom" in c["id"]):
            if c.get("statistic", "rmse") != "rmse" or c["a"]["study"] != "main":
                continue
            out.append(dict(c, id=c["id"] + "_at_preset", statement=c["statement"] + " (both at their presets)",
                            a=_at_preset_side(c["a"]), b=_at_preset_side(c["b"])))
            variants = {v for s in (c["a"], c["b"]) if _kind(s["variant"]) in kinds()
                        for v, p in describe(_kind(s["variant"]))["preset_variants"].items()
                        if p != {k: describe(_kind(s["variant"]))["preset"].get(k) for k in p}}
            for v in sorted(variants):
                out.append(dict(c, id=f"{c['id']}_at_preset_{v}", a=_at_preset_side(c["a"], v),
                                b=_at_preset_side(c["b"], v),
                                statement=c["statement"] + f" (both at their presets, {v} variant)"))
    return out


def claim_sizes() -> dict:
    """kind -> sizes the claims name (built in every configuration besides the headline)."""
    out: dict = {}
    for c in _claims():
        for side in (c["a"], c["b"]):
            base = side["variant"].split("/")[0]
            if "-" in base:
                kind, size = base.split("-", 1)
                out.setdefault(kind, set()).add(int(size) if size.isdigit() else float(size))
    for kind, v in RANGE_KINDS:
        out.setdefault(kind, set()).add(v)
    return {k: tuple(sorted(v)) for k, v in out.items()}


def claim_settings() -> set:
    """Labels (``error_curves.label``) of every setting a claim compares."""
    return {side["variant"] for c in _claims() for side in (c["a"], c["b"])}


def _errors(store, scene, cfg, side):
    v = store.get((scene, cfg, side["variant"], side["opaque"], side["set"], side["study"], side.get("order", "depth")))
    if v is None:
        return None
    if side["term"] == "zero":
        return np.zeros(v[0].size)
    return np.asarray(v[0 if side["term"] == "compression" else 1], np.float64)


def _verdict(r) -> str:
    if r["holds_in_every_configuration"] and r["n_configs"] >= MIN_EVERY:
        return "holds in every configuration"
    if r["holds_pooled"]:
        return "holds pooled"
    if r["low"] > r["below"]:
        return "does not hold"
    return "inconclusive"


def _kind(variant: str) -> str:
    return variant.split("/")[0].split("-")[0]


def preset_differences(side, opaque_matters: bool = True) -> list[str]:
    """How the side's setting departs from its kind's preset, e.g. ``['interpolation=exp
    (preset linear)', 'opaque inline (preset separate)']`` (empty at the preset; the exact
    curve, the truth and non-kinds have none)."""
    kind = _kind(side["variant"])
    if kind not in kinds():
        return []
    d = describe(kind)
    given = dict(x.split("=", 1) for x in side["variant"].split("/")[1:])
    out = []
    for k, v in d["preset"].items():
        have = given.get(k, str(d["headline"].get(k, d["params"][k]["default"])))
        if have != str(v):
            out.append(f"{k}={have} (preset {v})")
    want = d["preset_capture"].get("opaque", side["opaque"])
    if opaque_matters and want != side["opaque"]:
        out.append(f"opaque {side['opaque']} (preset {want})")
    return out


def _preset_note(spec, opaque_matters: bool = True) -> str:
    """'' when both sides are at their presets, else ' [not at preset: avsm-12 interpolation=exp
    (preset linear); ...]': a claim off the presets names it in its statement."""
    parts = []
    for k in ("a", "b"):
        diff = preset_differences(spec[k], opaque_matters)
        if diff:
            parts.append(f"{spec[k]['variant']} " + ", ".join(diff))
    return f" [not at preset: {'; '.join(parts)}]" if parts else ""


def summary_lines(findings: dict) -> dict:
    """One human line per claim for the end of a run: ``estimate [low, high]`` of the receiver
    RMSE ratio (or difference), the depth-uniform L2 beside it, the verdict, the number of
    configurations (``indicative`` below :data:`MIN_CONFIDENT`) and the insertion order."""
    out = {}
    for cid, c in findings.get("claims", {}).items():
        line = f"{c['estimate']:.3g} [{c['low']:.3g}, {c['high']:.3g}]"
        l2 = (c.get("metrics") or {}).get("depth_l2")
        if l2:
            line += f", depth-L2 {l2['estimate']:.3g} [{l2['low']:.3g}, {l2['high']:.3g}]"
        line += f": {c['verdict']}, {c['n_configs']} configs"
        if c.get("indicative"):
            line += " (indicative)"
        if c.get("order", "-") != "-":
            line += f", order {c['order']}"
        if not all(c.get("preset", {}).values()):
            line += ", not at preset"
        out[cid] = line
    return out


def _content(scene: str) -> list[str]:
    """The scene's content types (``SCENES.entry(name).content``: grid, particles, hair,
    blockers); empty for a scene that is not registered."""
    return list(SCENES.entry(scene).content) if scene in SCENES else []


def _order(side) -> str:
    kind = _kind(side["variant"])
    return side.get("order", "depth") if kind in kinds() and order_dependent(kind) else "-"


def _metric(r) -> dict:
    return dict(estimate=r["estimate"], low=r["low"], high=r["high"], n_configs=r["n_configs"], verdict=_verdict(r),
                indicative=r["n_configs"] < MIN_CONFIDENT)


def evaluate(spec, store, configs, n_boot: int = 1000, l2=None, blocks=None, by_order: bool = True,
             separate_scenes=None) -> dict | None:
    """One claim over the configurations where both sides were measured (None if none).

    l2: {(scene, config, setting, opaque, order): per-texel depth-uniform L2} (the second
    metric); blocks: {(scene, config, opaque[, receiver set]): 8 x 8 texel tile of each
    texel / receiver} (the within-configuration block bootstrap); by_order: also the claim
    with the order-dependent sides in every other order of :data:`ORDERS`; separate_scenes:
    :func:`separate_scenes` of ``store`` (None: found here, a pass over the store)."""
    separate = spec["scene"] in (separate_scenes_of(store) if separate_scenes is None else separate_scenes)
    if not separate:            # no opaque content: the separate capture is the inline one
        spec = dict(spec, **{k: dict(spec[k], opaque="inline") for k in ("a", "b")})
    a_all, b_all, used, blk = [], [], [], []
    for cfg in configs:
        a, b = _errors(store, spec["scene"], cfg, spec["a"]), _errors(store, spec["scene"], cfg, spec["b"])
        if a is None or b is None or a.size < 2:
            continue
        if spec.get("compare", "ratio") == "ratio" and not (np.any(a != 0) and np.any(b != 0)):
            continue
        a_all.append(a)
        b_all.append(b)
        used.append(cfg)
        blk.append((blocks or {}).get((spec["scene"], cfg, spec["a"]["opaque"], spec["a"]["set"])))
    if not used:
        return None
    blk = None if any(x is None or x.size != a.size for x, a in zip(blk, a_all)) else blk
    r = stats.claim(a_all, b_all, statistic=spec.get("statistic", "rmse"), compare=spec.get("compare", "ratio"),
                    below=spec.get("below"), configs=used, n_boot=n_boot, blocks_by_config=blk)
    per = [{k: pc[k] for k in ("config", "estimate", "low", "high", "a", "b", "holds")} for pc in r["per_config"]]
    out = {k: r[k] for k in ("estimate", "low", "high", "level", "below", "compare", "statistic", "n_configs",
                             "holds_in_every_configuration", "holds_pooled")}
    out.update(statement=spec["statement"] + _preset_note(spec, separate),
               scene=spec["scene"], content=_content(spec["scene"]), a=spec["a"], b=spec["b"], per_config=per,
               receivers_per_config=int(np.median([x.size for x in a_all])), verdict=_verdict(r),
               indicative=r["n_configs"] < MIN_CONFIDENT, interval_unit="configuration",
               within_configuration="8x8 texel blocks" if blk is not None else "receivers",
               order=next((o for o in (_order(spec["a"]), _order(spec["b"])) if o != "-"), "-"),
               preset={k: not preset_differences(spec[k], separate) for k in ("a", "b")},
               sides={"a": side_summary(a_all), "b": side_summary(b_all)})
    out["metrics"] = {"receiver_rmse": _metric(r), "depth_l2": _depth_l2_claim(spec, l2, blocks, configs, n_boot)}
    out["metric_dependent"] = metric_dependent(*out["metrics"].values(), below=r["below"])
    if out["metric_dependent"]:
        out["verdict"] = "metric-dependent"
    if by_order and out["order"] != "-":
        out["by_order"] = {}
        for o in ORDERS[1:]:
            s2 = dict(spec, **{k: dict(spec[k], order=o) if _order(spec[k]) != "-" else spec[k] for k in ("a", "b")})
            r2 = evaluate(s2, store, configs, n_boot, l2, blocks, by_order=False, separate_scenes={spec["scene"]}
                          if separate else set())
            if r2 is not None:
                out["by_order"][o] = {k: r2[k] for k in ("estimate", "low", "high", "n_configs", "verdict",
                                                         "indicative", "metric_dependent", "sides")}
                out["by_order"][o]["depth_l2"] = r2["metrics"]["depth_l2"]
    return out


def _depth_l2_claim(spec, l2, blocks, configs, n_boot) -> dict | None:
    """The claim on the depth-uniform L2 of the two curves (per-texel L2 paired, RMS ratio;
    None for difference claims, other studies, the zero side, or no data)."""
    if l2 is None or spec.get("compare", "ratio") != "ratio" or spec.get("statistic", "rmse") != "rmse":
        return None
    sides = (spec["a"], spec["b"])
    if any(s["study"] != "main" or s["term"] == "zero" for s in sides):
        return None
    xa, xb, used, blk, nonfinite = [], [], [], [], []
    for cfg in configs:
        a, b = (l2.get((spec["scene"], cfg, s["variant"], s["opaque"], s.get("order", "depth"))) for s in sides)
        if a is None or b is None or a.size != b.size or a.size < 2 or not (np.any(a > 0) and np.any(b > 0)):
            continue
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
            # a kind returned NaN on some texel (moments-8, simulated_plume s2-dir_b: 3 of
            # 10556 texels): reported, not pooled
            nonfinite.append(cfg)
            continue
        xa.append(np.asarray(a, np.float64))
        xb.append(np.asarray(b, np.float64))
        used.append(cfg)
        blk.append((blocks or {}).get((spec["scene"], cfg, spec["a"]["opaque"])))
    if not used:
        return None
    blk = None if any(x is None or x.size != a.size for x, a in zip(blk, xa)) else blk
    r = stats.claim(xa, xb, "rmse", "ratio", below=spec.get("below"), configs=used, n_boot=n_boot,
                    blocks_by_config=blk)
    out = _metric(r)
    if nonfinite:
        out["nonfinite_configs"] = nonfinite
    return out


def _dilution(store, configs, n_boot) -> dict:
    """Per scene: surface / in-volume compression RMSE of AVSM-8 and FOM-8 (geometric mean
    over configurations, bootstrap interval over configurations)."""
    out = {}
    scenes = sorted({k[0] for k in store})
    for sc in scenes:
        for v in ("avsm-8", "fom-8"):
            ratios = []
            for cfg in configs:
                s = _errors(store, sc, cfg, _side(v, rset=S))
                i = _errors(store, sc, cfg, _side(v))
                if s is None or i is None:
                    continue
                rs, ri = np.sqrt(np.mean(s ** 2)), np.sqrt(np.mean(i ** 2))
                ratios.append(max(rs, 1e-12) / max(ri, 1e-12))
            if len(ratios) >= 2:
                ci = stats.bootstrap_ci(np.log(ratios), "mean", n_boot=n_boot)
                out[f"{sc}/{v}"] = dict(geo_mean_ratio=float(np.exp(ci["estimate"])), low=float(np.exp(ci["low"])),
                                        high=float(np.exp(ci["high"])), max_ratio=float(max(ratios)),
                                        n_configs=len(ratios), below_0_1_everywhere=bool(max(ratios) < 0.1))
    return out


def _groups(rows, key_fn, value, where) -> dict:
    groups: dict = {}
    for r in rows:
        if where(r) and r.get(value) not in (None, ""):
            groups.setdefault(key_fn(r), []).append(float(r[value]))
    return groups


def _median_by(rows, key_fn, value, where) -> dict:
    return {k: float(np.median(v)) for k, v in _groups(rows, key_fn, value, where).items()}


def share_ci(mask, n_boot: int = 1000, level: float = 0.95, seed: int = 0) -> list[float]:
    """[share, low, high]: the share of True in ``mask`` with its percentile bootstrap
    interval.  Resampling n items of a 0/1 sample with replacement draws Binomial(n, p) ones,
    so the replicates are drawn as binomials: the same distribution in O(n_boot), not
    O(n_boot n) (40 k receivers x 1000 replicates per variant took minutes)."""
    mask = np.asarray(mask, bool).ravel()
    n = mask.size
    p = float(mask.mean()) if n else 0.0
    reps = np.random.default_rng(seed).binomial(n, p, n_boot) / max(n, 1)
    a = (1 - level) / 2
    return [p, float(np.quantile(reps, a)), float(np.quantile(reps, 1 - a))]


def _leak_table(store, configs, n_boot) -> dict:
    """Shares of in-volume receivers leaking / over-darkening by > 0.02 (vs the exact curve),
    pooled over configurations, with bootstrap intervals over receivers, for the moments
    variants the claims name (betas, families, counts), AVSM-8, FOM-8 and the FOMs of the
    moments' bytes, per scene (not every tuning combination: the bootstrap over all of them
    took minutes in the full run)."""
    out = {}
    named = {v for v in claim_settings() if v.startswith("moments")}   # the moments variants the claims name
    variants = sorted(({k[2] for k in store} & named) | {"avsm-8", "fom-8"} | {f for _, f in MOMENTS_VS_FOM})
    for sc in sorted({k[0] for k in store}):
        for v in variants:
            errs = [e for cfg in configs if (e := _errors(store, sc, cfg, _side(v))) is not None]
            if not errs:
                continue
            e = np.concatenate(errs)
            out[f"{sc}/{v}"] = dict(leak_fraction=share_ci(e > 0.02, n_boot), dark_fraction=share_ci(e < -0.02, n_boot),
                                    mean_signed_error=float(np.mean(e)), receivers=int(e.size))
    return out


def separate_scenes_of(store) -> set:
    """Scenes of ``store`` with a separate opaque capture (those with opaque content)."""
    return {k[0] for k in store if k[3] == "separate"}


def orders(store, configs, n_boot: int = 1000, l2=None, blocks=None, separate_scenes=None) -> dict:
    """Per scene and order-dependent setting (in-volume receivers, opaque inline): each
    other insertion order of :data:`ORDERS` against 'depth' on the same receivers and
    texels, the RMSE ratio (compression, vs the exact curve) and the depth-uniform L2
    ratio, with configuration-level intervals (:func:`evaluate`), and each order's signed
    mean and leak share."""
    out: dict = {}
    found = sorted({(k[0], k[2]) for k in store if k[6] != "depth" and k[5] == "main"})
    for scene, v in found:
        d = out.setdefault(scene, {}).setdefault(v, {})
        for o in ORDERS[1:]:
            spec = dict(scene=scene, a=_side(v, order=o), b=_side(v), statement=f"{v}: {o} order vs depth order")
            r = evaluate(spec, store, configs, n_boot, l2, blocks, by_order=False, separate_scenes=separate_scenes)
            if r is not None:
                d[o] = dict(rmse_ratio=[r["estimate"], r["low"], r["high"]], n_configs=r["n_configs"],
                            indicative=r["indicative"], depth_l2_ratio=r["metrics"]["depth_l2"],
                            metric_dependent=r["metric_dependent"], sides=r["sides"])
    return out


def findings(store: dict, rows: list[dict], n_boot: int = 1000, l2=None, blocks=None) -> dict:
    """``findings.json``: claims with intervals and verdicts, dilution by surface receivers,
    leak / dark shares, the decomposition and the best tuning per scene, the check of
    the truth against Mitsuba, and the AVSM family under every insertion order
    (:func:`orders`).  l2, blocks: as :func:`evaluate`."""
    configs = sorted({k[1] for k in store})
    sep = separate_scenes_of(store)
    claims = {}
    for spec in _claims():
        r = evaluate(spec, store, configs, n_boot, l2, blocks, separate_scenes=sep)
        if r is not None:
            claims[spec["id"]] = r
    # the map's own error against compression, every scene
    for sc in sorted({k[0] for k in store}):
        for v in ("avsm-8", "fom-8"):
            spec = dict(id=f"{v.replace('-', '')}_compression_below_map_error_{sc}", scene=sc, a=_side(v),
                        b=_side("exact", "total"),
                        statement=f"{v.upper()}'s compression error is below the exact map's own error vs "
                                  f"the truth (the spatial + capture floor dominates)")
            r = evaluate(spec, store, configs, n_boot, l2, blocks, separate_scenes=sep)
            if r is not None:
                claims[spec["id"]] = r
    main = lambda r: (r.get("study") == "main" and r.get("opaque") == "inline" and r.get("receivers") == C  # noqa: E731
                      and r.get("order", "-") in ("depth", "-"))
    decomposition = {}
    for col in ("rmse", "depth_l2", "total_rmse", "capture_rms", "spatial_rms", "total_p999_error", "total_max_error",
                "tau_rmse"):
        med = _median_by(rows, lambda r: (r["scene"], r.get("setting")), col, main)
        for (sc, v), x in med.items():
            decomposition.setdefault(sc, {}).setdefault(v, {})[f"median_{col}"] = x
    best = {}
    key = lambda r: (r["scene"], r["method"], str(r["param"]), r.get("setting"))  # noqa: E731
    med_total = _median_by(rows, key, "total_rmse", main)
    n_cfg = {k: len(v) for k, v in _groups(rows, key, "total_rmse", main).items()}
    for (sc, kind, param, v), x in med_total.items():
        if n_cfg[(sc, kind, param, v)] >= 2:                          # settings built in every configuration
            best.setdefault(sc, {}).setdefault(f"{kind}-{param}" if param else kind, {})[v] = x
    best = {sc: {g: dict(best=min(vs, key=vs.get), median_total_rmse=vs) for g, vs in gs.items() if len(vs) > 1}
            for sc, gs in best.items()}
    reference = {}
    for r in rows:
        if r.get("method") == "truth_vs_mitsuba":
            reference[f"{r['scene']}/{r['receivers']}"] = {k: r[k] for k in
                                                           ("rmse", "reference_se_rms", "within_3_stderr", "n")}
    return dict(configurations=configs, claims=claims, orders=orders(store, configs, n_boot, l2, blocks, sep),
                surface_dilution=_dilution(store, configs, n_boot),
                leak_dark=_leak_table(store, configs, n_boot), decomposition=decomposition, best_tuning=best,
                truth_vs_mitsuba=reference)

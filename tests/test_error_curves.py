"""error_curves' measurement machinery: the error decomposition, receiver sets, the separate
opaque depth map, builds on a subset of texels, the variants read from the registry and
the claims' intervals."""
import json

import numpy as np
import pytest

import avsm_dr as ad
from avsm_dr import receivers, stats
from avsm_dr.capture.opaque_map import OpaqueComposite
from experiments.error_curves import findings as F
from experiments import error_curves as E
from avsm_dr.evaluation import Probe, SubsetBuilder, light_variants
from avsm_dr.groundtruth import sample_density


@pytest.fixture(scope="module")
def plume():
    return ad.scenes.get("plume", size=16)


@pytest.fixture(scope="module")
def table():
    sc = ad.scenes.get("smoke_over_table", size=16)
    return (sc, ad.capture(sc, resolution=64, order="depth"),
            ad.capture(sc, resolution=64, opaque="separate", order="depth"))


# ------------------------------------------------------------------ decomposition
def test_terms_add_up_and_probe_is_the_bilinear_filter(plume):
    cap = ad.capture(plume, resolution=64, order="depth")
    pts = receivers.in_volume(plume, 300, seed=1)
    probe = Probe(cap, plume, pts, n_decomp=300)
    rep, exact = ad.build("avsm", cap.segments, nodes=4), ad.build("exact", cap.segments)
    est, ex = probe.lookup(rep), probe.lookup(exact)
    # the probe's own taps are the package's bilinear filter (float32 kernels: rounding only)
    np.testing.assert_allclose(est, np.asarray(cap.transmittance(rep, pts, filter="bilinear")), atol=2e-6)
    t = probe.terms(est, ex)
    np.testing.assert_allclose(t["compression"] + t["capture"] + t["spatial"], t["total"], atol=1e-12)
    rms = {k: float(np.sqrt(np.mean(v ** 2))) for k, v in t.items()}
    assert rms["total"] <= rms["compression"] + rms["capture"] + rms["spatial"] + 1e-12
    # AVSM-4 compresses a plume visibly; exact-curve compression is zero
    assert rms["compression"] > 1e-3
    assert np.all(probe.terms(ex, ex)["compression"] == 0)
    # the exact map's error is capture + spatial only, and both are resolved (not zero)
    assert rms["spatial"] > 1e-4 and rms["capture"] > 0


def test_receivers_on_texel_rays_have_only_a_capture_term(plume):
    """Receivers on texel rays (at texel centres): the spatial term is zero, so the exact
    map's error is the capture term alone; a march capture with 1/8-voxel steps keeps it
    at the midpoint rule's O(step^2) (and float32) level."""
    lo, hi = plume.bbox
    voxel = float(np.min((hi - lo) / np.array(plume.density.shape[::-1])))
    cap = ad.capture(plume, resolution=64, step=voxel / 8, order="depth")
    near, far = cap.segments.bounds()
    tex = np.nonzero(cap.segments.counts > 0)[0][::7][:200]
    o, d = cap.camera.rays(tex)
    pts = o + (near + (far - near) * np.linspace(0.2, 0.8, tex.size))[:, None] * d
    probe = Probe(cap, plume, pts, n_decomp=tex.size)
    ex = probe.lookup(ad.build("exact", cap.segments))
    t = probe.terms(ex, ex)
    assert np.max(np.abs(t["spatial"])) < 1e-9        # the same paths, float64
    assert 0 < np.max(np.abs(t["capture"])) < 2e-3    # measured 1.2e-3 (size 16, 64^2)
    np.testing.assert_allclose(t["total"], t["capture"], atol=1e-9)


# ---------------------------------------------------------------------- receivers
def test_in_volume_receivers_are_deterministic_inside_and_weighted(plume):
    a = receivers.in_volume(plume, 400, seed=2)
    b = receivers.in_volume(plume, 400, seed=2)
    c = receivers.in_volume(plume, 400, seed=3)
    assert a.shape == (400, 3) and np.array_equal(a, b) and not np.array_equal(a, c)
    lo, hi = plume.bbox
    assert np.all((a >= lo) & (a <= hi))
    assert np.all(sample_density(plume.density, plume.bbox, a) > 0)
    # drawn towards lit, visible medium: higher light x view visibility than density-only draws
    rng = np.random.default_rng(0)
    cand = receivers._density_candidates(plume, 2000, rng)
    cam = ad.groundtruth.default_camera(plume)
    vis = lambda p: receivers.visibility(plume, p) * receivers.visibility(plume, p, origin=cam.origin)  # noqa
    assert vis(a).mean() > 1.2 * vis(cand).mean()


def test_surface_receivers_lie_on_the_receiver_plane(plume):
    p = receivers.surface(plume, 100, seed=0)
    c, n, half = plume.receiver_plane
    assert p.shape == (100, 3)
    np.testing.assert_allclose((p - c) @ n, 0, atol=1e-12)
    assert np.all(np.abs(p - c) <= half + 1e-12)
    sets = receivers.receiver_sets(plume, 64, 16)
    assert list(sets) == ["in_volume", "surface", "uniform"]


@pytest.mark.parametrize("bad, msg", [(dict(n=-1), "n:"), (dict(seed=1.5), "seed:")])
def test_receiver_arguments_are_checked(plume, bad, msg):
    kw = dict(n=10, seed=0) | bad
    with pytest.raises(ValueError, match=f"^{msg}"):
        receivers.in_volume(plume, **kw)


# ------------------------------------------------------------- separate opaque map
def test_separate_opaque_map_equals_inline_for_exact(table):
    sc, inline, separate = table
    assert inline.opaque_depth is None and np.isfinite(separate.opaque_depth).sum() > 0
    assert separate.segments.n_segments < inline.segments.n_segments       # the table is not in the segments
    pts = np.concatenate([receivers.in_volume(sc, 300, seed=0), receivers.surface(sc, 300, seed=0),
                          sc.receivers])
    for filt in ("point", "bilinear"):
        a = np.asarray(inline.transmittance(ad.build("exact", inline.segments), pts, filter=filt))
        b = np.asarray(separate.transmittance(ad.build("exact", separate.segments), pts, filter=filt))
        np.testing.assert_allclose(a, b, atol=1e-6)                     # float32 rounding only


def test_separate_opaque_map_removes_fom_ringing(table):
    sc, inline, separate = table
    top = receivers.surface(sc, 400, seed=1)                           # on the table top
    ex = np.asarray(inline.transmittance(ad.build("exact", inline.segments), top))

    def rmse(cap):
        return float(np.sqrt(np.mean((np.asarray(cap.transmittance(ad.build("fom", cap.segments, harmonics=16), top))
                                      - ex) ** 2)))
    assert rmse(inline) > 0.1          # the step to T = 0 in the same Fourier series rings
    assert rmse(separate) < 1e-4


def test_opaque_composite_storage_and_checks(table):
    _, _, separate = table
    fom = ad.build("fom", separate.segments, harmonics=4)
    comp = OpaqueComposite(fom, separate.opaque_depth)
    assert comp.nbytes_per_texel == fom.nbytes_per_texel + 4
    assert comp.monotone == fom.monotone
    with pytest.raises(ValueError, match="^depth:"):
        OpaqueComposite(fom, separate.opaque_depth[:-1])
    with pytest.raises(ValueError, match="^opaque:"):
        ad.capture(table[0], resolution=64, opaque="sometimes")


# ---------------------------------------------------------------- subsets, studies
@pytest.mark.parametrize("kind, params", [("avsm", dict(nodes=8)), ("fom", dict(harmonics=8)),
                                          ("osm", dict(slices=16)), ("dsm", dict(tolerance=0.02))])
def test_subset_build_equals_whole_map(plume, kind, params):
    cap = ad.capture(plume, resolution=64, order="depth")
    probe = Probe(cap, plume, receivers.in_volume(plume, 200, seed=0), n_decomp=0)
    sub = SubsetBuilder(cap.segments, probe.tex.ravel())
    assert sub.texels.size < cap.segments.n_texels
    whole = probe.lookup(ad.build(kind, cap.segments, **params))
    np.testing.assert_allclose(probe.lookup(sub.build(kind, params)), whole, atol=1e-6)


def test_faint_segments_leave_the_curve_in_front_unchanged(plume):
    seg = ad.capture(plume, resolution=64, order="depth").segments
    f = E.with_faint_segments(seg, 8.0)
    nz = seg.counts > 0
    assert np.array_equal(f.counts, seg.counts + nz)
    near, far = seg.texel_bounds()
    tex = np.nonzero(nz)[0]
    z = near[tex] + 0.9 * (far[tex] - near[tex])
    np.testing.assert_allclose(np.asarray(ad.build("exact", f).eval(tex, z)),
                               np.asarray(ad.build("exact", seg).eval(tex, z)), atol=1e-7)
    fn, ff = f.texel_bounds()
    np.testing.assert_allclose((ff - fn)[tex], 8.01 * (far - near)[tex], rtol=1e-5)


def test_light_variants(plume):
    lv = light_variants(plume)
    d0, d1 = lv["dir_a"].direction, lv["dir_b"].direction
    assert np.degrees(np.arccos(np.clip(d0 @ d1, -1, 1))) == pytest.approx(25.0, abs=1e-6)
    cap = ad.capture(E.dataclasses.replace(plume, light=lv["spot"]), resolution=64, order="depth")
    assert cap.covers(receivers.in_volume(plume, 200, seed=0)).all()


# ------------------------------------------------------------- registry, claims
def test_variants_are_read_from_the_registry():
    for kind in ad.kinds():
        vs = E.variants(kind, quick=True, sweep=True)
        assert vs and len({E.label(kind, p) for p, _ in vs}) == len(vs)
        if "depth_range" in ad.describe(kind)["params"]:
            assert any(p.get("depth_range") == "texel" for p, _ in vs)
    labels = {E.label("moments", p) for p, _ in E.variants("moments", quick=False, sweep=False)}
    assert {"moments-4", "moments-4/overestimation=0.0", "moments-4/overestimation=1.0",
            "moments-3/family=trigonometric", "moments-8"} <= labels
    # the schema's constraint: no 2 or 3 power moments, no 6 or 8 trigonometric ones
    assert not any(lb.startswith(("moments-2", "moments-3")) and "trigonometric" not in lb for lb in labels)
    assert not any(lb.startswith(("moments-6", "moments-8")) and "trigonometric" in lb for lb in labels)
    assert {"avsm-8/precision=float16", "avsm-8/precision=unorm8"} <= {
        E.label("avsm", p) for p, _ in E.variants("avsm", quick=True, sweep=False)}
    assert {"avsm-8", "avsm-8/interpolation=exp"} <= {E.label("avsm", p) for p, _ in
                                                      E.variants("avsm", quick=False, sweep=False)}


def _claim_store(n_configs, orders=("depth",), l2_scale=None):
    """Errors of AVSM-12 (a tenth of FOM-16's on every receiver, plus 1 % noise) in
    ``n_configs`` configurations; per-texel L2 where AVSM-12's is ``l2_scale`` x FOM-16's."""
    rng = np.random.default_rng(0)
    store, l2, blocks = {}, {}, {}
    for c in range(n_configs):
        cfg = f"s{c}-dir_a"
        base = rng.standard_normal(500)
        tex = rng.standard_normal(300) ** 2 + 0.1
        blocks[(F.H, cfg, "inline", F.C)] = rng.integers(0, 40, 500)
        blocks[(F.H, cfg, "inline")] = rng.integers(0, 20, 300)
        for v, scale in (("avsm-12", 0.1), ("fom-16", 1.0)):
            for o in (orders if v.startswith("avsm") else ("depth",)):
                e = np.float32(scale * base + 0.01 * rng.standard_normal(500))
                store[(F.H, cfg, v, "inline", F.C, "main", o)] = (e, e)
                if l2_scale is not None:
                    k = l2_scale if v.startswith("avsm") else 1.0
                    l2[(F.H, cfg, v, "inline", o)] = np.float32(k * tex * (1 + 0.01 * rng.standard_normal(300)))
    return store, l2, blocks


def test_claims_report_intervals_per_configuration():
    store, _, _ = _claim_store(8)
    spec = next(s for s in F._claims() if s["id"] == "avsm12_vs_fom16_hair_smoke_compression")
    r = F.evaluate(spec, store, sorted({k[1] for k in store}), n_boot=200)
    assert r["n_configs"] == 8 and len(r["per_config"]) == 8
    assert r["low"] <= r["estimate"] <= r["high"] < 1
    assert all(p["low"] <= p["estimate"] <= p["high"] for p in r["per_config"])
    assert r["verdict"] == "holds in every configuration" and r["indicative"] is False
    assert r["order"] == "depth" and r["preset"] == {"a": True, "b": False}    # AVSM's preset linear, FOM's texel range
    swapped = dict(spec, a=spec["b"], b=spec["a"])
    assert F.evaluate(swapped, store, sorted({k[1] for k in store}), n_boot=200)["verdict"] == "does not hold"
    json.dumps(r)                                                      # serialisable as findings.json


@pytest.mark.parametrize("n, verdict, indicative", [(4, "holds pooled", False), (3, "holds pooled", True)])
def test_every_configuration_needs_eight_and_few_are_indicative(n, verdict, indicative):
    """Every per-configuration interval below 1, but fewer than 8 configurations: only
    'holds pooled'; below 4 configurations the claim is indicative."""
    store, _, _ = _claim_store(n)
    spec = next(s for s in F._claims() if s["id"] == "avsm12_vs_fom16_hair_smoke_compression")
    r = F.evaluate(spec, store, sorted({k[1] for k in store}), n_boot=200)
    assert r["holds_in_every_configuration"] and r["verdict"] == verdict and r["indicative"] is indicative
    assert r["metrics"]["receiver_rmse"]["indicative"] is indicative


def test_claims_carry_both_metrics_blocks_and_orders():
    """With per-texel L2 in the same direction the claim holds on both metrics (block
    bootstrap within configurations); with AVSM's L2 3x FOM's the metrics disagree and
    the verdict is 'metric-dependent'; the AVSM side is re-evaluated in every other order."""
    orders = ("depth", "reverse_depth", "random", "submission")
    store, l2, blocks = _claim_store(8, orders, l2_scale=0.5)
    spec = next(s for s in F._claims() if s["id"] == "avsm12_vs_fom16_hair_smoke_compression")
    cfgs = sorted({k[1] for k in store})
    r = F.evaluate(spec, store, cfgs, n_boot=200, l2=l2, blocks=blocks)
    m = r["metrics"]["depth_l2"]
    assert m["low"] <= 0.5 <= m["high"] < 1 and not r["metric_dependent"]
    assert r["within_configuration"] == "8x8 texel blocks"
    assert set(r["by_order"]) == set(orders[1:]) and all(v["high"] < 1 for v in r["by_order"].values())
    assert {"mean_signed_error", "leak_share"} <= set(r["sides"]["a"])
    store, l2, blocks = _claim_store(8, orders, l2_scale=3.0)
    r = F.evaluate(spec, store, cfgs, n_boot=200, l2=l2, blocks=blocks)
    assert r["metrics"]["depth_l2"]["low"] > 1 and r["high"] < 1
    assert r["metric_dependent"] and r["verdict"] == "metric-dependent"
    assert r["metrics"]["receiver_rmse"]["verdict"] == "holds in every configuration"
    o = F.orders(store, cfgs, n_boot=200, l2=l2, blocks=blocks)
    assert set(o[F.H]["avsm-12"]) == set(orders[1:])
    json.dumps(r)



def test_claims_off_the_presets_name_it_and_have_a_preset_companion():
    """A claim whose sides are not at their kinds' presets says so in its statement (what
    differs, e.g. AVSM's linear interpolation, FOM's global depth range); the opaque mode
    counts only where the scene has opaque content.  Every headline comparison of two kinds
    has an ``_at_preset`` companion with both sides at their presets."""
    assert F.at_preset("fom-16") == "fom-16/depth_range=texel"
    assert F.at_preset("avsm-8") == "avsm-8" and F.at_preset("avsm-8", "exp") == "avsm-8/interpolation=exp"
    beta = ad.describe("moments")["preset"]["overestimation"]          # tuned for media (moment_tuning)
    assert F.at_preset("moments-2/family=trigonometric") == \
        f"moments-2/depth_range=texel/family=trigonometric/overestimation={beta}"
    assert beta in E.TUNING["overestimation"]       # error_curves builds the preset's beta: its claims have data
    assert F.at_preset("exact") == "exact" and F.at_preset("beer/variant=two_node") == "beer/variant=two_node"
    store, _, _ = _claim_store(4)
    claims = {c["id"]: c for c in F._claims()}
    cfgs = sorted({k[1] for k in store})
    r = F.evaluate(claims["avsm12_vs_fom16_hair_smoke_compression"], store, cfgs, n_boot=100)
    assert "[not at preset: fom-16 depth_range=global (preset texel)]" in r["statement"] \
        and "opaque" not in r["statement"].split("[")[1]
    comp = claims["avsm12_vs_fom16_hair_smoke_compression_at_preset"]
    assert (comp["a"]["variant"], comp["b"]["variant"]) == ("avsm-12", "fom-16/depth_range=texel")
    exp = claims["avsm12_vs_fom16_hair_smoke_compression_at_preset_exp"]    # AVSM's other interpolation too
    assert (exp["a"]["variant"], exp["b"]["variant"]) == ("avsm-12/interpolation=exp", "fom-16/depth_range=texel")
    assert {c for c in claims if c.startswith("avsm8_vs_beer_particles")} == {
        f"avsm8_vs_beer_particles{s}" for s in ("", "_at_preset", "_at_preset_exp")}
    for v in ("avsm-12/interpolation=exp", "fom-16/depth_range=texel"):    # the same errors as the defaults
        for c in cfgs:
            store[(F.H, c, v, "inline", F.C, "main", "depth")] = store[(F.H, c, v.split("/")[0], "inline", F.C,
                                                                        "main", "depth")]
    r = F.evaluate(comp, store, cfgs, n_boot=100)        # no separate capture in the store: inline
    assert r["preset"] == {"a": True, "b": True} and "not at preset" not in r["statement"]
    assert {c[:-len("_at_preset")] for c in claims if c.endswith("_at_preset")} >= set(F.PRESET_COMPANIONS)
    assert all(not F.preset_differences(claims[c][k], False)        # companions' sides are at the presets
               for c in claims if c.endswith("_at_preset") for k in "ab")
    exp_sides = [claims[c][k]["variant"] for c in claims if c.endswith("_at_preset_exp") for k in "ab"]
    assert all(v.endswith("/interpolation=exp") for v in exp_sides if v.startswith("avsm-"))
    line = F.summary_lines({"claims": {"x": r}})["x"]
    assert line.startswith(f"{r['estimate']:.3g} [{r['low']:.3g}, {r['high']:.3g}]") and "4 configs" in line
    assert "\n" not in line and "{" not in line

def test_order_dependent_kinds_are_the_streaming_insertions():
    assert [k for k in ad.kinds() if E.order_dependent(k)] == ["avsm", "avsm_adaptive"]
    assert E.ORDERS[0] == "depth" and set(E.ORDERS) == {"depth", "reverse_depth", "random", "submission"}


@pytest.mark.slow
def test_quick_run_writes_findings_with_intervals(tmp_path):
    out = E.run(quick=True, out=tmp_path / "ec", scenes=["plume"])
    f = json.loads((tmp_path / "ec" / "findings.json").read_text())
    assert f["claims"] and all({"low", "high", "estimate", "verdict", "per_config"} <= set(c)
                               for c in f["claims"].values())
    assert set(out["summary"]) == set(f["claims"])
    assert all({"order", "preset", "metrics", "indicative", "sides"} <= set(c) for c in f["claims"].values())
    import csv
    rows = list(csv.DictReader((tmp_path / "ec" / "data.csv").open()))
    by = {}
    for r in rows:
        if r["study"] == "main" and r["method"] in ("avsm", "avsm_adaptive"):
            by.setdefault((r["config"], r["setting"], r["receivers"], r["opaque"]), set()).add(r["order"])
    # the headlines under every order, on the same receivers; order-independent kinds: '-'
    assert {E.ORDERS} <= {tuple(sorted(v, key=E.ORDERS.index)) for v in by.values()}
    assert {r["order"] for r in rows if r["method"] == "fom"} == {"-"}
    main = [r for r in rows if r["method"] not in ("truth_vs_mitsuba",)]
    assert all(float(r["bytes"]) == float(r["bytes_sparse"]) and r["bytes_dense"] == r["bytes_per_texel"]
               for r in main)
    assert all(float(r["depth_l2"]) >= 0 for r in main if r["study"] == "main")
    assert set(f["orders"]["plume"]["avsm-8"]) == set(E.ORDERS[1:])


def test_share_interval_is_the_bootstrap_of_a_proportion():
    """Binomial replicates are the bootstrap of a 0/1 sample's mean: the interval agrees with
    stats.bootstrap_ci's to the Monte Carlo error of 4000 replicates (~0.1 of the interval's
    half-width here: tolerance 0.002 on a half-width of ~0.007)."""
    m = np.random.default_rng(1).random(5000) < 0.07
    p, lo, hi = F.share_ci(m, 4000)
    ref = stats.bootstrap_ci(m.astype(float), "mean", n_boot=4000)
    assert p == ref["estimate"] and abs(lo - ref["low"]) < 2e-3 and abs(hi - ref["high"]) < 2e-3
    assert F.share_ci(np.zeros(10, bool)) == [0.0, 0.0, 0.0]


# ------------------------------------------------------------------ slow kinds: no clock
def _optimal_settings(out):
    import csv
    return sorted({(r["config"], r["setting"]) for r in csv.DictReader((out / "data.csv").open())
                   if r["method"] == "optimal"})


def test_slow_kinds_are_chosen_by_work_not_by_a_clock(tmp_path, monkeypatch):
    """Which variants a configuration builds reads the kind's work estimate, never a clock: a
    process_time that jumps an hour per call (every build "slow" by CPU time) gives the same
    rows; a SLOW_WORK below every build leaves the offline optimum at its headline setting."""
    import itertools
    import time
    opts = dict(quick=True, scenes=["plume"], kinds=["optimal"])
    every = sorted(("s0-dir_a", E.label("optimal", p)) for p, _ in E.variants("optimal", True, sweep=True))
    clock = itertools.count(0.0, 3600.0)
    monkeypatch.setattr(time, "process_time", lambda: next(clock))
    E.run(out=tmp_path / "loaded", **opts)
    assert _optimal_settings(tmp_path / "loaded") == every and len(every) > 3
    assert json.loads((tmp_path / "loaded" / "findings.json").read_text())["slow_kinds"] == {}
    monkeypatch.setattr(E, "SLOW_WORK", 0.0)
    E.run(out=tmp_path / "tiny", **opts)
    assert _optimal_settings(tmp_path / "tiny") == [("s0-dir_a", "optimal-8")]
    slow = json.loads((tmp_path / "tiny" / "findings.json").read_text())["slow_kinds"]
    assert set(slow) == {"optimal"} and slow["optimal"] > 0


def test_optimal_work_estimate_follows_the_cost_model():
    """optimal_work: 150 per point, N K^2 and (3 linf + 2 exp) K^3 per texel on the padded block."""
    from avsm_dr.representations import _curve
    from experiments.error_curves.cost import optimal_work
    seg = ad.Segments.from_arrays([0, 2, 3], [0.1, 0.2, 0.5], [0.4, 0.3, 0.9], optical_depth=[0.5, 1.0, 2.0])
    assert list(np.diff(_curve.points(seg)["off"])) == [4, 2]     # two texels' exact-curve points, own buckets
    assert optimal_work(seg, {}) == 150 * 6 + 8 * (16 + 4)
    assert optimal_work(seg, {"nodes": 4, "norm": "linf", "interpolation": "exp", "precision": "float16"}) \
        == 150 * 6 + 4 * (16 + 4) + 5 * (64 + 8)

"""The ``temporal`` experiment (``python -m experiments temporal``): the flicker definition on
synthetic errors with known answers, the cached plume animation, the moving-camera
receivers, and a quick run through the CLI."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from avsm_dr import fluid
from helpers import quick_cli_run
from experiments import _common
import experiments.temporal as T
from experiments.temporal import metrics as M
from experiments.temporal import scenes as S


# ------------------------------------------------------------------ definition
def test_flicker_of_known_error_sequences():
    """e alternating +-a every frame: error a, flicker 2a, index sqrt(2); a frozen error:
    flicker 0; a drift of b per frame: flicker |b|; the content term is the reference's own
    change.  Exact in float64 (sums of equal squares)."""
    F, K, a, b = 6, 5, 0.03, 0.004
    ref = np.linspace(0.2, 0.9, F)[:, None] * np.ones((1, K))          # content changes 0.14 per frame
    sign = (-1.0) ** np.arange(F)[:, None]
    cases = {"alternating": (ref + a * sign, a, 2 * a),
             "frozen": (ref + a, a, 0.0),
             "drift": (ref + b * np.arange(F)[:, None], np.sqrt(np.mean((b * np.arange(F)) ** 2)), b)}
    for name, (est, err, fl) in cases.items():
        pf = M.per_frame(est, ref)
        np.testing.assert_allclose(pf["flicker"][1:], fl, rtol=1e-12, atol=1e-15, err_msg=name)
        np.testing.assert_allclose(pf["content"][1:], 0.7 / (F - 1), rtol=1e-12, err_msg=name)
        assert np.isnan(pf["flicker"][0]) and np.isnan(pf["content"][0])
        p = M.pooled(M.receiver_sums(est, ref), F)
        np.testing.assert_allclose(p["error"], err, rtol=1e-12, err_msg=name)
        np.testing.assert_allclose(p["flicker"], fl, rtol=1e-12, atol=1e-15, err_msg=name)
        np.testing.assert_allclose(p["flicker_per_content"], fl / (0.7 / (F - 1)), rtol=1e-12, atol=1e-15)
    p = M.pooled(M.receiver_sums(ref + a * sign, ref), F)
    assert p["flicker_index"] == pytest.approx(np.sqrt(2.0), rel=1e-12)
    assert M.pooled(M.receiver_sums(ref, ref), F)["flicker_index"] == 0.0        # no error: 0, not NaN


def test_uncorrelated_errors_have_flicker_index_one():
    """Independent zero-mean errors per frame: flicker^2 = 2 var, error^2 = var, index 1
    (sampling error of 4e5 normal values ~ 0.2 %; tolerance 2 %)."""
    rng = np.random.default_rng(5)
    ref = rng.random((4, 100_000))
    est = ref + 0.01 * rng.standard_normal(ref.shape)
    assert M.pooled(M.receiver_sums(est, ref), 4)["flicker_index"] == pytest.approx(1.0, rel=0.02)


def _disagreeing_series(F=4):
    """Four configurations whose errors disagree: |e| = 0.01, 0.02, 0.03, 0.04 at every receiver
    and frame (random signs), the last with 4x the receivers; pooled over all receivers the RMS
    error would be 0.0334 with a tight interval, per configuration first their mean is 0.025."""
    rng = np.random.default_rng(3)
    ms = [("exact", "exact", {}, "depth"), ("fom-4", "fom", {}, "depth")]
    series = {}
    for i, level in enumerate((0.01, 0.02, 0.03, 0.04)):
        K = 64 * (4 if i == 3 else 1)
        ref = rng.uniform(0.2, 0.8, (F, K))
        est = ref + level * rng.choice([-1.0, 1.0], (F, K))
        series[("smoke", f"c{i}")] = dict(exact=ref, truth=ref, est={"exact": ref, "fom-4": est},
                                          l2={m[0]: [np.ones(2, np.float32)] * F for m in ms},
                                          bytes={m[0]: 8.0 for m in ms}, sparse_bytes={m[0]: 8.0 for m in ms})
    return series, ms


def test_per_setting_intervals_take_the_configuration_as_unit():
    """Each configuration's statistic first, then the mean and its interval over configurations:
    an interval over the texels / receivers of the configurations pooled fails both asserts."""
    series, ms = _disagreeing_series()
    f = T.findings(series, ms, dict(frames=4, n_boot=500))
    v = f["per_setting"]["smoke"]["exact"]["fom-4"]
    assert v["n_configs"] == 4
    assert [v["per_config"][f"c{i}"]["error"] for i in range(4)] == pytest.approx([0.01, 0.02, 0.03, 0.04], rel=1e-12)
    assert v["error"]["estimate"] == pytest.approx(0.025, rel=1e-12)          # not the pooled 0.0334
    assert v["error"]["low"] < 0.02 and v["error"]["high"] > 0.03              # the configurations' spread
    assert f["per_setting"]["smoke"]["exact"]["exact"]["error"] == {"estimate": 0.0, "low": 0.0, "high": 0.0}


def test_recomputation_from_rows_matches_the_run():
    """data.csv's per-frame rows (as strings) give every configuration's statistics of the
    series (to rounding), hence the same intervals; one configuration: no interval."""
    series, ms = _disagreeing_series()
    f = T.findings(series, ms, dict(frames=4, n_boot=500))
    rows = [{k: str(v) for k, v in r.items()} for r in T._rows(series, ms)]
    per = M.per_config_from_rows(rows)
    again, headline = T.per_setting(per, ["smoke"], ms, 500)
    for vs in ("exact", "truth"):
        for label, _, _, _ in ms:
            got, want = again["smoke"][vs][label], f["per_setting"]["smoke"][vs][label]
            for key in M.STATISTICS:
                for k in ("estimate", "low", "high"):
                    assert got[key][k] == pytest.approx(want[key][k], rel=1e-8, abs=1e-15), (vs, label, key, k)
    assert headline["smoke"]["most_flicker"] == f["headline"]["smoke"]["most_flicker"] == "fom-4"
    one = M.config_ci({"c0": per[("smoke", "exact", "fom-4")]["c0"]})
    assert one["n_configs"] == 1 and one["error"]["estimate"] == pytest.approx(0.01) and np.isnan(one["error"]["low"])


@pytest.mark.parametrize("est, ref, name", [(np.zeros((1, 3)), np.zeros((1, 3)), "estimate"),
                                            (np.zeros((3, 3)), np.zeros((3, 4)), "reference")])
def test_metrics_reject_bad_shapes(est, ref, name):
    with pytest.raises(ValueError, match=f"^{name}:"):
        M.per_frame(est, ref)


# ------------------------------------------------------------------ animation
def test_plume_sequence_matches_simulate_plume_bit_for_bit(tmp_path):
    shape = (16, 24, 16)                   # the quick run's grid (kernels compiled once for both)
    seq = fluid.simulate_plume_sequence(shape, frames=2, start=2, stride=2, seed=1, cache=tmp_path)
    assert seq.shape == (2, *shape) and seq.dtype == np.float32
    for f in range(2):
        assert np.array_equal(seq[f], fluid.simulate_plume(shape, steps=2 + 2 * f, seed=1, cache=False))
    assert len(list(tmp_path.glob("plume_seq_*.npy"))) == 1
    assert np.array_equal(fluid.simulate_plume_sequence(shape, frames=2, start=2, stride=2, seed=1,
                                                        cache=tmp_path), seq)       # from the cache
    with pytest.raises(ValueError, match="^frames:"):
        fluid.simulate_plume_sequence(shape, frames=0, cache=False)
    with pytest.raises(ValueError, match="^kwargs:"):
        fluid.simulate_plume_sequence(shape, frames=1, start=1, cache=False, steps=3)


def test_turned_spot_orbits_its_aim_point():
    """A spot light turned about the vertical axis keeps its distance to its aim point (the point
    of its axis nearest the centre) and still aims at it; at 0 degrees it is unchanged; a
    directional light's direction turns alike."""
    from avsm_dr.scene import DirectionalLight, SpotLight
    spot = SpotLight(position=[2.0, 1.0, 0.5], direction=[-2.0, -0.25, -0.5], fov=40.0)
    centre = np.array([0.0, 0.75, 0.0])
    aim = spot.position + np.dot(centre - spot.position, spot.direction) * spot.direction
    assert np.allclose(S.turned(spot, 0.0, centre).position, spot.position)
    for deg in (0.25, 10.0, 90.0):
        t = S.turned(spot, deg, centre)
        v = aim - t.position
        assert isinstance(t, SpotLight) and t.fov == 40.0
        np.testing.assert_allclose(v / np.linalg.norm(v), t.direction, atol=1e-12)
        assert np.linalg.norm(v) == pytest.approx(np.linalg.norm(aim - spot.position), rel=1e-12)
        np.testing.assert_allclose(t.direction, S.rotate_y(spot.direction, deg), atol=1e-12)
    d = S.turned(DirectionalLight(direction=(1.0, -0.3, 0.25)), 5.0, centre).direction
    np.testing.assert_allclose(d, S.rotate_y(np.array([1.0, -0.3, 0.25]) / np.linalg.norm([1.0, -0.3, 0.25]), 5.0))


def test_full_run_has_ten_configurations_and_seeds_change_every_animation(tmp_path, monkeypatch):
    """FULL: >= 10 distinct configurations, every light of LIGHTS (the spot included); a
    different seed gives different content in every animation (frame-0 densities and hair
    strands of seeds 0 and 1, under the spot light; tiny grids)."""
    from avsm_dr.scene import SpotLight
    cfgs = [tuple(c) for c in T.FULL["configs"]]
    assert len(set(cfgs)) == len(cfgs) >= 10 and {li for _, li in cfgs} == set(T.LIGHTS) and "spot" in T.LIGHTS
    monkeypatch.setattr(fluid, "CACHE_DIR", tmp_path)
    P = dict(T.QUICK, frames=2, start_steps=2, n_receivers=64, hair_strands=20)
    a0, a1 = (T._animations(P, seed, ["spot"]) for seed in (0, 1))
    for setting in T.SETTINGS:
        f0, f1 = a0[(setting, "spot")](0), a1[(setting, "spot")](0)
        assert isinstance(f0.scene.light, SpotLight), setting
        assert not np.array_equal(f0.scene.density, f1.scene.density), setting
        if setting == "hair":
            assert not np.array_equal(f0.scene.hair.strands, f1.scene.hair.strands)
    assert not np.allclose(a0[("light", "spot")](1).scene.light.position, a0[("light", "spot")](0).scene.light.position)


def test_camera_receivers_stay_in_the_box_and_move():
    lo, hi = S.PLUME_BOX
    a, b = S.camera_points(S.PLUME_BOX, 0.0, 6), S.camera_points(S.PLUME_BOX, 10.0, 6)
    assert a.shape == (72, 3)
    for p in (a, b):
        assert np.all(p >= lo - 1e-12) and np.all(p <= hi + 1e-12)
    assert np.max(np.abs(a - b)) > 0.01
    with pytest.raises(ValueError, match="^fov:"):
        S.camera_points(S.PLUME_BOX, 0.0, 6, fov=90.0)


# -------------------------------------------------------------------- the run
def test_narrowed_runs_are_checked():
    P, _ = T.STUDY.params(True, methods=["avsm-8 staged sorted", "exact"], settings=["camera"])
    assert P["methods"] == ["exact", "avsm-8 staged sorted"] and P["settings"] == ["camera"]     # methods() order
    P, _ = T.STUDY.params(True, methods=["avsm-8 refit_l2 submission", "avsm-8 submission", "exact"])
    assert P["methods"] == ["exact", "avsm-8 submission", "avsm-8 refit_l2 submission"]
    for kw, name in ((dict(methods=["avsm-8 nope sorted"]), "methods"), (dict(methods=[]), "methods"),
                     (dict(settings=["wind"]), "settings"), (dict(settings=[]), "settings")):
        with pytest.raises(ValueError, match=f"^{name}:"):
            T.STUDY.params(True, **kw)


def test_submission_rows_come_last_in_submission_order():
    """``avsm-8 submission`` and one ``avsm-8 <insertion> submission`` per variant, unsorted, on
    the ``'submission'`` capture, after every other row (whose order and parameters they leave alone)."""
    ms = T.methods(quick=True)
    sub = [m for m in ms if m[3] == "submission"]
    assert [m[0] for m in sub] == ["avsm-8 submission"] + [f"avsm-8 {i} submission" for i in T.insertion_variants()]
    assert ms[-len(sub):] == sub and all(m[1] == "avsm" and m[2]["sort"] is False for m in sub)
    assert {m[3] for m in ms[:-len(sub)]} == {"depth", "random"}
    assert all(m[3] == "random" for m in ms if m[0].endswith(" unsorted"))


def test_insertion_claims_skip_stream_rows_not_run():
    """A narrowed run without random-order stream AVSM: its variants keep the flicker-vs-sorted
    claim and lose only the comparisons that need the missing row.  Synthetic errors: the
    variant's alternate +-0.01, sorted AVSM's +-0.02, so the flicker ratio is 0.5."""
    from avsm_dr.stats import claim
    F, K = 4, 50
    ref = np.zeros((F, K))
    sign = (-1.0) ** np.arange(F)[:, None] * np.ones((1, K))
    p = dict(nodes=8, sort=False)
    ms = [("avsm-8 sorted", "avsm", dict(p, sort=True), "depth"),
          ("avsm-8 refit_l2 unsorted", "avsm", dict(p, insertion="refit_l2"), "random"),
          ("avsm-8 refit_l2 submission", "avsm", dict(p, insertion="refit_l2"), "submission")]
    est = {"avsm-8 sorted": 0.02 * sign, "avsm-8 refit_l2 unsorted": 0.01 * sign,
           "avsm-8 refit_l2 submission": 0.01 * sign}
    series = {("camera", "s0-dir_a"): dict(exact=ref, truth=ref, est=est)}
    out = T.insertion_claims(series, "camera", ["s0-dir_a"], ms, claim, 100)
    assert set(out) == {"avsm-8 refit_l2 unsorted", "avsm-8 refit_l2 submission"}
    for rec in out.values():
        assert set(rec["exact"]) == {"flicker_vs_sorted", "verdict"}
        assert rec["exact"]["flicker_vs_sorted"]["ratio"] == pytest.approx(0.5, rel=1e-12)
        assert rec["exact"]["verdict"] == "less"
        fl = rec["exact"]["flicker_vs_sorted"]       # holds in its one configuration, but 1 < MIN_EVERY
        assert fl["high"] < 1 and fl["indicative"] and not fl["holds_in_every_configuration"]
    cfgs = [f"s{s}-dir_a" for s in range(T.MIN_EVERY)]
    many = T.insertion_claims({("camera", c): series[("camera", "s0-dir_a")] for c in cfgs}, "camera", cfgs, ms,
                              claim, 100)
    fl = many["avsm-8 refit_l2 unsorted"]["exact"]["flicker_vs_sorted"]
    assert fl["n_configs"] == T.MIN_EVERY and fl["holds_in_every_configuration"] and not fl["indicative"]


def test_claims_resample_each_receivers_tile_with_all_its_frames():
    """Values of a claim are e[t, i] raveled frame by frame: each gets receiver i's tile."""
    series = {("smoke", "c"): dict(blocks=np.array([4, 4, 9]))}
    got = T._blocks_for(series, "smoke", ["c"], [np.zeros(6)])
    assert np.array_equal(got[0], [4, 4, 9, 4, 4, 9])
    assert T._blocks_for(series, "smoke", ["c"], [np.zeros(5)]) is None
    assert T._blocks_for({("smoke", "c"): {}}, "smoke", ["c"], [np.zeros(6)]) is None


@pytest.mark.slow   # 26 s; the page is tested against the committed full run
def test_quick_temporal_run(tmp_path, monkeypatch):
    monkeypatch.setattr(fluid, "CACHE_DIR", tmp_path / "cache")
    out = quick_cli_run("temporal", tmp_path)
    for name in ("data.csv", "findings.json", "meta.json", "error_flicker_per_frame.png", "flicker_vs_error.png",
                 "insertion_flicker.png", "shadow_smoke.gif"):
        assert (out / name).stat().st_size > 0, name
    rows = _common.read_csv(out / "data.csv")
    assert {r["setting"] for r in rows} == {"smoke", "light", "camera", "hair"}
    methods = {r["method"] for r in rows}
    assert {"exact", "avsm-8 unsorted", "avsm-8 sorted", "avsm_march-8"} <= methods
    exact = [r for r in rows if r["method"] == "exact" and r["vs"] == "exact"]
    assert exact and all(float(r["error_rms"]) == 0.0 for r in exact)
    assert all(float(r["flicker_rms"]) == 0.0 for r in exact if r["frame"] != "0")   # the same lookups
    moved = [float(r["content_rms"]) for r in exact if r["frame"] != "0"]
    assert min(moved) > 0                                                             # every animation moves
    f = json.loads((out / "findings.json").read_text())
    assert "8 x 8 texel tiles" in f["intervals"] and "over the configurations" in f["intervals"]
    for setting, block in f["per_setting"].items():
        assert block["exact"]["exact"]["flicker"]["estimate"] == 0.0
        un = block["exact"]["avsm-8 unsorted"]                 # one configuration: its value, no interval
        assert un["n_configs"] == 1 and un["error"]["estimate"] == un["per_config"]["s0-dir_a"]["error"] > 0
        assert np.isnan(un["error"]["low"]) and np.isnan(un["error"]["high"])
        assert f["headline"][setting]["most_flicker"] in methods
    from experiments.temporal.recompute import recompute      # the same numbers from data.csv
    again = recompute(out, tmp_path / "recomputed")
    assert (tmp_path / "recomputed" / "flicker_vs_error.png").stat().st_size > 0
    for setting, block in f["per_setting"].items():
        for label, v in block["truth"].items():
            assert again["per_setting"][setting]["truth"][label]["error"]["estimate"] == \
                pytest.approx(v["error"]["estimate"], rel=1e-8), (setting, label)
    assert again["claims"] == f["claims"] and again["headline"].keys() == f["headline"].keys()
    variants = {f"avsm-8 {ins} {order}" for ins in T.insertion_variants()
                for order in ("unsorted", "sorted", "submission")} | {"avsm-8 submission"}
    assert "stream" not in T.insertion_variants() and variants <= methods
    for setting, block in f["insertion"].items():
        assert set(block) == variants and setting in f["headline"]
        assert f["headline"][setting]["most_flicker"] not in variants            # one row per kind
        for label, rec in block.items():
            order = label.split(" ")[-1]
            for vs in ("exact", "truth"):
                keys = {"flicker_vs_sorted", "verdict"} | ({"flicker_vs_unsorted"} if order == "submission" else set())
                if label != "avsm-8 submission":
                    keys |= {"flicker_vs_stream", "error_vs_stream"}
                    assert rec[vs]["flicker_vs_stream"]["b"] == "avsm-8 " + order
                assert set(rec[vs]) == keys, (setting, label, vs)
                for key in keys - {"verdict"}:
                    c = rec[vs][key]
                    assert c["a"] == label and c["low"] <= c["ratio"] <= c["high"], (setting, label, vs, key)
                if order == "submission":
                    assert rec[vs]["flicker_vs_unsorted"]["b"] == "avsm-8 unsorted"
                fl = rec[vs]["flicker_vs_sorted"]
                assert fl["b"] == "avsm-8 sorted"
                assert rec[vs]["verdict"] == ("less" if fl["high"] < 1 else "more" if fl["low"] > 1
                                              else "indistinguishable")
    # every row records its capture order, sparse and dense bytes, the signed mean and
    # leak share at the receivers and the depth-uniform L2 of the curve
    order = {m[0]: m[3] for m in T.methods(quick=True)}
    for r in rows:
        assert r["order"] == order[r["method"]], r
        for k in ("bytes", "bytes_dense", "signed_mean", "leak_share", "depth_l2"):
            assert np.isfinite(float(r[k])), (k, r)
        assert float(r["bytes_dense"]) == float(r["bytes_per_texel"])
        assert 0 < float(r["bytes"]) <= float(r["bytes_dense"]) + 1
        assert 0 <= float(r["leak_share"]) <= 1 and float(r["depth_l2"]) >= 0
        assert (float(r["depth_l2"]) == 0) == (r["method"] == "exact"), r
    for setting in f["per_setting"]:
        assert set(f["curves"][setting]) == methods
        err = f["claims"][setting]["avsm_sorted_vs_unsorted_error"]
        assert set(err["metrics"]) == {"receiver_rmse", "depth_l2"} and err["order"] == ["depth", "random"]
        assert err["indicative"] and err["n_configs"] == 1 and err["interval_unit"] == "configuration"
        for m in err["metrics"].values():
            assert m["low"] <= m["estimate"] <= m["high"] and np.isfinite(m["estimate"])
        assert err["metric_dependent"] == (min(m["high"] for m in err["metrics"].values()) < 1
                                           < max(m["low"] for m in err["metrics"].values()))
        ev = f["insertion"][setting]["avsm-8 refit_l2 unsorted"]["exact"]["error_vs_stream"]
        assert set(ev["metrics"]) == {"receiver_rmse", "depth_l2"} and isinstance(ev["metric_dependent"], bool)
    cam = f["insertion"]["camera"]["avsm-8 submission"]["exact"]["flicker_vs_unsorted"]
    assert cam["high"] < 1    # content and light still: the same draw order gives the same map every frame
    from PIL import Image
    with Image.open(out / "shadow_smoke.gif") as im:
        assert im.n_frames == 5


def test_the_page_is_recomputed_from_the_committed_full_run(tmp_path):
    """docs/research/temporal/run holds the full run behind the temporal page (per-frame rows,
    findings, meta): recomputing it reproduces the run's per-configuration statistics, and the
    page's smoke table quotes them (Beer's error and flicker with their intervals)."""
    import gzip
    from experiments.temporal.recompute import recompute
    root = Path(__file__).resolve().parents[1]
    run = root / "docs" / "research" / "temporal" / "run"
    old = json.loads(gzip.decompress((run / "findings.json.gz").read_bytes()))
    new = recompute(run, tmp_path / "again")
    assert json.loads((run / "meta.json").read_text())["params"]["quick"] is False
    for setting, block in old["per_setting"].items():
        for label, v in block["exact"].items():
            for stat in ("error", "flicker"):
                assert new["per_setting"][setting]["exact"][label][stat]["estimate"] == \
                    pytest.approx(v[stat]["estimate"], rel=1e-8, abs=1e-12), (setting, label, stat)
    beer = new["per_setting"]["smoke"]["exact"]["beer"]
    row = "| beer | " + " | ".join(f"{beer[k]['estimate']:.4f} [{beer[k]['low']:.4f}, {beer[k]['high']:.4f}]"
                                   for k in ("error", "flicker"))
    assert row in (root / "docs" / "research" / "temporal.md").read_text()

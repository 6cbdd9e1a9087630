"""The memory-budget experiment (``python -m experiments memory_budget``): the equal-error byte
interpolation, the DSM byte matching, and one quick run through the CLI (rows at equal
bytes, findings with intervals, figures, cache)."""
from __future__ import annotations

import json
import math

import pytest

import avsm_dr as ad
from helpers import quick_cli_run
from experiments import _common, memory_budget as MB
from cases import random_segments, to_segments


def test_bytes_to_match_interpolates_log_log():
    b, e = [16, 32, 64, 128], [0.1, 0.01, 0.004, 0.004]
    assert MB.bytes_to_match(b, e, 0.01) == pytest.approx(32)
    # halfway in log error between 16 and 32 bytes: halfway in log bytes
    assert MB.bytes_to_match(b, e, math.sqrt(0.1 * 0.01)) == pytest.approx(math.sqrt(16 * 32))
    assert MB.bytes_to_match(b, e, 0.5) == 16                     # worse than the least budget
    assert math.isnan(MB.bytes_to_match(b, e, 0.001))             # better than fixed ever gets: censored
    assert MB.bytes_to_match(b, e, 0.004) == pytest.approx(64)    # the flat tail: the first budget reaching it
    # a non-monotone curve is read as the best error reached with at most those bytes
    assert MB.bytes_to_match([16, 32, 64], [0.1, 0.2, 0.01], 0.1) == 16


def test_dsm_at_bytes_stays_below_the_target(rng):
    seg = to_segments(random_segments(rng, texels=64, max_count=30))
    least = ad.build("dsm", seg, tolerance=0.5).nbytes_per_texel
    for target in (2.5 * least,):
        rep = MB.dsm_at_bytes(seg, target, steps=3)
        assert rep is not None and rep.nbytes_per_texel <= target
        assert rep.nbytes_per_texel > 0.7 * target                  # the search got close from below
    assert MB.dsm_at_bytes(seg, 0.9 * least) is None


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    return quick_cli_run("memory_budget", tmp_path_factory.mktemp("results"))


def test_quick_run_compares_at_equal_bytes(quick):
    rows = _common.read_csv(quick / "data.csv")
    meta = json.loads((quick / "meta.json").read_text())
    P = meta["params"]
    assert {r["method"] for r in rows} >= {"avsm", "adaptive", "adaptive_uniform", "dsm", "optimal"}
    for r in rows:
        b, budget = float(r["bytes_per_texel"]), float(r["budget_bytes_per_texel"])
        assert b <= budget + 1e-9, r                              # nobody exceeds the budget
        assert 0 <= float(r["rmse"]) <= 1 and 0 <= float(r["depth_rms"]) <= 1
        if r["method"] == "avsm":
            assert b == 8 * int(r["nodes"])                       # float32: 2 N x 4 bytes
            # the sparse baseline: an occupancy bit per texel, 8 N per non-empty texel
            filled = int(r["nonempty"]) / int(r["texels"])
            assert float(r["bytes_sparse"]) == pytest.approx(1 / 8 + 8 * int(r["nodes"]) * filled, rel=1e-12)
    orders = ["depth", "submission", "reverse_depth", "random"]
    assert P["orders"] == orders
    for n in P["budgets"]:
        for o in orders:                        # fixed and adaptive AVSM under every order, same receivers
            ad_rows = [r for r in rows if r["method"] == "adaptive" and int(r["nodes"]) == n and r["order"] == o
                       and r["interpolation"] == "linear"]
            fx = [r for r in rows if r["method"] == "avsm" and int(r["nodes"]) == n and r["order"] == o
                  and r["interpolation"] == "linear"]
            assert len(ad_rows) == len(fx) == len(P["scenes"])
    interp = {(r["method"], r["interpolation"]) for r in rows}
    for n in P["nodes"]:                    # AVSM's preset interpolation beside the headline's linear
        for i in ("linear", "exp"):
            assert len([r for r in rows if r["method"] == "avsm" and int(r["nodes"]) == n
                        and r["interpolation"] == i and r["order"] == "depth"]) == len(P["scenes"])
    assert {("adaptive", "exp"), ("adaptive", "linear")} <= interp
    assert {i for m, i in interp if m in ("dsm", "optimal")} == {"-"}
    # the preset's exp rows under every order too (fixed and adaptive), on the same receivers
    for m in ("avsm", "adaptive"):
        for o in orders:
            assert {int(r["nodes"]) for r in rows if r["method"] == m and r["interpolation"] == "exp"
                    and r["order"] == o} == set(P["nodes"] if m == "avsm" else P["budgets"]), (m, o)
    # both metrics, signed mean, leak share and both byte layouts on every row, finite
    for r in rows:
        for k in ("rmse", "depth_l2", "signed_mean", "leak_share", "bytes", "bytes_dense"):
            assert math.isfinite(float(r[k])), (k, r)
        assert float(r["bytes"]) == float(r["bytes_sparse"]) and float(r["bytes_dense"]) == float(r["bytes_per_texel"])
        assert 0 <= float(r["leak_share"]) <= 1 and abs(float(r["signed_mean"])) <= float(r["rmse"]) + 1e-12
    assert {r["order"] for r in rows if r["method"] in ("dsm", "optimal", "adaptive_uniform")} <= {"-", "depth"}
    assert {r["order"] for r in rows if r["method"] in ("dsm", "optimal")} == {"-"}
    # the allocation pays off on the plume at the smallest budget (measured: ratio ~0.04)
    f = json.loads((quick / "findings.json").read_text())
    r = f["rmse_ratio_adaptive_over_avsm"]["plume"]["N=2"]
    assert r["low"] <= r["estimate"] <= r["high"] < 1
    s = f["bytes_saved_at_equal_rmse"]["plume"]["N=2"]
    assert s["censored"] == 0 and 0 < s["saving"] < 1
    # the headline is against sparse fixed-N AVSM: charging its empty texels (dense) saves more
    # (measured on the quick plume: 0.10 sparse, 0.74 dense)
    assert f["bytes_saved_at_equal_rmse_dense_baseline"]["plume"]["N=2"]["saving"] > s["saving"]
    assert f["avsm_order"] == "depth" and set(f["bytes_saved_at_equal_rmse_by_order"]) == set(orders)
    assert f["bytes_saved_at_equal_rmse_by_order"]["depth"] == f["bytes_saved_at_equal_rmse"]
    # exp and linear AVSM differ (measured on the quick plume: exp / linear 1.3-2.6 at N = 2-8)
    e = f["rmse_ratio_avsm_exp_over_linear"]["plume"]["N=2"]
    assert e["low"] <= e["estimate"] <= e["high"] and e["estimate"] != pytest.approx(1, abs=1e-3)
    assert set(f["bytes_saved_at_equal_rmse_exp"]["plume"]) == {f"N={n}" for n in P["budgets"]}
    assert set(f["bytes_saved_at_equal_rmse_by_order_exp"]) == set(orders)
    assert f["bytes_saved_at_equal_rmse_by_order_exp"]["depth"] == f["bytes_saved_at_equal_rmse_exp"]
    assert r["indicative"] is True and s["indicative"] is True                   # one configuration
    # two-metric claims per order, configuration-level, flagged
    c = f["claims"]["plume"]["N=2"]
    for o in orders:
        k = "" if o == "depth" else f"@{o}"
        assert {f"adaptive{k}_over_avsm{k}", f"adaptive{k}/exp_over_avsm{k}/exp", f"avsm{k}/exp_over_avsm{k}"} <= set(c)
    for v in c.values():
        assert set(v["metrics"]) == {"receiver_rmse", "depth_l2"} and v["interval_unit"] == "configuration"
        assert all(m["low"] <= m["estimate"] <= m["high"] for m in v["metrics"].values())
        assert v["indicative"] is True and v["within_configuration"] == "8x8 texel blocks"
        assert isinstance(v["metric_dependent"], bool) and set(v["sides"]) == {"a", "b"}
    # measured on the quick plume, front to back at N = 2: exp over linear AVSM 1.34 [1.15, 1.63] at the
    # receivers, 0.85 [0.77, 0.94] in depth L2: the metrics disagree
    assert c["avsm/exp_over_avsm"]["metric_dependent"] is True
    assert c["avsm/exp_over_avsm"]["preset"] == {"a": False, "b": True}        # AVSM's preset is linear
    assert c["adaptive@random_over_avsm@random"]["preset"] == {"a": True, "b": True}
    figures = {"error_vs_bytes", "error_vs_bytes_depth", "allocation"}
    assert {p.name for p in quick.glob("*.png")} == {f + ".png" for f in figures}
    assert {p.name for p in quick.glob("*.pdf")} == {f + ".pdf" for f in figures}   # vector beside PNG
    again = MB.run(quick=True, out=quick)
    assert again.get("cached") is True


def test_page_tables_and_savings_from_the_run_files(quick):
    """The page's tables come from a run's files alone (one row, or one per metric or budget,
    per scene), and the savings recomputed from data.csv equal the run's findings (the CSV
    keeps 9 significant digits)."""
    from experiments.memory_budget import tables as TB
    rows, f, meta = TB.load(quick)
    again = TB.recompute(rows)
    assert set(again) == set(TB.SAVINGS)
    for k, per_scene in again.items():
        assert set(per_scene) == set(f[k]), k
        for scene, per_n in per_scene.items():
            for n, e in per_n.items():
                assert e["configs"] == f[k][scene][n]["configs"] and e["censored"] == f[k][scene][n]["censored"]
                want = f[k][scene][n].get("saving")
                assert e.get("saving") == (None if want is None else pytest.approx(want, rel=1e-6, abs=1e-9)), \
                    (k, scene, n)
    t = TB.page_tables(TB.with_scenes(f, meta))
    per_row = {"savings": 2, "savings_exp": 2, "by_order": 3, "by_order_exp": 3, "exp_over_linear_claims": 2}
    for name, lines in t.items():
        assert len(lines) == 2 + per_row.get(name, 1) * len(meta["params"]["scenes"]), name
        assert lines[1].startswith("| --- |") and lines[2].startswith("| plume |")
    # the table cell is the findings' value, two decimals
    s = f["bytes_saved_at_equal_rmse"]["plume"]["N=2"]
    assert t["savings"][2].split(" | ")[3].startswith(f"{s['saving']:.2f}")
    with pytest.raises(ValueError, match="run_dir"):
        TB.load(quick / "nowhere")


def test_full_mode_scenes_and_configurations():
    """Full mode: every built-in scene (error_curves' list), at least 10 configurations (seed x
    light) per scene, a spot light among them, each a valid avsm_dr.evaluation.Configuration;
    a bad light names its argument."""
    from avsm_dr.builtin_scenes import SCENES
    from avsm_dr.evaluation import Configuration
    from experiments import error_curves
    assert MB.FULL["scenes"] == error_curves.FULL["scenes"] == list(SCENES.names())
    assert len(MB.FULL["scenes"]) >= 10 and MB.QUICK["scenes"] == ["plume"]
    cfgs = [Configuration(s, li) for s, li in MB.FULL["configs"]]
    assert len({c.label for c in cfgs}) == len(cfgs) >= 10
    assert any(c.light == "spot" for c in cfgs)
    assert MB.FULL["interpolations"] == ["linear", "exp"] and ad.describe("avsm")["preset"]["interpolation"] == "linear"
    with pytest.raises(ValueError, match="light"):
        MB._resolve(dict(MB.QUICK, configs=[[0, "sun"]]), quick=True)
    with pytest.raises(ValueError, match="scenes"):
        MB.STUDY.params(quick=True, scenes=["plume", "nebula"])
    assert MB.STUDY.params(quick=False, scenes=["tall_column"])[0]["scenes"] == ["tall_column"]


def test_figure_layout_rows_of_at_most_five():
    """Ten scene panels: two rows of five; four: one row; never more than five a row."""
    from experiments._plotstyle import panel_shape
    from experiments.memory_budget.plots import COLUMNS

    def _shape(n):
        return panel_shape(n, COLUMNS)
    assert _shape(10) == (2, 5) and _shape(4) == (1, 4) and _shape(1) == (1, 1) and _shape(6) == (2, 3)
    assert all(r * c >= n and c <= 5 for n in range(1, 23) for r, c in [_shape(n)])


@pytest.mark.parametrize("scene", ["smoke_over_table", "particles"])
def test_spot_light_configuration_runs(scene):
    """A spot-light configuration (new in full mode) on an opaque-table scene and on particles:
    rows for fixed and adaptive AVSM in both interpolations, errors finite."""
    from avsm_dr.evaluation import Configuration
    P = dict(MB.QUICK, scenes=[scene], configs=[[1, "spot"]], nodes=[2, 4], budgets=[2], n_volume=64,
             orders=["depth"], optimal_max_n=0)
    rows, errors, heat = [], {}, {}
    MB._config_rows(scene, Configuration(1, "spot"), P, rows, errors, heat)
    got = {(r["method"], r["interpolation"], r["nodes"]) for r in rows}
    assert {("avsm", "linear", 4), ("avsm", "exp", 4), ("adaptive", "linear", 2), ("adaptive", "exp", 2)} <= got
    assert all(r["light"] == "spot" and 0 <= r["rmse"] <= 1 for r in rows)
    assert all(math.isfinite(float(v)) for e in errors.values() for v in e)


def _committed_run(name: str):
    """docs/research/memory_budget/<name>: a full-mode run (ten configurations per scene, the
    full mode's configurations) whose savings recompute from its data.csv; returns its
    findings, meta, the page's tables from it and the page's text."""
    from pathlib import Path
    from experiments.memory_budget import tables as TB
    root = Path(__file__).resolve().parents[1]
    rows, f, meta = TB.load(root / "docs" / "research" / "memory_budget" / name)
    P = meta["params"]
    assert P["quick"] is False and P["configs"] == MB.FULL["configs"]
    for scene in P["scenes"]:
        assert len({r["config"] for r in rows if r["scene"] == scene}) == len(MB.FULL["configs"]), scene
    again = TB.recompute(rows)
    for k in ("bytes_saved_at_equal_rmse", "bytes_saved_at_equal_depth_rms"):
        for scene, per_n in f[k].items():
            # the CSV's 9 digits give 1e-7 in absolute terms (1 - a / b near 0 keeps them only so),
            # except smoke_over_table's depth RMS, about 0.5 at every N (the page's caveat): log-log
            # interpolation between nearly equal errors magnifies the rounding (measured 6.7e-6 at N = 2)
            tol = 1e-4 if scene == "smoke_over_table" and "depth" in k else 1e-7
            for n, e in per_n.items():
                got = again[k][scene][n]
                assert got["censored"] == e["censored"]
                assert got.get("saving") == pytest.approx(e.get("saving"), abs=tol), (k, scene, n)
    page = (root / "docs" / "research" / "memory_budget.md").read_text()
    return f, meta, TB.page_tables(TB.with_scenes(f, meta)), page


def test_the_page_quotes_the_committed_gaussian_blobs_run():
    """docs/research/memory_budget/run_gaussian_blobs holds the full-mode run of the second
    particle scene behind the page's section on it, quoted verbatim."""
    f, meta, t, page = _committed_run("run_gaussian_blobs")
    assert meta["params"]["scenes"] == ["gaussian_blobs"]
    for name in ("savings", "by_order", "savings_exp", "adaptive_over_avsm", "avsm_exp_over_linear",
                 "uniform_allocation", "adaptive_over_uniform", "others"):
        assert "\n".join(t[name]) in page, name


def test_the_page_quotes_the_committed_nine_scene_run():
    """docs/research/memory_budget/run holds the full-mode run behind the page's findings (every
    built-in scene but gaussian_blobs, run alone): every table of the tables tool quoted verbatim
    before the page's section on the second particle scene."""
    f, meta, tables, page = _committed_run("run")
    assert set(meta["params"]["scenes"]) == set(MB.FULL["scenes"]) - {"gaussian_blobs"}
    main = page.split("## The second particle scene")[0]
    assert len(tables) == 12
    for name, lines in tables.items():
        assert "\n".join(lines) in main, name

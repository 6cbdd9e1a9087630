"""The moments tuning study (experiments/moment_tuning.py): one quick run through the command
line, its tables' structure and the properties its numbers must have (held-out seeds, a
complete grid, the choice = the table's argmin, ordered intervals)."""
import json
import math
from collections import defaultdict

import numpy as np
import pytest

import avsm_dr as ad
from avsm_dr.evaluation import read_csv
from avsm_dr.representations.moments import DEFAULT_BIAS, DEFAULT_TRIG_BIAS
from experiments import error_curves as EC
from experiments import moment_tuning as S
from helpers import quick_cli_run

TEXT = ("scene", "config", "light", "opaque", "group", "family", "target", "order")
FLAGS = ("default",)


def _typed(row: dict) -> dict:
    """A CSV row with its numbers parsed (the CSV holds text)."""
    out = {}
    for k, v in row.items():
        out[k] = v if k in TEXT else (v == "True") if k in FLAGS else float(v)
    return out


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = quick_cli_run("moment_tuning", tmp_path_factory.mktemp("moment_tuning"))
    rows = [_typed(r) for r in read_csv(out / "data.csv")]
    table = [_typed(r) for r in read_csv(out / "sensitivity.csv")]
    return rows, table, json.loads((out / "findings.json").read_text()), out


def _setting(r):
    return (r["target"], r["alpha_factor"], r["beta"])


def test_seeds_are_held_out_from_error_curves(quick):
    rows, _, found, _ = quick
    ec = {s for s, _ in EC.FULL["configs"]} | {s for s, _ in EC.QUICK["configs"]}
    for P in (S.FULL, S.QUICK):
        assert not {s for s, _ in P["configs"]} & ec
    assert not {int(r["seed"]) for r in rows} & ec
    assert found["seeds_disjoint"] is True and set(found["error_curves_seeds"]) == ec
    assert set(found["held_out_seeds"]) == {int(r["seed"]) for r in rows}
    with pytest.raises(ValueError, match="held out"):
        S._resolve(dict(S.QUICK, configs=[[0, "dir_a"], [100, "spot"]]), True)


def test_every_grid_point_in_every_cell(quick):
    rows, table, _, out = quick
    P = S.QUICK
    cells = defaultdict(list)
    for r in rows:
        cells[(r["scene"], r["config"], r["group"])].append(r)
    groups = {S.group_label(f, n): f for f, n in P["groups"]}
    assert len(cells) == len(P["scenes"]) * len(P["configs"]) * len(groups)
    for (scene, config, group), rs in cells.items():
        want = S.grid(P, groups[group])
        assert sorted(_setting(r) for r in rs) == sorted(want), (scene, config, group)
        assert sum(r["default"] for r in rs) == 1
        d = next(r for r in rs if r["default"])
        assert d["beta"] == 0.25 and d["target"] == "default"
        table_ = DEFAULT_TRIG_BIAS if d["family"] == "trigonometric" else DEFAULT_BIAS
        assert d["alpha"] == pytest.approx(table_[int(d["moments"])]["float32"])
        # ratios to the cell's best: >= 1, the best is 1
        for m in S.METRICS:
            assert min(r[f"ratio_{m}"] for r in rs) == pytest.approx(1.0)
            assert all(r[f"ratio_{m}"] >= 1 - 1e-12 for r in rs)
        assert all(np.isfinite(r[m]) and r[m] >= 0 for r in rs for m in S.METRICS)
    assert len(table) == sum(len(S.grid(P, f)) for f, _ in P["groups"])
    assert {r["opaque"] for r in rows} == {"separate"}                      # the preset's capture
    # both metrics: the capture order, sparse and dense bytes and the leak share on every row
    assert {r["order"] for r in rows} == {"depth"}
    assert all(r["bytes_dense"] == r["bytes_per_texel"] and 0 < r["bytes"] and 0 <= r["leak_share"] <= 1
               for r in rows)
    assert (out / "moment_tuning.png").is_file() and (out / "moment_tuning.pdf").is_file()


def test_sensitivity_is_the_geometric_mean_of_the_data(quick):
    rows, table, _, _ = quick
    for t in table[::7]:
        sel = [r for r in rows if r["group"] == t["group"] and _setting(r) == _setting(t)]
        assert len(sel) == t["n_cells"]
        for m in S.METRICS:
            assert t[f"ratio_{m}"] == pytest.approx(math.exp(np.mean(np.log([r[f"ratio_{m}"] for r in sel]))),
                                                    rel=1e-6)
        assert t["signed_mean"] == pytest.approx(np.mean([r["signed_mean"] for r in sel]), abs=1e-9)


def test_choice_is_the_argmin_of_the_table(quick):
    _, table, found, _ = quick
    for g, d in found["groups"].items():
        sel = [r for r in table if r["group"] == g]
        for metric, key in (("depth_l2", "chosen"), ("rmse", "rmse_choice")):
            best = min(sel, key=lambda r: r[f"ratio_{metric}"])
            c = d[key]
            assert (c["target"], c["alpha_factor"], c["beta"]) == _setting(best), (g, metric)
            assert min(r[f"ratio_{metric}"] for r in sel) == pytest.approx(
                next(r for r in sel if _setting(r) == _setting(best))[f"ratio_{metric}"])
        assert d["same_choice"] == ((d["chosen"]["target"], d["chosen"]["alpha_factor"], d["chosen"]["beta"])
                                    == (d["rmse_choice"]["target"], d["rmse_choice"]["alpha_factor"],
                                        d["rmse_choice"]["beta"]))
        assert d["metric_dependent"] == (not d["same_choice"]
                                         and d["rmse_cost_of_depth_l2_choice"] > 1 + S.METRIC_TOLERANCE)
        assert d["rmse_cost_of_depth_l2_choice"] >= 1 - 1e-12
    pt = found["preset"]["by_beta"]
    assert found["preset"]["beta"] == min(pt, key=lambda r: r["ratio_depth_l2"])["beta"]
    assert found["preset"]["rmse_beta"] == min(pt, key=lambda r: r["ratio_rmse"])["beta"]


def test_improvement_is_recomputed_from_the_rows(quick):
    rows, _, found, _ = quick
    for g, d in found["groups"].items():
        c = d["chosen"]
        for m in S.METRICS:
            cells = defaultdict(dict)
            for r in rows:
                if r["group"] == g:
                    cells[(r["scene"], r["config"])]["d" if r["default"] else _setting(r)] = r[m]
            ratios = [v[(c["target"], c["alpha_factor"], c["beta"])] / v["d"] for v in cells.values()]
            iv = d["tuned_over_default"][m]
            assert iv["n_configs"] == len(ratios)
            assert iv["estimate"] == pytest.approx(math.exp(np.mean(np.log(ratios))), rel=1e-9)
            assert iv["estimate"] <= 1 + 1e-12      # the default is a grid point: the choice is no worse in-sample
    beats = all(o[m]["high"] < 1 for o in found["preset"]["preset_over_default"].values() for m in S.METRICS)
    assert found["preset"]["preset_beats_defaults"] == beats


def _intervals(obj):
    if isinstance(obj, dict):
        if {"estimate", "low", "high"} <= set(obj):
            yield obj
        for v in obj.values():
            yield from _intervals(v)
    elif isinstance(obj, list):
        for v in obj:
            yield from _intervals(v)


def test_intervals_are_ordered(quick):
    _, _, found, _ = quick
    ivs = list(_intervals(found))
    assert len(ivs) > 10
    for iv in ivs:
        assert 0 < iv["low"] <= iv["estimate"] <= iv["high"], iv
        assert iv["level"] == 0.95


def test_the_kinds_preset_beta_is_on_the_studys_grid():
    """The study measures the preset it justifies (and MBOIT's default beside it)."""
    d = ad.describe("moments")
    beta = d["preset"].get("overestimation", d["params"]["overestimation"]["default"])
    assert beta in S.FULL["betas"] and S.default_beta() in S.FULL["betas"]
    assert d["preset"]["depth_range"] == "texel"

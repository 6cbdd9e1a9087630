"""The moment-storage experiment (``python -m experiments moment_storage``): one quick run
through the CLI (rows per variant and alpha choice, tuning on a held-out seed, claims with
intervals that match the CSV, bytes per texel, figure, cache)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from helpers import quick_cli_run
from experiments import _common, moment_storage as MS


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    return quick_cli_run("moment_storage", tmp_path_factory.mktemp("results"))


def _rmse(rows, **match):
    (r,) = [r for r in rows if all(r[k] == v for k, v in match.items())]
    return float(r["rmse"])


def test_quick_run_rows_bytes_and_tuning(quick):
    rows = _common.read_csv(quick / "data.csv")
    P = json.loads((quick / "meta.json").read_text())["params"]
    F = json.loads((quick / "findings.json").read_text())
    labels = [MS.label(*v) for v in MS.VARIANTS]
    modes = {"inline", "separate"}                        # the quick scene has a blocker: the control runs
    assert {r["opaque"] for r in rows} == modes
    assert len(rows) == len(P["scenes"]) * len(modes) * len(P["configs"]) * len(labels) * len(MS.TAGS)
    assert {r["variant"] for r in rows} == set(labels) and {r["tag"] for r in rows} == set(MS.TAGS)
    for r in rows:
        assert math.isfinite(float(r["rmse"])) and float(r["rmse"]) > 0, r
        assert float(r["max_error"]) >= float(r["rmse"]) >= abs(float(r["mean_error"])), r
        if r["tag"] == "tuned":                           # the tuned alpha is the one findings report
            assert float(r["alpha"]) == F["best_alpha"][r["opaque"]][r["variant"]], r
    # the held-out seed is never evaluated
    assert P["tune_seed"] not in {int(r["seed"]) for r in rows}
    # bytes: 5 float32; 5 16-bit codes + a float32 scale; 4 16-bit codes + b_0 in float32
    b = F["bytes_per_texel"]
    assert b["float32"] == 20 and b["float16/scaled"] == b["unorm16/scaled"] == 14
    assert b["float16/msm"] == b["unorm16/msm"] == 12
    assert all(float(r["bytes_per_texel"]) == b[r["variant"]] for r in rows)
    # the tuned alpha minimises the held-out seed's squared error summed over scenes and lights
    tune = _common.read_csv(quick / "tuning.csv")
    assert {int(r["seed"]) for r in tune} == {P["tune_seed"]}
    for mode in modes:
        for lab in labels:
            sse = [sum(float(r["rmse"]) ** 2 for r in tune if r["opaque"] == mode and r["variant"] == lab
                       and float(r["alpha"]) == a) for a in P["alphas"]]
            assert F["best_alpha"][mode][lab] == P["alphas"][int(np.argmin(sse))], (mode, lab, sse)


def test_quick_run_claims_match_the_csv(quick):
    rows = _common.read_csv(quick / "data.csv")
    P = json.loads((quick / "meta.json").read_text())["params"]
    claims = json.loads((quick / "findings.json").read_text())["claims"]
    n_claims = 1 + 4 * len(MS.TAGS) + 2 * len(MS.TAGS)   # float32 default, 4 variants, 2 msm-vs-scaled
    for scene, by_mode in claims.items():
        for mode, d in by_mode.items():
            assert len(d) == n_claims, sorted(d)
            for key, c in d.items():
                assert c["n_configs"] == len(P["configs"]) and len(c["per_config"]) == len(P["configs"])
                assert 0 < c["low"] <= c["estimate"] <= c["high"] < math.inf, (key, c)
                for est, lo, hi in c["per_config"].values():
                    assert lo <= est <= hi, (key, c)
            for prec in ("float16", "unorm16"):
                for tag in MS.TAGS:
                    c = d[f"{prec} msm vs scaled ({tag})"]
                    for config, (est, _, _) in c["per_config"].items():
                        m = dict(scene=scene, opaque=mode, config=config, tag=tag)
                        ratio = _rmse(rows, variant=f"{prec}/msm", **m) / _rmse(rows, variant=f"{prec}/scaled", **m)
                        assert est == pytest.approx(ratio, rel=1e-7)      # CSV keeps 9 significant digits
                    # the pooled estimate is the geometric mean of the per-configuration ratios
                    logs = [math.log(v[0]) for v in c["per_config"].values()]
                    assert c["estimate"] == pytest.approx(math.exp(sum(logs) / len(logs)), rel=1e-12)
                    assert c["holds_in_every_configuration"] == all(v[2] < 1 for v in c["per_config"].values())
    assert list(quick.glob("*.png"))
    assert MS.run(quick=True, out=quick).get("cached") is True


def test_quick_run_both_metrics(quick):
    """Every row carries the depth L2, signed mean, leak share, both byte layouts and
    the order ('-': moments do not depend on it); every claim both metrics with configuration-level
    intervals, metric_dependent, indicative (2 configurations) and each side's signed mean and
    leak share; the receiver RMSE estimate is the claim's own."""
    rows = _common.read_csv(quick / "data.csv")
    claims = json.loads((quick / "findings.json").read_text())["claims"]
    for r in rows:
        for k in ("depth_l2", "signed_mean", "leak_share", "bytes", "bytes_dense"):
            assert math.isfinite(float(r[k])), (k, r)
        assert r["order"] == "-" and float(r["signed_mean"]) == float(r["mean_error"])
        assert 0 <= float(r["leak_share"]) <= 1 and float(r["depth_l2"]) >= 0
        assert float(r["bytes_dense"]) == float(r["bytes_per_texel"])
    for by_mode in claims.values():
        for d in by_mode.values():
            for key, c in d.items():
                assert set(c["metrics"]) == {"receiver_rmse", "depth_l2"}, key
                assert c["metrics"]["receiver_rmse"]["estimate"] == pytest.approx(c["estimate"], rel=1e-12)
                assert all(m["low"] <= m["estimate"] <= m["high"] for m in c["metrics"].values()), key
                assert c["indicative"] is True and c["interval_unit"] == "configuration" and c["order"] == "-"
                assert c["within_configuration"] == "8x8 texel blocks" and isinstance(c["metric_dependent"], bool)
                assert all(0 <= x["leak_share"] <= 1 for x in c["sides"].values())


def test_tuning_seed_must_be_held_out(monkeypatch, tmp_path):
    monkeypatch.setitem(MS.QUICK, "configs", MS.QUICK["configs"] + [[MS.QUICK["tune_seed"], "dir_a"]])
    with pytest.raises(ValueError, match="^tune_seed"):
        MS.run(quick=True, out=tmp_path)

"""The spatial-vs-depth budget experiment (``python -m experiments spatial_budget``) and the reference
transmittance it and ``images`` are measured against."""
from __future__ import annotations

import json

import numpy as np
import pytest

import avsm_dr as ad
from helpers import quick_cli_run
from experiments import _common, images
from experiments import spatial_budget as budget


def test_fit_spends_the_budget_on_the_size_parameter():
    """Largest size value that fits: AVSM 8 bytes per node, FOM 4 (2n + 1), OSM 4 per slice
    (float32), read through the registry."""
    assert budget.fit("avsm", 128.0) == dict(ad.describe("avsm")["headline"], nodes=16)
    assert budget.fit("avsm", 127.9)["nodes"] == 15
    assert budget.fit("fom", 124.0)["harmonics"] == 15
    assert budget.fit("osm", 32.0)["slices"] == 8
    assert budget.fit("avsm", 8.0) is None                       # fewer bytes than 2 nodes
    for kind, per in (("avsm", 300.0), ("fom", 61.0), ("osm", 17.0)):
        p = budget.fit(kind, per)
        size = ad.describe(kind)["size"]
        assert budget.bytes_per_texel(kind, **p) <= per < budget.bytes_per_texel(kind, **dict(p, **{size: p[size] + 1}))


def test_plan_keeps_bytes_per_map():
    B = 1 << 19
    pl = budget.plan(B, [64, 128, 256])
    assert ("avsm", 64, {"nodes": 16}) in [(k, r, {ad.describe(k)["size"]: p[ad.describe(k)["size"]]})
                                           for k, r, p in pl if k == "avsm"]
    for kind, r, p in pl:
        assert r * r * budget.bytes_per_texel(kind, **p) <= B
    mom = [(r, p["moments"]) for k, r, p in pl if k == "moments"]
    fits = [r for r in (64, 128, 256) if B / r ** 2 >= budget.bytes_per_texel("moments", moments=4)]
    assert [r for r, _ in mom] == fits and len(fits) >= 2        # moments trade count for resolution too
    assert all(m in (4, 6, 8) for _, m in mom) and mom[0][1] == 8


def test_fit_skips_sizes_the_schema_does_not_allow():
    """Power moments come in even counts (5, 7, 9 stored floats): the largest allowed one fits."""
    assert budget.fit("moments", 27.9)["moments"] == 4
    assert budget.fit("moments", 28.0)["moments"] == 6
    assert budget.fit("moments", 100.0)["moments"] == 8
    assert budget.fit("moments", 19.9) is None


@pytest.mark.mitsuba
def test_quadrature_light_is_the_groundtruth_raymarch():
    """The images/budget reference T (Dr.Jit, one lane per point) equals
    groundtruth.transmittance(method='raymarch') on the same midpoints (float64 sums in
    another order: 1e-12), with the table (a blocker) as an analytic factor."""
    for scene in (ad.scenes.three_columns(size=8), ad.scenes.smoke_over_table(size=8)):
        lo, hi = (np.asarray(b, float) for b in scene.bbox)
        p = np.concatenate([scene.receivers[::8],
                            lo + np.random.default_rng(0).random((200, 3)) * (hi - lo)])
        want = ad.groundtruth.transmittance(scene, p, method="raymarch")[0]
        got = images.quadrature_light(scene)(p)
        assert want.min() < 0.5
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_quick_spatial_budget_run(tmp_path):
    out = quick_cli_run("spatial_budget", tmp_path)
    rows = _common.read_csv(out / "data.csv")
    assert {r["kind"] for r in rows} >= {"exact", "avsm", "fom", "osm", "moments"}
    assert {r["receivers"] for r in rows} == {"all", "volume", "surface"}
    for r in rows:
        assert float(r["rmse"]) >= 0 and int(r["nan_count"]) == 0
        assert float(r["lookup_ns"]) > 0
        if r["kind"] != "exact":
            assert int(float(r["map_bytes"])) <= int(r["budget_bytes"])
        # order, sparse / dense bytes and the depth-uniform L2 of the curve on every row
        assert r["order"] == "depth" and float(r["bytes_dense"]) == float(r["bytes_per_texel"]) > 0
        assert float(r["bytes"]) > 0 and np.isfinite(float(r["depth_l2"]))
        assert (float(r["depth_l2"]) == 0) == (r["kind"] == "exact"), r
    # at equal bytes a finer map with fewer nodes is a different trade-off, not the same numbers
    avsm = {int(r["resolution"]): float(r["rmse"]) for r in rows if r["kind"] == "avsm" and r["receivers"] == "all"}
    assert len(avsm) == 2 and avsm[64] != avsm[128]
    findings = json.loads((out / "findings.json").read_text())
    item = findings[f"plume_{1 << 19}B_avsm"]
    assert item["best_resolution"] in (64, 128)
    for v in item["per_resolution"].values():
        assert v["low"] <= v["rmse"] <= v["high"]
    ru = item["vs_runner_up"]
    assert ru["n_configs"] == 1 and ru["indicative"] and ru["interval_unit"] == "configuration"
    assert sorted(p.name for p in out.glob("*.png")) == ["error_vs_resolution.png", "lookup_cost.png"]
    again = budget.run(quick=True, out=out)
    assert again.get("cached") is True

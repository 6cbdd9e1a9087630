"""The learned depth warp experiment (``python -m experiments learned_warp``): a quick run
through the CLI writes its tables, findings with intervals and figures; training lowers the
training loss; ``findings`` on hand-made rows."""
from __future__ import annotations

import json

import numpy as np
import pytest

from experiments import _cli as cli
from experiments import _common, learned_warp


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("results")
    assert cli.main(["learned_warp", "--quick", "--out", str(out)]) == 0
    return out / "learned_warp"


def test_quick_run_writes_results(quick_run):
    rows = _common.read_csv(quick_run / "data.csv")
    kinds = [k for k, _ in learned_warp.KINDS]
    assert {r["kind"] for r in rows} == set(kinds)
    assert {"identity", "log", "learned"} <= {r["method"] for r in rows} <= {"identity", "log", "learned", "kind_log",
                                                                            "preset"}
    for kind in ("osm", "fom"):              # the per-texel-range preset is a baseline at equal bytes
        pre = [json.loads(r["params"]) for r in rows if r["kind"] == kind and r["method"] == "preset"]
        assert pre and all(p["depth_range"] == "texel" for p in pre), kind
    assert {r["split"] for r in rows} == {"train", "held_out"}
    assert {"depth_l2", "receiver_rmse", "signed_mean", "leak_share", "max_error", "bytes_per_texel", "group", "seed",
            "light"} <= set(rows[0])
    for r in rows:                           # both metrics measured in every row
        assert float(r["depth_l2"]) > 0 and float(r["receiver_rmse"]) > 0 and 0 <= float(r["leak_share"]) <= 1
    metric_rows = _common.read_csv(quick_run / "avsm_metric.csv")
    assert all(float(r["receiver_rmse"]) > 0 for r in metric_rows)
    for r in rows + metric_rows:             # order and sparse / dense bytes on every row
        assert r["order"] == "depth" and float(r["bytes_dense"]) == float(r["bytes_per_texel"]) > 0
        assert 0 < float(r["bytes"]) and np.isfinite(float(r["bytes"]))
    for kind in kinds:                       # equal bytes: one size per kind whatever the warp
        assert len({r["bytes_per_texel"] for r in rows if r["kind"] == kind}) == 1
    for name in ("warps.png", "error_per_scene.png", "loss.png", "avsm_metric.png", "meta.json", "losses.csv",
                 "warps.csv", "avsm_metric.csv", "avsm_metric_loss.csv"):
        assert (quick_run / name).is_file(), name
    warps = _common.read_csv(quick_run / "warps.csv")
    for kind in kinds:                       # monotone from 0 to 1 by construction
        w = np.array([float(r["w"]) for r in warps if r["kind"] == kind and r["method"] == "learned"])
        assert abs(w[0]) < 1e-12 and abs(w[-1] - 1) < 1e-6 and np.all(np.diff(w) > 0)


def test_training_lowers_the_loss(quick_run):
    """Adam from the identity lowers the training MSE for every kind, and for OSM and FOM
    the learned warp beats no warp on the training scenes at fresh receivers."""
    losses = _common.read_csv(quick_run / "losses.csv")
    for kind, _ in learned_warp.KINDS:
        v = [float(r["train_mse"]) for r in losses if r["kind"] == kind]
        assert v[-1] < v[0], (kind, v)
    f = json.loads((quick_run / "findings.json").read_text())
    for kind in ("osm", "fom"):
        assert f[kind]["train"]["learned_depth_l2"] < f[kind]["train"]["identity_depth_l2"]
    for kind in f:
        for g, e in f[kind].items():
            for c in (v for k, v in (e.items() if isinstance(e, dict) else ()) if k.startswith("learned_over_")):
                assert isinstance(c["metric_dependent"], bool), (kind, g)
                for metric in learned_warp.METRICS:
                    assert c[metric]["low"] <= c[metric]["ratio"] <= c[metric]["high"], (kind, g, metric)
    for kind in ("osm", "fom"):
        e = f[kind]["held_out_all"]
        assert {"preset_depth_l2", "preset_receiver_rmse", "learned_over_preset"} <= set(e)
        assert e["indicative"] is False
        assert 0 <= e["learned_over_preset"]["receiver_rmse"]["learned_smaller_in"] <= e["n_configs"]
    assert "preset_depth_l2" not in f["moments"]["train"]   # no moment count fits 20 B with a range
    m = f["avsm_metric"]
    assert 0 < m["beta_learned"] < 1 and m["bytes_per_texel"] == 64
    assert {"paper_depth_l2", "learned_receiver_rmse", "learned_over_paper"} <= set(m["held_out_all"])


def test_findings_on_hand_made_rows():
    """Ratios are means of per-configuration values, per metric; groups and their counts as
    given; a baseline the two metrics rank in opposite directions is metric-dependent."""
    rows = []
    for split, group, k in (("train", "smoke", 3), ("held_out", "hair_and_smoke", 2)):
        for s in range(k):
            for m, v, rec in (("identity", 0.2, 0.05), ("log", 0.4, 0.2), ("learned", 0.1, 0.1)):
                rows.append(dict(split=split, group=group, kind="osm", bytes_per_texel=32, method=m,
                                 depth_l2=v * (s + 1), receiver_rmse=rec * (s + 1)))
    f = learned_warp.findings(rows)["osm"]
    assert f["train"]["n_configs"] == 3 and f["hair_and_smoke"]["n_configs"] == 2
    assert f["held_out_other_types"]["n_configs"] == 2
    ident, log = f["train"]["learned_over_identity"], f["train"]["learned_over_log"]
    assert ident["depth_l2"]["ratio"] == pytest.approx(0.5) and ident["receiver_rmse"]["ratio"] == pytest.approx(2.0)
    assert ident["metric_dependent"] is True           # smaller in depth L2, larger at the receivers
    assert log["depth_l2"]["ratio"] == pytest.approx(0.25) and log["receiver_rmse"]["ratio"] == pytest.approx(0.5)
    assert log["metric_dependent"] is False
    assert f["train"]["identity_depth_l2"] == pytest.approx(0.4)
    assert f["train"]["identity_receiver_rmse"] == pytest.approx(0.1)


def test_metric_dependent_needs_two_established_directions():
    below, above, spans = dict(low=0.5, high=0.9), dict(low=1.1, high=1.5), dict(low=0.9, high=1.1)
    assert learned_warp.metric_dependent(below, above) and learned_warp.metric_dependent(above, below)
    assert not learned_warp.metric_dependent(below, below)
    assert not learned_warp.metric_dependent(below, spans)


def test_preset_params_at_equal_bytes():
    """OSM and FOM at their per-texel-range preset lower the size to the same bytes; moments
    (fewest moments + range > 20 B) get none."""
    import avsm_dr as ad
    from cases import random_segments, to_segments
    seg = to_segments(random_segments(np.random.default_rng(0), texels=8, max_count=4))
    osm = learned_warp.preset_params("osm", {"slices": 8}, seg)
    assert osm == {"slices": 6, "depth_range": "texel"}
    assert ad.build("osm", seg, **osm).nbytes_per_texel == ad.build("osm", seg, slices=8).nbytes_per_texel
    assert learned_warp.preset_params("fom", {"harmonics": 3}, seg) == {"harmonics": 2, "depth_range": "texel"}
    assert learned_warp.preset_params("moments", {}, seg) is None


def test_findings_flags_few_configurations():
    """Fewer than MIN_CONFIGS configurations: indicative; learned_smaller_in counts them."""
    rows = [dict(split="train", group="smoke", kind="osm", bytes_per_texel=32, method=m, depth_l2=v + 0.01 * s,
                 receiver_rmse=v) for s in range(3) for m, v in (("preset", 0.2), ("learned", 0.1 if s else 0.3))]
    e = learned_warp.findings(rows)["osm"]["train"]
    assert e["indicative"] is True and e["learned_over_preset"]["depth_l2"]["learned_smaller_in"] == 2


def test_blended_metric_avsm_at_beta_0_is_the_avsm_kind():
    """The experiment's hard AVSM (kind's insertion, blended removal) with beta = 0 gives
    the avsm kind's nodes bit for bit (same operations in the same order); beta > 0 moves
    them, and the surrogate (softmin) stays finite."""
    import avsm_dr as ad
    from experiments.learned_warp.avsm import _opaque, avsm_nodes
    from cases import random_segments, to_segments
    N = 5                                    # odd: the texel fills up with one clear node left
    seg = to_segments(random_segments(np.random.default_rng(3), texels=48, max_count=12))
    depths, values = ad.build("avsm", seg, nodes=N).nodes_numpy()
    lanes, d, t = avsm_nodes(seg, N, _opaque(0.0))
    got_d = np.stack([np.asarray(x) for x in d], 1)
    got_t = np.stack([np.asarray(x) for x in t], 1)
    np.testing.assert_array_equal(got_d, depths[lanes])
    np.testing.assert_array_equal(got_t, values[lanes])
    _, d2, _ = avsm_nodes(seg, N, _opaque(0.9))
    assert not np.array_equal(np.stack([np.asarray(x) for x in d2], 1), got_d)
    _, d3, t3 = avsm_nodes(seg, N, _opaque(0.3), _opaque(0.05))
    assert all(np.all(np.isfinite(np.asarray(x))) for x in d3 + t3)


def test_receiver_lookup_of_the_warp_matches_the_unwarped_kind():
    """At the in-volume receivers the identity warp (theta = 0) gives the unwarped kind's
    bilinear T (the warp's lookup path is only a change of depth variable), and the hard
    AVSM node lists at beta = 0 give the avsm kind's."""
    import avsm_dr as ad
    from experiments.learned_warp import SceneData, _receiver_rep, receiver_errors
    from experiments.learned_warp.avsm import NodeLists
    P = dict(learned_warp.QUICK, size=8, resolution=64, receivers_per_texel=2, n_volume=64)
    d = SceneData("smoke", "plume", 0, 0, P)
    plain = d.probe.lookup(ad.build("fom", d.seg, harmonics=3))
    warped = d.probe.lookup(_receiver_rep(d, "fom", {"harmonics": 3}, np.zeros(8)))
    np.testing.assert_allclose(warped, plain, atol=2e-5)
    assert np.any(np.abs(plain - d.exact_receivers) > 1e-4)   # FOM-3 is not the exact curve there
    np.testing.assert_allclose(d.probe.lookup(NodeLists(d.seg, 4, 0.0)),
                               d.probe.lookup(ad.build("avsm", d.seg, nodes=4)), atol=1e-6)
    e = receiver_errors(d, ad.build("exact", d.seg))
    assert e["receiver_rmse"] == 0 and e["leak_share"] == 0

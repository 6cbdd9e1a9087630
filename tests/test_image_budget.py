"""The image-budget study (experiments/image_budget): one quick run through the command line,
its tables' structure, the map and thresholds re-derived from data.csv, and the answer's rules
on synthetic arrays."""
import itertools
import json
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

from avsm_dr.evaluation import Configuration, read_csv
from avsm_dr.scene import SpotLight
from experiments import image_budget as S
from experiments.image_budget import analysis as A
from helpers import quick_cli_run

pytestmark = pytest.mark.mitsuba

TEXT = {"setting", "config", "kind", "label", "size_param", "size", "best_kind", "best_label", "order"}
BOOL = {"fits", "invisible", "threshold"}
FLIPS = ("flip", "flip_compression", "flip_spatial", "flip_resolution", "flip_render_noise", "flip_reference_noise")


def _typed(row: dict) -> dict:
    out = {}
    for k, v in row.items():
        out[k] = (v if k in TEXT else (v == "True") if k in BOOL
                  else int(v) if k in ("frame", "resolution", "n_configs") else float(v))
    return out


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = quick_cli_run("image_budget", tmp_path_factory.mktemp("image_budget"))
    P, _ = S.STUDY.params(quick=True)
    rows = [_typed(r) for r in read_csv(out / "data.csv")]
    cells = [_typed(r) for r in read_csv(out / "map.csv")]
    return rows, cells, json.loads((out / "findings.json").read_text()), P, out


def test_every_kind_budget_resolution_and_frame_is_present(quick):
    rows, _, _, P, out = quick
    keys = [(r["setting"], r["config"], r["kind"], r["budget"], r["resolution"], r["frame"]) for r in rows]
    assert len(keys) == len(set(keys))
    cfgs = [Configuration(s, li).label for s, li in P["configs"]]
    want = set(itertools.product(P["settings"], cfgs, P["kinds"], P["budgets"], P["resolutions"], range(P["frames"])))
    assert set(keys) == want and P["kinds"][0] == "exact" and len(P["kinds"]) >= 4
    for name in ("budget_map", "flip_vs_bytes", "frames"):
        assert (out / f"{name}.png").is_file() and (out / f"{name}.pdf").is_file()
    # every kind has a configuration within the largest budget; a configuration within a budget
    # is the one with the most (calibrated) bytes that fit
    for kind in P["kinds"][1:]:
        assert any(r["fits"] for r in rows if r["kind"] == kind and r["budget"] == max(P["budgets"]))
    for r in rows:
        assert r["fits"] == (r["calibrated_bytes"] <= r["budget"]), r
        assert r["bytes_per_texel"] > 0


def test_rows_carry_the_curve_metrics_of_their_maps(quick):
    """Every row records the capture order, sparse and dense bytes of the map that
    made the image, and that map's depth-uniform L2, signed mean and leak share against the
    exact curve (0 for exact; the smallest AVSM further from it than its largest)."""
    rows, _, _, _, _ = quick
    for r in rows:
        assert r["order"] == "depth" and r["bytes_dense"] == r["bytes_per_texel"] and r["bytes"] > 0, r
        for k in ("depth_l2", "curve_signed_mean", "curve_leak_share"):
            assert np.isfinite(r[k]), (k, r)
        assert 0 <= r["curve_leak_share"] <= 1 and r["depth_l2"] >= 0
        assert (r["depth_l2"] == 0) == (r["kind"] == "exact"), r
    first = rows[0]["config"]
    l2 = {r["label"]: r["depth_l2"] for r in rows if r["kind"] == "avsm" and r["frame"] == 0 and r["config"] == first}
    assert l2["avsm-2"] > l2[max(l2, key=lambda s: int(s.split("-")[1]))]
    _, cells, found, P, _ = quick
    assert all(np.isfinite(c["best_depth_l2"]) for c in cells if c["best_kind"])
    for s in P["settings"]:
        for res in P["resolutions"]:
            thr = found["thresholds"][s][str(res)]
            assert thr["n_configs"] == len(P["configs"]) and thr["interval_unit"] == "configuration"
            assert thr["indicative"] is (len(P["configs"]) < S.MIN_CONFIGS)
            assert "B/texel" in found["headline"][f"{s} {res}^2"] or "visible" in found["headline"][f"{s} {res}^2"]
            cur = found["curves"][s][str(res)]
            assert set(cur) == {r["label"] for r in rows if (r["setting"], r["resolution"]) == (s, res)}
            assert cur["exact"]["depth_l2"] == 0 and all(np.isfinite(v["depth_l2"]) for v in cur.values())


def test_flips_and_the_error_split(quick):
    rows, _, _, _, _ = quick
    for r in rows:
        for k in FLIPS:
            assert 0.0 <= r[k] <= 1.0, (k, r)
        assert r["flip_reference_noise"] > 0 and r["flip_render_noise"] > 0       # independent seeds differ
        if r["kind"] == "exact":
            assert r["flip_compression"] == 0.0 and r["mean_signed_compression"] == 0.0
            assert r["flip"] == r["flip_spatial"]
            assert r["frame"] == 0 or r["flicker_compression"] == 0.0
        elif r["frame"] > 0:
            assert r["flicker_compression"] >= 0 and r["flicker"] >= 0
    # a configuration is rendered once per frame and resolution: its rows agree at every budget
    by = defaultdict(set)
    for r in rows:
        by[(r["setting"], r["config"], r["frame"], r["resolution"], r["label"])].add(
            (r["flip"], r["flip_compression"], r["bytes_per_texel"]))
    assert all(len(v) == 1 for v in by.values())
    # the smallest AVSM loses to its largest (the study resolves compression)
    avsm = {r["label"]: r["flip_compression"] for r in rows
            if r["kind"] == "avsm" and r["frame"] == 0 and r["config"] == rows[0]["config"]}
    assert len(avsm) >= 2 and avsm["avsm-2"] > avsm[max(avsm, key=lambda s: int(s.split("-")[1]))]


def _means(rows, setting, res, budget):
    """{label: (mean compression FLIP, mean bytes, kind)} of the kinds within budget in every
    configuration (a kind's most common label), and the noise; every configuration has as
    many frames, so the mean over rows is the mean over configurations of their means."""
    sel = [r for r in rows if (r["setting"], r["resolution"], r["budget"]) == (setting, res, budget)]
    acc = defaultdict(list)
    for r in sel:
        acc[r["kind"]].append(r)
    noise = np.mean([r["flip_reference_noise"] for r in sel if r["kind"] == "exact"])
    out = {}
    for kind, rs in acc.items():
        if all(r["fits"] for r in rs):
            labels = [r["label"] for r in rs]
            out[max(labels, key=labels.count)] = (np.mean([r["flip_compression"] for r in rs]),
                                                  np.mean([r["bytes_per_texel"] for r in rs]), kind)
    return out, noise


def test_map_is_the_cheapest_invisible_or_least_visible_kind(quick):
    rows, cells, found, P, _ = quick
    assert len(cells) == len(P["settings"]) * len(P["resolutions"]) * len(P["budgets"])
    for c in cells:
        m, noise = _means(rows, c["setting"], c["resolution"], c["budget"])
        assert c["noise_flip"] == pytest.approx(noise)
        if not m:
            assert c["best_kind"] == ""
            continue
        comp, nbytes, kind = m[c["best_label"]]
        assert kind == c["best_kind"] and c["best_flip_compression"] == pytest.approx(comp)
        invisible = {lab: v for lab, v in m.items() if v[0] < noise}
        assert c["invisible"] == bool(invisible)
        if invisible:
            assert comp < noise and nbytes == min(v[1] for v in invisible.values())
        else:
            least = min(v[0] for v in m.values())
            assert comp <= least * (1 + A.TIE)
            assert nbytes == min(v[1] for v in m.values() if v[0] <= least * (1 + A.TIE))
    assert [c for c in cells if c["threshold"]] == [c for c in cells if c["budget"] == found["thresholds"][
        c["setting"]][str(c["resolution"])]["bytes"]]


def test_thresholds_and_their_intervals(quick):
    rows, cells, found, P, _ = quick
    assert set(found["thresholds"]) == set(P["settings"])
    for setting in P["settings"]:
        ref = found["reference"][setting]
        assert 0 < ref["noise_flip_mean"] < 0.1 and 0 < ref["se_rms_over_white"] < 0.05
        for res in P["resolutions"]:
            for key in ("thresholds", "thresholds_vs_render_noise"):
                thr = found[key][setting][str(res)]
                ci = thr["interval"]
                assert thr["indicative"] is (len(P["configs"]) < S.MIN_CONFIGS) and ci["unit"] == "configuration"
                assert ci["n"] == len(P["configs"]) == thr["n_configs"]
                if thr["reached"] and thr["kind"] != "exact":
                    cl = thr["claim"]
                    assert cl["n_configs"] == len(P["configs"]) and cl["low"] <= cl["estimate"] <= cl["high"]
                    assert cl["indicative"] is (len(P["configs"]) < S.MIN_CONFIGS)
                    assert cl["verdict"] != "holds in every configuration" or cl["n_configs"] >= S.MIN_EVERY
                if ci["low"] is not None and ci["high"] is not None:
                    assert ci["low"] <= ci["high"]
                if thr["reached"]:
                    assert thr["bytes"] in P["budgets"] and ci["estimate"] == thr["bytes"]
                    assert (ci["low"] is None or ci["low"] <= thr["bytes"]) and \
                           (ci["high"] is None or thr["bytes"] <= ci["high"])
                    assert thr["flip_compression"] < thr["noise_flip"] and thr["stored_bytes"] <= thr["bytes"]
            thr = found["thresholds"][setting][str(res)]
            inv = {b: {v[2] for v in m.values() if v[0] < noise}
                   for b in P["budgets"] for m, noise in [_means(rows, setting, res, b)]}
            stays = [b for b in P["budgets"] if set.intersection(*[inv[b2] for b2 in P["budgets"] if b2 >= b])]
            # the threshold: the smallest budget from which some kind is invisible at every larger budget
            assert thr["bytes"] == (min(stays) if stays else None)
            if thr["reached"]:
                assert all(thr["kind"] in inv[b] for b in P["budgets"] if b >= thr["bytes"])


def _pixels_differ(a, b) -> float:
    """Share of pixels of two PNG files that differ by more than a quarter of full scale in some
    channel (another FreeType build moves anti-aliasing by a level or two; a stale figure, a moved
    point or another colour, changes thousands of pixels by far more)."""
    from matplotlib.image import imread
    x, y = imread(a), imread(b)
    assert x.shape == y.shape, (a, b, x.shape, y.shape)
    return float((np.abs(x - y).max(axis=-1) > 0.25).mean())


def test_redraw_from_data_csv_gives_the_runs_figures(quick, tmp_path):
    """``redraw`` (``python -m experiments._replot image_budget data.csv``) recomputes the map
    from data.csv alone and draws the run's budget_map.png and flip_vs_bytes.png again."""
    from experiments import _replot
    rows, cells, _, P, out = quick
    typed = _replot.typed(read_csv(out / "data.csv"))
    got = S.params_from_rows(typed)
    assert {k: got[k] for k in ("settings", "configs", "frames", "resolutions", "budgets", "kinds")} == \
        {k: P[k] for k in ("settings", "configs", "frames", "resolutions", "budgets", "kinds")}
    _, again = S.findings(typed, got)
    assert [(c["setting"], c["resolution"], c["budget"], c["best_label"], c["invisible"], c["threshold"])
            for c in again] == [(c["setting"], c["resolution"], c["budget"], c["best_label"], c["invisible"],
                                 c["threshold"]) for c in cells]
    files = _replot.replot("image_budget", out / "data.csv", tmp_path)
    assert [f.name for f in files] == ["budget_map.png", "flip_vs_bytes.png"]
    for f in files:
        assert _pixels_differ(f, out / f.name) < 1e-3, f.name


def test_params_from_rows_rejects_what_is_not_a_run():
    with pytest.raises(ValueError, match="rows"):
        S.params_from_rows([])
    row = dict(setting="smoke", config="seed0", frame=0, resolution=64, budget=16, kind="exact")
    with pytest.raises(ValueError, match="rows: config 'seed0'"):
        S.params_from_rows([row])
    assert S.params_from_rows([dict(row, config="s3-spot")])["configs"] == [[3, "spot"]]


PAGE = Path(__file__).resolve().parents[1] / "docs" / "research" / "image_budget"
RUN = PAGE / "run"
_NO_RUN = pytest.mark.skipif(not (RUN / "data.csv.gz").is_file(),
                             reason="docs/research/image_budget/run (the page's full run) is not committed")


def threshold_row(setting: str, res, thr: dict) -> str:
    """The start of the page's threshold table row of ``thr`` (findings.json's ``thresholds``),
    up to its verdict: animation, map, budget [interval], label (stored bytes), compression /
    noise [interval]."""
    ci, cl = thr["interval"], thr["claim"]
    return (f"| {setting} | {res}^2 | {thr['bytes']:g} B [{ci['low']:g}, {ci['high']:g}] | `{thr['label']}` "
            f"({thr['stored_bytes']:.1f}) | {cl['estimate']:.2f} [{cl['low']:.2f}, {cl['high']:.2f}] | {cl['verdict']}")


def map_row(setting: str, res, cells: list[dict]) -> str:
    """The page's best-kind table row of one animation and resolution from map.csv's cells
    (budgets in order): label and compression / noise ratio per budget, the threshold in bold."""
    def cell(c):
        text = f"`{c['best_label']}`, {c['best_flip_compression'] / c['noise_flip']:.2g}x"
        return f"**{text}**" if c["threshold"] else text
    return f"| {setting} | {res}^2 | " + " | ".join(cell(c) for c in cells) + " |"


@_NO_RUN
def test_page_figures_are_drawn_from_the_committed_full_run(tmp_path):
    """docs/research/image_budget/{budget_map,flip_vs_bytes}.png are what the committed full
    run's data draws with this revision's plot code (redraw with ``python -m experiments._replot
    image_budget docs/research/image_budget/run/data.csv.gz --out docs/research/image_budget``)."""
    from experiments import _replot
    meta = json.loads((RUN / "meta.json").read_text())
    assert meta["experiment"] == "image_budget" and meta["params"]["quick"] is False
    files = _replot.replot("image_budget", RUN / "data.csv.gz", tmp_path)
    assert [f.name for f in files] == ["budget_map.png", "flip_vs_bytes.png"]
    for f in files:
        assert _pixels_differ(f, PAGE / f.name) < 1e-3, f"{f.name}: redraw the figure (command above)"


@_NO_RUN
def test_page_quotes_the_committed_full_run():
    """The page's noise line, threshold table and best-kind table are the committed run's
    findings.json and map.csv."""
    import gzip
    found = json.loads(gzip.decompress((RUN / "findings.json.gz").read_bytes()))
    cells = [_typed(r) for r in read_csv(RUN / "map.csv")]
    page = " ".join((PAGE.parent / "image_budget.md").read_text().split())
    for setting, ref in found["reference"].items():
        per = ref["noise_flip_per_config"].values()
        assert f"{ref['noise_flip_mean']:.4f} (`{setting}`, {min(per):.4f}-{max(per):.4f}" in page, setting
        for res, thr in found["thresholds"][setting].items():
            assert threshold_row(setting, res, thr) in page
            row = [c for c in cells if c["setting"] == setting and c["resolution"] == int(res)]
            assert map_row(setting, res, sorted(row, key=lambda c: c["budget"])) in page


# ------------------------------------------------------------------ the rules, synthetic
def test_threshold_needs_invisibility_at_every_larger_budget():
    fits = np.ones((2, 4), bool)
    nbytes = np.array([[16, 32, 64, 128], [12, 30, 60, 100]], float)
    # kind 0 invisible at 32 but visible again at 64; kind 1 invisible from 64 on
    comp = np.array([[0.5, 0.05, 0.2, 0.05], [0.5, 0.3, 0.05, 0.01]])
    assert A.threshold_index(comp, nbytes, fits, 0.1) == (2, 1)
    # both invisible from 64: the cheaper wins
    comp[0] = [0.5, 0.3, 0.05, 0.05]
    nbytes[1, 2] = 70.0
    assert A.threshold_index(comp, nbytes, fits, 0.1) == (2, 0)
    # a kind that does not fit at 128 cannot hold the threshold beyond it
    fits[0, 3] = False
    assert A.threshold_index(comp, nbytes, fits, 0.1) == (2, 1)
    assert A.threshold_index(comp, nbytes, fits, 0.001) == (None, None)


def test_cell_rules_and_ties():
    comp = np.array([0.30, 0.301, 0.2, 0.05])
    nbytes = np.array([12.0, 16.0, 20.0, 200.0])
    fits = np.array([True, True, False, False])
    assert A.best_in_cell(comp, nbytes, fits, 0.1) == (0, False)            # tie within TIE: the cheaper
    fits[2] = True
    assert A.best_in_cell(comp, nbytes, fits, 0.1) == (2, False)            # the least visible
    fits[3] = True
    assert A.best_in_cell(comp, nbytes, fits, 0.1) == (3, True)             # the only invisible one
    assert A.best_in_cell(comp, nbytes, fits, 0.5) == (0, True)             # all invisible: the cheapest
    assert A.best_in_cell(comp, nbytes, np.zeros(4, bool), 0.5) == (None, False)


def test_interval_over_configurations():
    """Configurations disagree: the bootstrap interval spans the budgets they point to."""
    rng = np.random.default_rng(0)
    C = 8
    base = np.array([[0.3, 0.2, 0.05, 0.01]])[..., None]
    comp = base * np.exp(rng.normal(0, 0.8, (1, 4, C)))
    ci = A.threshold_ci(comp, np.ones((1, 4, C)), np.ones((1, 4, C), bool), np.full(C, 0.1), [16, 32, 64, 128],
                        n_boot=300)
    assert ci["unit"] == "configuration" and ci["n"] == C
    assert ci["low"] != ci["high"]
    lo = ci["low"] if ci["low"] is not None else 256
    hi = ci["high"] if ci["high"] is not None else 256
    est = ci["estimate"] if ci["estimate"] is not None else 256
    assert lo <= est <= hi


def test_full_mode_runs_ten_configurations_with_a_spot_light():
    P, _ = S.STUDY.params(quick=False)
    cfgs = [Configuration(s, li) for s, li in P["configs"]]
    assert len({c.label for c in cfgs}) == len(cfgs) >= 10
    assert any(c.light == "spot" for c in cfgs) and len({c.seed for c in cfgs}) >= 4
    assert len(cfgs) >= S.MIN_EVERY > S.MIN_CONFIGS
    with pytest.raises(ValueError, match="configs"):
        S._resolve(dict(P, configs=[[0, "dir_a"]]), False)
    with pytest.raises(ValueError, match="light"):
        S._resolve(dict(P, configs=[[0, "dir_a"], [1, "sun"]]), False)


def test_seeds_change_the_plume_and_the_spot_light_turns_about_it():
    P, _ = S.STUDY.params(quick=True)
    P = dict(P, settings=["smoke", "light"])
    a, b = S.animations(P, 0, "dir_a"), S.animations(P, 1, "spot")
    assert not np.array_equal(a["smoke"](0).scene.density, b["smoke"](0).scene.density)
    s0, s1 = b["light"](0).scene.light, b["light"](1).scene.light
    assert isinstance(s0, SpotLight) and isinstance(s1, SpotLight)
    c = 0.5 * (np.asarray(S.S.PLUME_BOX[0]) + np.asarray(S.S.PLUME_BOX[1]))
    for li in (s0, s1):        # still aimed at the plume's centre, at the same distance
        v = c - li.position
        assert np.allclose(v / np.linalg.norm(v), li.direction, atol=1e-9)
    assert np.linalg.norm(c - s0.position) == pytest.approx(np.linalg.norm(c - s1.position))
    assert np.degrees(np.arccos(np.clip(s0.direction @ s1.direction, -1, 1))) > 0.5 * P["light_step"]
    # the light animation's frame 0 is the smoke animation's last frame: one key, rendered once
    last = P["frames"] - 1
    for anim in (a, b):
        assert S.frame_key(anim["light"](0)) == S.frame_key(anim["smoke"](last))
        assert S.frame_key(anim["light"](1)) != S.frame_key(anim["light"](0)) != S.frame_key(anim["smoke"](0))
    assert S.frame_key(a["smoke"](0)) != S.frame_key(b["smoke"](0))


def test_every_configuration_wording_needs_eight():
    r = dict(holds_in_every_configuration=True, holds_pooled=True, low=0.5, below=1.0, n_configs=S.MIN_EVERY - 1)
    assert S._verdict(r) == "holds pooled"
    assert S._verdict(dict(r, n_configs=S.MIN_EVERY)) == "holds in every configuration"


def test_summary_pools_configurations_and_keeps_each_ones_threshold():
    """Two configurations: one invisible from 32 B, the other from 64 B; the pooled threshold
    uses the means over configurations, and a kind that does not fit in one of them is out."""
    comp = np.array([[[0.5, 0.5], [0.05, 0.3], [0.01, 0.05], [0.01, 0.01]],      # kind 0: (B=4, C=2)
                     [[0.5, 0.5], [0.01, 0.01], [0.01, 0.01], [0.01, 0.01]]])    # kind 1: never fits in config 1
    nbytes = np.ones_like(comp)
    fits = np.ones(comp.shape, bool)
    fits[1, :, 1] = False
    s = A.summarise(comp, nbytes, fits, np.array([0.1, 0.1]), [16, 32, 64, 128], ["a", "b"],
                    [["a"] * 4, ["b"] * 4], n_boot=200, min_configs=4)
    thr = s["threshold"]
    assert thr["per_config"] == [32.0, 64.0] and thr["n_configs"] == 2 and thr["indicative"]
    assert thr["bytes"] == 64.0 and thr["kind"] == "a"                       # mean at 32 B: 0.175 > 0.1
    assert [c["kinds_within_budget"] for c in s["cells"]] == [1, 1, 1, 1]
    assert thr["interval"]["unit"] == "configuration" and thr["interval"]["n"] == 2


def test_frame_panel_falls_back_to_the_kinds_setting_of_the_first_configuration():
    """The frame figure shows configuration 0's images; a budget's most common label may be
    another size of the same kind there (sizes differ between configurations): the full run
    crashed on it with a KeyError."""
    from experiments.image_budget.plots import _shown
    imgs = {"exact": 0, "dsm-0.05": 1, "avsm-4": 2}
    assert _shown("avsm-4", imgs) == "avsm-4"
    assert _shown("dsm-0.005", imgs) == "dsm-0.05"
    assert _shown("fom-8", imgs) == "exact"


def test_a_failing_figure_leaves_the_data(tmp_path, monkeypatch):
    """The data files are written before the figures: a figure that raises (after a long run)
    leaves data.csv, map.csv and findings.json (a tiny run: two configurations, two kinds)."""
    from experiments._common import Results
    from experiments.image_budget import plots
    P, _ = S.STUDY.params(quick=True)
    P.update(configs=[[0, "dir_a"], [1, "dir_b"]], frames=2, size=8, start_steps=2, image=8, spp=1,
             reference_spp=4, resolutions=[64], budgets=[16], kinds=["exact", "beer"], n_boot=100)

    def boom(*_, **__):
        raise RuntimeError("a figure failed")
    monkeypatch.setattr(plots, "plot_all", boom)
    with pytest.raises(RuntimeError, match="a figure failed"):
        S._compute(Results("image_budget", tmp_path, True, P), P)
    rows = read_csv(tmp_path / "data.csv")
    assert {r["kind"] for r in rows} == {"exact", "beer"} and len(rows) == 2 * 2 * 2
    assert read_csv(tmp_path / "map.csv") and "headline" in json.loads((tmp_path / "findings.json").read_text())
    assert not (tmp_path / "meta.json").exists()                # not a finished (cached) result

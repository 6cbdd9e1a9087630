"""The frame benchmark (``python -m experiments frame --quick``): every built-in scene, both grid
capture methods and every registered kind get a frame row with per-stage times, rates and
shares, first-call times, a stacked-bar figure and the capture/build ratio in meta.json."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

import avsm_dr as ad
from helpers import quick_cli_run
from avsm_dr.builtin_scenes import SCENES
from experiments import _common, frame
from avsm_dr.io import write_vol


def _f(v):
    return float(v) if v not in ("", None) else float("nan")


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    return quick_cli_run("frame", tmp_path_factory.mktemp("results"))


def test_quick_frame_covers_every_scene_method_and_kind(quick):
    rows = _common.read_csv(quick / "data.csv")
    kinds = set(ad.kinds())
    assert {"plume", "particles"} <= {r["scene"] for r in rows}
    assert any(r["grid_shape"] for r in rows if r["scene"] == "plume")
    assert not any(r["grid_shape"] for r in rows if r["scene"] == "particles")
    for name in SCENES:
        grid = any(r["grid_shape"] for r in rows if r["scene"] == name)
        for res in frame.QUICK_RESOLUTIONS:
            for method in (frame.METHODS if grid else ("",)):
                got = {r["kind"] for r in rows if r["scene"] == name and int(r["resolution"]) == res
                       and r["method"] == method}
                assert got == kinds, (name, res, method)
    assert {int(r["resolution"]) for r in rows} == set(frame.QUICK_RESOLUTIONS)
    assert list(quick.glob("*.png")) == [quick / "frame.png"]
    # the insertion order every build saw: the capture's, front to back
    assert {r["order"] for r in rows if r["kind"] == "avsm"} == {"depth"}
    assert {r["order"] for r in rows if r["kind"] in ("fom", "exact")} == {"-"}


def test_quick_frame_stage_times_rates_and_shares(quick):
    rows = _common.read_csv(quick / "data.csv")
    timed = [r for r in rows if not r["note"]]
    assert len(timed) > 0.8 * len(rows)                        # only slow builds are skipped
    for r in timed:
        c, b, lk, fr = (_f(r[k]) for k in ("capture_s", "build_s", "lookup_s", "frame_s"))
        assert c > 0 and b > 0 and lk > 0 and _f(r["capture_first_s"]) > 0 and _f(r["build_first_s"]) > 0
        assert math.isclose(fr, c + b + lk, rel_tol=1e-6)
        shares = sum(_f(r[k]) for k in ("capture_share", "build_share", "lookup_share"))
        assert math.isclose(shares, 1.0, rel_tol=1e-6)
        assert math.isclose(_f(r["capture_segments_per_s"]), int(r["segments"]) / c, rel_tol=1e-6)
        assert math.isclose(_f(r["lookups_per_s"]), int(r["lookups"]) / lk, rel_tol=1e-6)
        assert _f(r["capture_jit_s"]) >= 0 and _f(r["lookup_jit_s"]) >= 0
    for r in rows:
        if r["note"]:
            assert r["note"].startswith(("skipped: build work estimate", "skipped: offline reference")) \
                    and math.isnan(_f(r["build_s"]))


def test_skipped_builds_follow_the_work_estimate_not_a_clock(monkeypatch):
    """Which builds a frame runs reads the kinds' declared work (FRAME_WORK), never a clock:
    with time.perf_counter and time.process_time jumping an hour per call (every build "slow"),
    the same cells are built and skipped, with the same notes; a budget at the middle of three
    kinds' estimates skips the costliest alone; the quick budget skips none of them."""
    import itertools
    import time
    from experiments.error_curves.cost import FRAME_WORK
    scene = frame.builtin_scenes(frame.SIZES["quick"], ["plume"])["plume"]
    seg = ad.capture(scene, resolution=64, method="exact", order="depth").segments
    slow = ["dsm", "avsm_march", "avsm_adaptive"]
    work = {k: FRAME_WORK[k](seg, ad.describe(k)["headline"]) for k in slow}
    assert len(set(work.values())) == 3 and max(work.values()) < frame.BUILD_BUDGET["quick"]
    budget = sorted(work.values())[1]

    def cells():
        rows = frame.frame_rows("plume", scene, 64, ["exact"], ["avsm", *slow], 256, 1, budget,
                                np.random.default_rng(0))
        return sorted((r["kind"], r["note"]) for r in rows)

    calm = cells()
    clock = itertools.count(0.0, 3600.0)
    monkeypatch.setattr(time, "perf_counter", lambda: next(clock))
    monkeypatch.setattr(time, "process_time", lambda: next(clock))
    assert cells() == calm
    costliest = max(work, key=work.get)
    assert [k for k, note in calm if note] == [costliest]
    assert dict(calm)[costliest].startswith(f"skipped: build work estimate {work[costliest]:.3g} > limit")


def test_a_build_the_memory_guard_refuses_is_a_skipped_cell(monkeypatch):
    """A build above the memory budget (here: 1.4 MB, which DSM's polyline at tolerance 0.01
    exceeds on the plume at 64^2, 1.7 MB, and AVSM-8's build does not, 1.0 MB) is a row with a
    note and no times; the other kinds of the frame are measured."""
    from avsm_dr import validation
    scene = frame.builtin_scenes(frame.SIZES["quick"], ["plume"])["plume"]
    monkeypatch.setattr(validation, "MEMORY_BUDGET_BYTES", 1_400_000)
    rows = {r["kind"]: r for r in frame.frame_rows("plume", scene, 64, ["exact"], ["avsm", "dsm"], 256, 1,
                                                   frame.BUILD_BUDGET["quick"], np.random.default_rng(0))}
    assert rows["dsm"]["note"].startswith("skipped: build refused by the memory guard: tolerance")
    assert math.isnan(rows["dsm"]["build_s"]) and math.isnan(rows["dsm"]["lookup_s"])
    assert rows["avsm"]["note"] == "" and rows["avsm"]["build_s"] > 0 and rows["avsm"]["lookup_s"] > 0


def test_quick_frame_exact_capture_has_fewer_iterations_and_segments(quick):
    """Deterministic counts (no timing): per grid scene and resolution, the exact capture takes
    fewer iterations (and so density samples) per ray and emits fewer segments than the march."""
    rows = _common.read_csv(quick / "data.csv")
    for name in SCENES:
        if not any(r["grid_shape"] for r in rows if r["scene"] == name):
            continue
        for res in frame.QUICK_RESOLUTIONS:
            by = {r["method"]: r for r in rows if r["scene"] == name and int(r["resolution"]) == res}
            assert by["exact"]["lanes"] == by["march"]["lanes"]
            assert _f(by["exact"]["samples_per_ray"]) < _f(by["march"]["samples_per_ray"])
            assert int(by["exact"]["segments"]) < int(by["march"]["segments"])


def test_quick_frame_meta_reports_the_capture_over_build_ratio(quick):
    meta = json.loads((quick / "meta.json").read_text())
    assert meta["experiment"] == "frame" and meta["params"]["quick"] is True
    s = meta["summary"]
    for m in frame.METHODS:
        assert s[f"plume_128_{m}_capture_over_avsm8_build"] > 0
    assert isinstance(s["skipped"], list)


def test_user_grid_and_bad_input(tmp_path):
    rng = np.random.default_rng(0)
    d = (rng.random((8, 10, 9)) * 4).astype(np.float32)
    d[:2] = 0
    path = tmp_path / "g.vol"
    write_vol(path, d, (np.array([-0.5, -0.5, -0.5]), np.array([0.5, 0.7, 0.4])))
    out = frame.run(quick=True, out=tmp_path / "frame", grid=str(path), scenes=[], resolutions=(64,),
                    methods=("exact",))
    rows = _common.read_csv(out["csv"])
    assert {r["scene"] for r in rows} == {"grid:g"} and {r["method"] for r in rows} == {"exact"}
    assert all(int(r["segments"]) > 0 for r in rows)
    with pytest.raises(ValueError, match="^grid"):
        frame.run(quick=True, out=tmp_path / "f2", grid=str(tmp_path / "missing.vol"))
    with pytest.raises(ValueError, match="^scenes"):
        frame.run(quick=True, out=tmp_path / "f3", scenes=["nope"])
    with pytest.raises(ValueError, match="^methods"):
        frame.run(quick=True, out=tmp_path / "f4", methods=("rk4",))

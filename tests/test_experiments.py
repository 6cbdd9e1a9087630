"""Every experiment runs in --quick mode through the CLI and writes its CSV (with the
documented columns), figures and meta.json into its own ``<--out>/<name>/`` folder; the
results cache is keyed on parameters, package source and versions; the CLI reports a bad
``--out`` in one line; the recipes in ``experiments/`` call existing experiments."""
import dataclasses
import json
import math
import re
import os
import subprocess
import sys
import types
from pathlib import Path

import drjit as dr
import pytest

from experiments import _cli as cli
from experiments import _common
from experiments._headline import generic, interval
from experiments._study import Study

ROOT = Path(__file__).resolve().parents[1]
ERROR_COLUMNS = {"scene", "method", "param", "bytes_per_texel", "rmse", "max_error"}
#: Studies whose quick run takes minutes on 2 cores: their quick run is a slow test, and the
#: default run checks them end to end on the tiny parameters of TINY (same code, every table).
SLOW_QUICK = {"bench", "backward_cost"}
EXPERIMENTS = [pytest.param(n, marks=pytest.mark.slow) if n in SLOW_QUICK else n
               for n in ["error_curves", "runtime_vs_error", "curves", "images", "stress", "ordering", "bench",
                         "bench_capture", "inverse", "backward_cost"]]
#: Parameters replacing a slow study's quick ones in the default run (the rest as in QUICK).
TINY = {
    "bench": dict(maps=[(16, 10), (8, 100)], lookups=4000, numpy_segments=4000, repeats=1, scene_resolution=64,
                  scene_repeats=1, mitsuba_spp=[4, 8], mitsuba_cap=256, mitsuba_reps=[("avsm", {"nodes": 4})],
                  scale_texels=[8, 16], scale_counts=[10, 30], scale_side=16, scale_nodes=[2, 4], scale_repeats=1,
                  skip_side=16, memory_side=16, dense_plume=16, skip_resolution=64, peak_iters=200),
    "backward_cost": dict(size=8, resolution=64, step_fractions=[0.5], repeats=1, stack_cases=[(8, 200)],
                          kinds=["avsm", "fom"]),
}


def _rows(path):
    return _common.read_csv(path)


@pytest.fixture(scope="module")
def shared_out(tmp_path_factory):
    """One ``--out`` for every experiment of this module: none may touch another's files."""
    return tmp_path_factory.mktemp("results")


#: The old end of a run: ``  <key padded>  <value>`` lines and ``key_name=value`` dumps of nested dicts.
RAW_LINE, RAW_DICT = re.compile(r"^  \S+\s{2,}\S"), re.compile(r"\w_\w+=[-\d]")


def _end_of_run(name: str, stdout: str) -> list[str]:
    """The lines a run printed last: from ``<name>: <about>`` to ``wrote <folder>/ (...)``."""
    lines = stdout.splitlines()
    start = max(i for i, ln in enumerate(lines) if ln == f"{name}: {cli.study(name).about}")
    return lines[start:]


@pytest.mark.parametrize("name", EXPERIMENTS)
def test_quick_experiment_writes_results(name, shared_out, capsys):
    assert name in cli.experiment_names()
    assert cli.main([name, "--quick", "--out", str(shared_out)]) == 0
    out = shared_out / name
    # it ends with what was measured, a few human headline lines and where the files are
    end = _end_of_run(name, capsys.readouterr().out)
    assert end[-1].startswith(f"wrote {out}/ (") and "data.csv" in end[-1], end
    assert 3 <= len(end) <= cli.SUMMARY_LINES + 3, end
    assert not [ln for ln in end if RAW_LINE.match(ln) or RAW_DICT.search(ln) or "{" in ln], end
    rows = _rows(out / "data.csv")
    assert rows, "empty CSV"
    meta = json.loads((out / "meta.json").read_text())
    assert meta["params"]["quick"] is True and meta["experiment"] == name
    assert meta["drjit"] == dr.__version__ and meta["numpy"] and meta["backend"] and meta["machine"]
    assert "git_commit" in meta and meta["cache_key"] == _common.cache_key()
    assert list(out.glob("*.png")), "no figure written"
    # every figure also as a vector PDF beside it (paper-ready; experiments._plotstyle), both recorded
    assert [p.name for p in out.glob("*.png") if not p.with_suffix(".pdf").is_file()] == []
    assert all({p.name, p.with_suffix(".pdf").name} <= set(meta["files"]) for p in out.glob("*.png"))
    # experiments sharing --out keep to their own folders
    assert not [p for p in shared_out.iterdir() if p.is_file()]
    for sub in shared_out.iterdir():
        if (sub / "meta.json").exists():
            assert json.loads((sub / "meta.json").read_text())["experiment"] == sub.name
    if name == "error_curves":
        assert ERROR_COLUMNS <= set(rows[0])
        assert {r["method"] for r in rows} >= {"exact", "avsm", "fom", "osm", "dsm"}
        assert all(r["method"] == r["method"].lower() for r in rows)
        assert (out / "findings.json").exists()
    if name == "stress":
        cols = set(rows[0])
        assert any("nan" in c for c in cols) and any("inf" in c for c in cols)
        assert sum(int(r["nan_count"]) + int(r["inf_count"]) for r in rows) == 0
        assert sum(int(r["bounds_violations"]) for r in rows) == 0
        # the order each kind saw: the cases are drawn unsorted, sort=True sorts them
        assert {(r["method"], r["sorted"], r["order"]) for r in rows if r["method"] == "avsm"} == {
            ("avsm", "False", "random"), ("avsm", "True", "depth")}
        assert {r["order"] for r in rows if r["method"] in ("fom", "exact")} == {"-"}
        checks = _rows(out / "reliability.csv")          # hostile input: refused or right
        assert len(checks) >= 10 and sum(int(r["failures"]) for r in checks) == 0, checks
    if name == "ordering":
        sorted_rows = [r for r in rows if r["sorted"] == "True"]
        assert all(float(r["flicker_rms"]) == 0.0 == float(r["flicker_depth_l2"]) for r in sorted_rows)  # no flicker
        assert all(float(r["flicker_depth_l2"]) > 0 for r in rows if r["sorted"] == "False")
        assert {r["order"] for r in sorted_rows} == {"depth"} and {r["order"] for r in rows} == {"depth", "random"}
        assert all(float(r["depth_l2"]) > 0 and 0 <= float(r["leak_share"]) <= 1 for r in rows)
    if name == "inverse":                                   # the insertion order each model's build saw
        assert {(r["model"], r["order"]) for r in rows} == {("exact", "-"), ("fom", "-"), ("avsm", "depth")}
    if name == "curves":                                    # the insertion order of every row
        assert {(r["method"], r["order"]) for r in rows} >= {("avsm", "depth"), ("fom", "-"), ("exact", "-")}
        assert {r["order"] for r in rows if r["method"] == "avsm"} == {"depth"}
    if name == "images":                  # the curve metrics of the maps that made the images
        for r in rows:
            assert math.isfinite(float(r["depth_l2"])) and float(r["bytes"]) > 0 and float(r["bytes_dense"]) > 0
            assert r["order"] == ("depth" if r["method"] == "avsm" else "-"), r
        assert all(float(r["depth_l2"]) == 0 for r in rows if r["method"] == "exact")
    if name in ("runtime_vs_error", "ordering"):     # both metrics' columns (depth L2, signed, leak, bytes), finite
        for r in rows:
            for k in ("depth_l2", "signed_mean", "leak_share", "bytes", "bytes_dense"):
                assert math.isfinite(float(r[k])), (name, k, r)
    if name in ("runtime_vs_error", "ordering"):                  # one row set per configuration, claims
        configs = {f"s{seed}-{light}" for seed, light in meta["params"]["configs"]}
        assert {r["config"] for r in rows} == configs and len(configs) == 2
        found = json.loads((out / "findings.json").read_text())
        claims = [c for f in found.values() for c in (f["claims"].values() if name == "runtime_vs_error" else
                                                      [c for per_n in f["claims"].values() for c in per_n.values()])]
        assert claims and all(f["n_configs"] == 2 and f["indicative"] for f in found.values())
        for c in claims:
            assert c["n_configs"] == 2 and c["indicative"] is True and isinstance(c["metric_dependent"], bool)
            assert c["order"] in (("depth", "-") if name == "runtime_vs_error" else ("depth / random",)), c["order"]
            assert set(c["metrics"]) == {"receiver_rmse", "depth_l2"}
            assert all(m["low"] <= m["estimate"] <= m["high"] for m in c["metrics"].values()), c
            assert all({"mean_signed_error", "leak_share"} <= set(s) for s in c["sides"].values())
    if name == "ordering":                     # sorted: no flicker on either metric, in every configuration
        for per_n in json.loads((out / "findings.json").read_text())["three_columns"]["claims"].values():
            assert all(m["high"] < 0 for m in per_n["sorting_removes_flicker"]["metrics"].values())
    if name == "runtime_vs_error":
        from experiments.error_curves.labels import order_dependent
        assert all(math.isfinite(float(r["time_ratio"])) for r in rows)
        assert all(float(r["time_ratio"]) == 1.0 for r in rows if (r["method"], r["param"]) == ("avsm", "8"))
        assert all(r["order"] == ("depth" if r["method"] != "exact" and order_dependent(r["method"]) else "-")
                   for r in rows)
        assert {r["pareto_depth_l2"] for r in rows if r["method"] != "exact"} == {"True", "False"}
        assert set(meta["summary"]["pareto_front_depth_l2"]) == set(meta["summary"]["pareto_front"])
    if name == "bench_capture":
        assert [r["case"] for r in rows] == ["tight", "4x per axis", "4x volume"]
        assert float(rows[0]["ratio_capture"]) == 1.0
        assert all(int(r["segments"]) > 0 and float(r["capture_s"]) > 0 for r in rows)
    # a second run with the same parameters reuses the results
    again = __import__(f"experiments.{name}", fromlist=["run"]).run(quick=True, out=out)
    assert again.get("cached") is True


@pytest.mark.parametrize("name", ["runtime_vs_error", "ordering"])
def test_full_mode_runs_ten_configurations_per_scene_with_a_spot_light(name):
    """The claims of a full run rest on >= 10 configurations (scene seed x light) per scene, a
    spot light among them, all distinct; the quick run keeps to one or two."""
    study = cli.study(name)
    configs = [tuple(c) for c in study.full["configs"]]
    assert len(configs) >= 10 and len(set(configs)) == len(configs)
    assert any(light == "spot" for _, light in configs) and {"dir_a", "dir_b"} <= {li for _, li in configs}
    assert 1 <= len(study.quick["configs"]) <= 2


def test_moment_tuning_full_mode_runs_error_curves_layout_on_held_out_seeds():
    """moment_tuning's full run: 10 configurations per scene in error_curves' layout (two
    directional lights on every seed, the spot light on the first two), on seeds error_curves
    never evaluates; its quick run keeps to three."""
    from experiments import error_curves, moment_tuning
    configs = [tuple(c) for c in moment_tuning.FULL["configs"]]
    assert len(configs) >= 10 and len(set(configs)) == len(configs)
    assert sum(li == "spot" for _, li in configs) == 2 and {"dir_a", "dir_b"} <= {li for _, li in configs}
    held = sorted({s for s, _ in configs})
    layout = [(held.index(s), li) for s, li in configs]
    assert layout == [tuple(c) for c in error_curves.FULL["configs"]]
    assert not set(held) & {s for s, _ in error_curves.FULL["configs"]}
    assert len(moment_tuning.QUICK["configs"]) == 3


def test_learned_warp_full_mode_runs_ten_configurations_per_held_out_scene_with_a_spot_light():
    """learned_warp's full run: every held-out group has >= 10 distinct configurations (seed x
    light), a spot light among them; the new plume seeds use no training light; the quick
    run keeps a spot light so that its path is exercised."""
    from experiments import learned_warp as lw
    train_lights = {li for *_, li in lw.FULL["train"]}
    groups = {}
    for group, name, seed, light in lw.FULL["held"]:
        groups.setdefault(group, []).append((name, seed, light))
    assert len(groups) == 5
    for group, configs in groups.items():
        assert len(configs) >= 10 and len(set(configs)) == len(configs), group
        assert any(li == lw.SPOT for *_, li in configs), group
    assert not {li for *_, li in groups["smoke_new_seeds"]} & train_lights
    assert lw.SPOT not in train_lights
    assert any(li == lw.SPOT for *_, li in lw.QUICK["held"])


def test_runtime_vs_error_times_every_greedy_build_from_the_segments(monkeypatch):
    """greedy caches its Visvalingam-Whyatt order on the segments: every timed build (warm-up
    and repeat alike, of every kind) starts from ``Segments.drop_cache()`` and computes the
    curve points again, not reusing an earlier setting's."""
    from avsm_dr import Segments
    from avsm_dr.representations import _curve
    from experiments import runtime_vs_error as rve
    calls, drops = [], []
    real, real_drop = _curve.curve_points, Segments.drop_cache
    monkeypatch.setattr(_curve, "curve_points", lambda seg: calls.append(1) or real(seg))
    monkeypatch.setattr(Segments, "drop_cache", lambda seg, *a, **k: drops.append(1) or real_drop(seg, *a, **k))
    P = dict(rve.QUICK, resolution=64, n_volume=64, sweeps={"avsm": [{"nodes": 8}],
                                                            "greedy": [{"nodes": 2}, {"nodes": 4}]})
    for first, builds in ((True, 4), (False, 2)):      # warm-up + one repeat, or one build, per setting
        calls.clear(), drops.clear()
        rows = rve._config("three_columns", 0, "dir_a", P, first, {})
        assert len(calls) == builds and len(drops) == 3 * builds // 2      # 3 settings, 2 of them greedy
        assert all(r["build_s"] > 0 for r in rows if r["method"] == "greedy")


#: bench's tiny run (56 s of the default run: Numba, Warp and Mitsuba peers) is slow too; its tables
#: are checked by the bench unit tests (test_peers, test_bench_machine, test_bench_memory_guard).
@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n == "bench" else n
                                  for n in sorted(TINY)])
def test_slow_study_runs_end_to_end_on_tiny_parameters(name, tmp_path):
    """The default run's check of a study whose quick run is slow: the same ``compute`` on
    TINY parameters writes every file it declares, a figure with its PDF, and meta.json."""
    module = __import__(f"experiments.{name}", fromlist=["STUDY"])
    study = dataclasses.replace(module.STUDY, quick=dict(module.STUDY.quick, **TINY[name]))
    result = study.run(quick=True, out=tmp_path / name)
    out = Path(result["out"])
    assert _rows(out / "data.csv"), "empty CSV"
    for declared in study.writes:
        f = out / declared.split()[0]
        assert f.is_file() and f.stat().st_size > 0, f"{name} did not write {f.name}"
    meta = json.loads((out / "meta.json").read_text())
    assert meta["experiment"] == name and meta["params"]["quick"] is True
    pngs = list(out.glob("*.png"))
    assert pngs and all(p.with_suffix(".pdf").is_file() for p in pngs)
    if name == "backward_cost":
        rows = _rows(out / "data.csv")
        assert {r["kind"] for r in rows} >= {"avsm", "fom"}
        assert all(float(r["seconds"]) > 0 for r in rows if r.get("seconds") not in (None, ""))


def test_unknown_experiment_is_rejected(capsys):
    with pytest.raises(SystemExit):
        cli.main(["no_such_experiment"])


# ------------------------------------------------------------------ results cache
def _toy_results(tmp_path, name="toy"):
    res = _common.Results(name, tmp_path / name, quick=True, params={"n": 3})
    res.write_csv([{"x": 1.0}])
    res.write_meta({"ok": True})
    return res


def test_cache_key_includes_source_and_versions(tmp_path, monkeypatch):
    """Cached results are reused only with the same source hash, versions and backend."""
    res = _toy_results(tmp_path)
    assert res.cached() == {"csv": str(res.dir / "data.csv"), "out": str(res.dir), "cached": True}
    assert res.cached(force=True) is None
    assert _common.Results("toy", res.dir, True, {"n": 4}).cached() is None          # other parameters
    with monkeypatch.context() as m:
        m.setattr(_common, "source_hash", lambda: "0" * 16)                          # the code changed
        assert _common.Results("toy", res.dir, True, {"n": 3}).cached() is None
    with monkeypatch.context() as m:
        installed = _common.versions()
        m.setattr(_common, "versions", lambda: dict(installed, numpy="0.0"))        # a library changed
        assert _common.Results("toy", res.dir, True, {"n": 3}).cached() is None
    assert _common.Results("toy", res.dir, True, {"n": 3}).cached() is not None


def test_source_hash_covers_the_package_and_the_studies():
    h = _common.source_hash()
    assert re.fullmatch(r"[0-9a-f]{16}", h) and h == _common.source_hash()
    assert (_common.PACKAGE_DIR / "segments.py").exists()
    assert (_common.STUDIES_DIR / "_common.py").exists()


def test_meta_records_provenance(tmp_path):
    meta = json.loads((_toy_results(tmp_path).dir / "meta.json").read_text())
    from importlib import metadata
    assert meta["mitsuba"] == metadata.version("mitsuba")
    assert meta["drjit"] == dr.__version__
    assert meta["git_commit"] is None or re.fullmatch(r"[0-9a-f]{40}", meta["git_commit"])
    assert meta["cache_key"]["source"] == _common.source_hash()
    assert meta["backend"] == meta["cache_key"]["backend"]


def test_versions_do_not_import_mitsuba():
    code = ("import avsm_dr, sys; from experiments._common import versions; v = versions(); "
            "print('mitsuba' in sys.modules, v['mitsuba'] is not None)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=True)
    assert out.stdout.split() == ["False", "True"]


def test_git_commit_fails_gracefully(monkeypatch, tmp_path):
    monkeypatch.setattr(_common, "STUDIES_DIR", tmp_path)                 # not a git checkout
    assert _common.git_commit() is None

    def no_git(*a, **k):
        raise FileNotFoundError("git")
    monkeypatch.setattr(_common.subprocess, "run", no_git)
    assert _common.git_commit() is None


def test_results_refuse_another_experiments_folder(tmp_path):
    res = _toy_results(tmp_path, "first")
    with pytest.raises(ValueError, match="^out: .*'first'"):
        _common.Results("second", res.dir, True, {})
    with pytest.raises(ValueError, match="^out:"):
        _common.Results("second", "", True, {})
    with pytest.raises(ValueError, match="^out: .*file"):
        _common.Results("second", res.dir / "data.csv", True, {})


def test_meta_records_each_file_and_is_written_last(tmp_path):
    res = _common.Results("toy", tmp_path / "toy", quick=True, params={"n": 3})
    res.write_csv([{"x": 1.0}, {"x": 2.0}])
    res.write_json("findings.json", {"a": 1})
    res.write_npz("arrays.npz", a=[1.0, 2.0])
    assert not (res.dir / "meta.json").exists() and res.cached() is None      # no meta yet: not a result
    res.write_meta()
    files = json.loads((res.dir / "meta.json").read_text())["files"]
    assert set(files) == {"data.csv", "findings.json", "arrays.npz"} and files["data.csv"]["rows"] == 2
    assert files["data.csv"]["sha256"] == _common.file_sha256(res.dir / "data.csv")
    assert sorted(p.name for p in res.dir.iterdir()) == ["arrays.npz", "data.csv", "findings.json", "meta.json"]
    assert res.cached() is not None


@pytest.mark.parametrize("damage", ["truncated_csv", "csv_rewritten", "findings_changed", "npz_removed",
                                    "meta_without_files"])
def test_damaged_results_are_recomputed(tmp_path, damage):
    """A table cut short (an interrupted --force run), replaced, or a recorded file changed or
    gone: the folder is not served as cached."""
    res = _common.Results("toy", tmp_path / "toy", quick=True, params={"n": 3})
    res.write_csv([{"x": float(i)} for i in range(50)])
    res.write_json("findings.json", {"a": 1})
    res.write_npz("arrays.npz", a=[1.0])
    res.write_meta()
    assert res.cached() is not None
    csv_path = res.dir / "data.csv"
    if damage == "truncated_csv":
        csv_path.write_bytes(csv_path.read_bytes()[: len(csv_path.read_bytes()) // 2])
    elif damage == "csv_rewritten":                # a --force run that wrote its table, then died
        _common.Results("toy", res.dir, True, {"n": 3}).write_csv([{"x": 9.0}])
    elif damage == "findings_changed":
        (res.dir / "findings.json").write_text('{"a": 2}')
    elif damage == "npz_removed":
        (res.dir / "arrays.npz").unlink()
    elif damage == "meta_without_files":           # a meta.json of the old format
        meta = json.loads((res.dir / "meta.json").read_text())
        del meta["files"]
        (res.dir / "meta.json").write_text(json.dumps(meta))
    assert _common.Results("toy", res.dir, True, {"n": 3}).cached() is None


def test_interrupted_write_keeps_the_old_file(tmp_path):
    """A write that fails half-way leaves the previous file whole and no temporary file."""
    res = _common.Results("toy", tmp_path / "toy", quick=True, params={})
    res.write_csv([{"x": 1.0}])
    before = (res.dir / "data.csv").read_bytes()

    class Crash(Exception):
        pass

    def rows():
        yield {"x": 2.0}
        raise Crash
    with pytest.raises(Crash):
        res.write_csv(rows())

    def half(tmp):
        tmp.write_text("x\n3.0\n")
        raise Crash
    with pytest.raises(Crash):
        res.write_file("data.csv", half)
    assert (res.dir / "data.csv").read_bytes() == before
    assert sorted(p.name for p in res.dir.iterdir()) == ["data.csv"]


# ------------------------------------------------------------------------- CLI
def test_experiments_sharing_out_keep_their_own_folders(tmp_path, monkeypatch, capsys):
    """Two experiments into one --out: each writes <out>/<name>/, neither touches the other."""
    def make(name, value):
        def compute(res, P):
            import matplotlib
            matplotlib.use("Agg")
            import matplotlib.pyplot as plt
            res.save_figure(plt.figure(), f"{name}.png")
            return dict(rows=[{"value": value}], summary={})
        study = Study(name, f"toy {name}", "nothing", {}, {}, compute)
        return types.SimpleNamespace(STUDY=study, run=study.run)

    for name, value in (("toy_a", 1), ("toy_b", 2)):
        monkeypatch.setitem(sys.modules, f"experiments.{name}", make(name, value))
    monkeypatch.setattr(cli, "experiment_names", lambda: ["toy_a", "toy_b"])
    assert cli.main(["toy_a", "--out", str(tmp_path)]) == 0
    assert cli.main(["toy_b", "--out", str(tmp_path)]) == 0
    assert _rows(tmp_path / "toy_a" / "data.csv") == [{"value": "1"}]
    assert _rows(tmp_path / "toy_b" / "data.csv") == [{"value": "2"}]
    assert sorted(p.name for p in (tmp_path / "toy_a").glob("*.png")) == ["toy_a.png"]
    assert sorted(p.name for p in (tmp_path / "toy_b").glob("*.png")) == ["toy_b.png"]
    assert sorted(p.name for p in (tmp_path / "toy_a").glob("*.pdf")) == ["toy_a.pdf"]   # vector beside PNG
    assert sorted(p.name for p in tmp_path.iterdir()) == ["toy_a", "toy_b"]
    # a folder holding another experiment's results is refused in one line (exit 2)
    (tmp_path / "toy_a" / "toy_b").mkdir()
    (tmp_path / "toy_a" / "toy_b" / "meta.json").write_text(json.dumps({"experiment": "toy_a"}))
    capsys.readouterr()
    assert cli.main(["toy_b", "--out", str(tmp_path / "toy_a")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("experiments: error: --out:")


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "experiments", *args], capture_output=True, text=True, timeout=300,
                          cwd=ROOT)


@pytest.mark.parametrize("case", ["empty", "file", "under_file", "proc"])
def test_bad_out_is_a_one_line_error(tmp_path, case):
    """An empty, file-valued or unwritable --out: one line on stderr, exit status 2, no traceback
    and nothing written."""
    f = tmp_path / "a_file"
    f.write_text("keep")
    out = {"empty": "", "file": str(f), "under_file": str(f / "sub"), "proc": "/proc/avsm_dr_no_such_dir"}[case]
    p = _cli("curves", "--quick", "--out", out)
    assert p.returncode == 2, p.stderr
    assert "Traceback" not in p.stderr and p.stderr.count("\n") == 1, p.stderr
    assert p.stderr.startswith("experiments: error: --out"), p.stderr
    assert f.read_text() == "keep" and sorted(x.name for x in tmp_path.iterdir()) == ["a_file"]


@pytest.mark.parametrize("case", ["backend_env", "address", "workers", "unavailable_backend_env"])
def test_bad_environment_and_ray_options_are_one_line_errors(tmp_path, case):
    """AVSM_DR_BACKEND=garbage, --address garbage, --workers 1000000000: one line naming the
    variable or option, exit status 2, no traceback, before any work."""
    import os
    env = dict(os.environ)
    args = ["error_curves", "--quick", "--out", str(tmp_path)]
    if case == "backend_env":
        env["AVSM_DR_BACKEND"], want = "garbage", "experiments: error: AVSM_DR_BACKEND: expected one of"
    elif case == "unavailable_backend_env":
        import avsm_dr as ad
        if "cuda" in ad.available_backends():
            pytest.skip("CUDA is available here")
        env["AVSM_DR_BACKEND"], want = "cuda", "experiments: error: AVSM_DR_BACKEND='cuda': backend 'cuda' is not"
    elif case == "address":
        args, want = args + ["--address", "garbage"], "experiments: error: --address: expected a Ray address"
    else:
        args, want = args + ["--workers", "1000000000"], "experiments: error: --workers: expected an integer in [1, "
    p = subprocess.run([sys.executable, "-m", "experiments", *args], capture_output=True, text=True, timeout=300,
                       cwd=ROOT, env=env)
    assert p.returncode == 2, p.stderr
    assert "Traceback" not in p.stderr and p.stderr.count("\n") == 1 and p.stderr.startswith(want), p.stderr
    assert not any(tmp_path.iterdir())                                        # nothing written


def test_value_errors_of_a_run_are_one_line(tmp_path, monkeypatch, capsys):
    """Any ValueError an experiment raises (a bad argument deep inside) is printed as one
    line, exit status 2; other exceptions still propagate."""
    def compute(res, P):
        raise ValueError("nodes: expected an integer in [2, 64],\n got 1")
    study = Study("toy_bad", "toy", "nothing", {}, {}, compute)
    monkeypatch.setitem(sys.modules, "experiments.toy_bad", types.SimpleNamespace(STUDY=study, run=study.run))
    monkeypatch.setattr(cli, "experiment_names", lambda: ["toy_bad"])
    assert cli.main(["toy_bad", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err == "experiments: error: nodes: expected an integer in [2, 64], got 1\n"


# ---------------------------------------------------------------------- recipes
def test_every_study_says_what_it_reproduces_and_describes_itself(capsys):
    """Each study carries its recipe (REPRODUCES), and ``<study> --help`` prints its own
    description, options and what it writes (plain text: no reST roles, double back-quotes or
    Markdown bold)."""
    names = cli.experiment_names()
    assert "error_curves" in names and "bench" in names
    for name in names:
        module = __import__(f"experiments.{name}", fromlist=["run"])
        assert isinstance(getattr(module, "REPRODUCES", None), str) and module.REPRODUCES.strip(), name
        with pytest.raises(SystemExit) as exc:
            cli.main([name, "--help"])
        assert exc.value.code == 0
        text = capsys.readouterr().out
        assert f"python -m experiments {name}" in text and "--quick" in text and f"DIR/{name}/" in text, name
        assert ":mod:`" not in text and "``" not in text and "**" not in text, name
    with pytest.raises(SystemExit):
        cli.main(["--help"])
    listing = capsys.readouterr().out
    assert all(f"  {n} " in listing for n in names)
    assert not list((ROOT / "experiments").glob("*.sh")), "recipes live in the studies (REPRODUCES)"


def test_run_ends_with_a_short_human_summary(tmp_path):
    """A run ends with what was measured, at most SUMMARY_LINES headline lines and where its
    files are, never a dict."""
    (tmp_path / "toy").mkdir()
    (tmp_path / "toy" / "findings.json").write_text("{}")
    summary = {f"claim_{i}": "holds in every configuration" for i in range(30)} | {"ratio": 1.23456789}
    text = cli.summary_text("toy", {"out": str(tmp_path / "toy"), "summary": summary}, tmp_path / "toy")
    lines = text.splitlines()
    assert lines[0] == "toy:" and lines[1] == "  claim 0: holds in every configuration"
    assert lines[-1].startswith("wrote ") and "findings.json" in lines[-1]
    assert len(lines) == 1 + cli.SUMMARY_LINES + 2 and lines[-2] == "  ... and 19 more in findings.json"
    assert "{" not in text and all(len(ln) < 160 for ln in lines)


def test_generic_headline_formats_numbers_and_intervals():
    """A study without its own headline: one line per leaf, keys as words, numbers to 3
    significant digits, intervals as ``estimate [low, high]``, never a dict's repr."""
    summary = {"run_seconds": 12.345, "order": ["depth", "random"], "rate": 25980927.5, "ok": True,
               "plume": {"N=8": {"avsm_over_optimal": {"estimate": 2.90213, "low": 2.8312, "high": 2.9871,
                                                       "per_config": {"s0": [2.9, 2.8, 3.0]}},
                                 "texels": 4096},
                         "timing": {"build_s": 0.01234, "lookup_s": 0.5}}}
    assert generic(summary) == ["run seconds: 12.3", "order: depth, random", "rate: 26 M", "ok: yes",
                                "plume / N=8 / avsm over optimal: 2.9 [2.83, 2.99]", "plume / N=8 / texels: 4096",
                                "plume / timing: build s 0.0123, lookup s 0.5"]


def test_a_declared_headline_ends_fresh_and_reused_runs_alike(tmp_path, monkeypatch, capsys):
    """``Study.headline`` reads the recorded summary: a fresh run and a reused one print the
    same lines (between what was measured and where the files are); a headline that fails on
    the summary says so and falls back to the generic lines instead of failing the run."""
    def compute(res, P):
        return dict(rows=[{"x": 1}], summary={"ratio": {"estimate": 0.5, "low": 0.25, "high": 0.75}})
    study = Study("toy_head", "toy about", "nothing", {}, {}, compute,
                  headline=lambda s: [f"a over b: {interval(s['ratio'])}"])
    monkeypatch.setitem(sys.modules, "experiments.toy_head", types.SimpleNamespace(STUDY=study, run=study.run))
    monkeypatch.setattr(cli, "experiment_names", lambda: ["toy_head"])
    runs = []
    for _ in range(2):
        assert cli.main(["toy_head", "--out", str(tmp_path)]) == 0
        runs.append(capsys.readouterr().out.splitlines())
    assert runs[0][:2] == runs[1][:2] == ["toy_head: toy about", "  a over b: 0.5 [0.25, 0.75]"]
    assert runs[0][2].startswith("wrote ") and runs[1][2].startswith("reused cached results in ")
    broken = dataclasses.replace(study, headline=lambda s: [s["missing"]])
    text = cli.summary_text("toy_head", {"out": str(tmp_path / "toy_head")}, tmp_path, broken).splitlines()
    assert text[1] == "  (the study's headline failed: KeyError: 'missing'; its summary follows)"
    assert text[2] == "  ratio: 0.5 [0.25, 0.75]"


def test_error_curves_headline_counts_the_verdicts():
    """error_curves ends with how many claims got each verdict, then its claims' own lines
    (``findings.summary_lines``), ids as in findings.json."""
    from experiments.error_curves import findings as F

    def claim(verdict, est):
        return dict(estimate=est, low=est * 0.9, high=est * 1.1, verdict=verdict, n_configs=10, preset={"a": True})
    lines = F.summary_lines({"claims": {"a": claim("holds in every configuration", 0.5),
                                        "b": claim("does not hold", 2.0),
                                        "c": claim("holds in every configuration", 0.25)}})
    head = cli.study("error_curves").headline_lines(lines)
    assert head[0].startswith("3 claims: 2 holds in every configuration, 1 does not hold; per claim: ")
    assert head[1:] == ["a: 0.5 [0.45, 0.55]: holds in every configuration, 10 configs",
                        "b: 2 [1.8, 2.2]: does not hold, 10 configs",
                        "c: 0.25 [0.225, 0.275]: holds in every configuration, 10 configs"]


def test_installed_package_imports_no_study(tmp_path):
    """Outside the repository (no ``experiments`` importable) ``avsm_dr`` imports and works, and
    ``python -m avsm_dr`` says where the studies are instead of failing with a traceback."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    code = ("import sys, avsm_dr as ad; seg = ad.Segments.from_arrays([0, 1], z0=[0.1], z1=[0.2], "
            "transmittance=[0.5]); ad.build('avsm', seg, nodes=4); "
            "print(any(m == 'experiments' or m.startswith('experiments.') for m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0 and out.stdout.strip() == "False", out.stderr[-2000:]
    out = subprocess.run([sys.executable, "-m", "avsm_dr", "error_curves"], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 2 and "python -m experiments" in out.stderr and "Traceback" not in out.stderr


def test_study_declares_parameters_options_and_files(tmp_path, capsys):
    """A Study's quick / full parameters, its declared options (on the command line and as
    keywords of run; anything else refused) and its files: the CLI reads them, sniffs nothing."""
    calls = []

    def compute(res, P, extra=None):
        calls.append((dict(P), extra))
        return dict(rows=[{"n": P["n"]}], tables={"more.csv": [{"m": 1}]}, findings={"f": 1}, summary={"s": P["n"]})
    from experiments._study import Option
    study = Study("toy_decl", "toy", "nothing", {"n": 3, "k": [1]}, {"n": 1, "k": [1]}, compute,
                  options=(Option("k", "k values", type=int, nargs="+"), Option("extra", "not a parameter")))
    assert study.params(True) == ({"n": 1, "k": [1]}, {})
    assert study.params(False, k=[2, 5], extra="x") == ({"n": 3, "k": [2, 5]}, {"extra": "x"})
    with pytest.raises(TypeError, match="workers"):
        study.run(quick=True, out=tmp_path / "t", workers=2)             # not a sweep study
    out = study.run(quick=True, out=tmp_path / "t", k=[4])
    assert calls == [({"n": 1, "k": [4]}, None)] and out["summary"] == {"s": 1}
    assert sorted(p.name for p in (tmp_path / "t").iterdir()) == ["data.csv", "findings.json", "meta.json", "more.csv"]
    again = study.run(quick=True, out=tmp_path / "t", k=[4])
    assert again["cached"] is True and again["summary"] == {"s": 1} and len(calls) == 1
    assert study.run(quick=True, out=tmp_path / "t", k=[5]).get("cached") is None and len(calls) == 2
    # the real studies: declared options reach the command line
    assert cli.study("error_curves").sweep and "error_curves" in cli.sweep_experiments()
    assert "ordering" not in cli.sweep_experiments()
    with pytest.raises(SystemExit):
        cli.main(["frame", "--help"])
    text = capsys.readouterr().out
    assert "--resolutions" in text and "--scenes" in text and "Parameters" in text


def test_backward_cost_refuses_a_kind_it_cannot_differentiate(tmp_path):
    """``kinds`` restricts backward_cost's run; a name outside the differentiable online kinds
    (here the offline oracle) is refused by name before any work starts."""
    module = __import__("experiments.backward_cost", fromlist=["STUDY"])
    study = dataclasses.replace(module.STUDY, quick=dict(module.STUDY.quick,
                                                         **dict(TINY["backward_cost"], kinds=["avsm", "optimal"])))
    with pytest.raises(ValueError, match="kinds.*optimal"):
        study.run(quick=True, out=tmp_path / "bc")


def test_meta_names_the_code_the_run_started_with(monkeypatch, tmp_path):
    """git commit, its dirtiness and the cache key are taken when the run starts: a commit made
    while it runs is not the code it executed; run_seconds is the run's wall time."""
    monkeypatch.setattr(_common, "git_commit", lambda: "a" * 40)
    monkeypatch.setattr(_common, "git_dirty", lambda: False)
    res = _common.Results("toy", tmp_path / "toy", True, {"x": 1})
    monkeypatch.setattr(_common, "git_commit", lambda: "b" * 40)
    monkeypatch.setattr(_common, "git_dirty", lambda: True)
    meta = json.loads(res.write_meta({}).read_text())
    assert meta["git_commit"] == "a" * 40 and meta["git_dirty"] is False
    assert meta["cache_key"] == _common.cache_key() and meta["run_seconds"] >= 0
    assert _common.git_dirty() in (True, False, None)


def test_a_run_imports_its_lazily_imported_modules_at_its_start():
    """``preload`` imports the shared ``experiments._*`` modules and the study package's own modules
    before a run, so that an edit of experiments/ during a run cannot mix old and new source (a run
    once failed in its figures that way); subpackages (bench's optional peer kernels) stay lazy."""
    import sys
    from experiments._cli import preload
    names = preload("memory_budget")
    assert {"experiments.memory_budget.plots", "experiments.memory_budget.tables", "experiments._plotstyle",
            "experiments._common"} <= set(names)
    assert all(n in sys.modules for n in names)
    assert not any(n.startswith("experiments.bench.peer_kernels") for n in preload("bench"))
    assert "experiments.bench.paper_table" in preload("bench")

"""The budget study (``python -m experiments budget --volume FILE --bytes B``): per kind the
fitting setting with the lowest measured RMSE, the map floor, the printed table, ``--help``
and one-line errors for bad options."""
from __future__ import annotations

import contextlib
import io
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from experiments import _cli as cli
from experiments import _common

ROOT = Path(__file__).resolve().parents[1]
BUDGET = 24.0
BOX = ["-1", "-0.5", "-1", "1", "1.5", "1"]


@pytest.fixture(scope="module")
def volume(tmp_path_factory):
    """A small smoke ball with structure along the light (a .npy of extinction per unit)."""
    z, y, x = np.mgrid[-1:1:24j, -1:1:24j, -1:1:24j]
    grid = 25 * np.clip(1 - x ** 2 - y ** 2 - z ** 2, 0, None) * (1 + 0.6 * np.sin(7 * y))
    path = tmp_path_factory.mktemp("vol") / "ball.npy"
    np.save(path, grid.astype(np.float32))
    return path


@pytest.fixture(scope="module")
def quick_run(volume, tmp_path_factory):
    """One quick CLI run in this process: (its folder, what it printed)."""
    out = tmp_path_factory.mktemp("results")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        rc = cli.main(["budget", "--quick", "--out", str(out), "--volume", str(volume), "--bytes", str(BUDGET),
                       "--box", *BOX])
    assert rc == 0
    return out / "budget", buf.getvalue()


def _f(row, key):
    return float(row[key])


def test_chosen_settings_fit_and_have_the_lowest_rmse(quick_run):
    folder, _ = quick_run
    data, best = _common.read_csv(folder / "data.csv"), _common.read_csv(folder / "best.csv")
    assert data and best
    chosen = [b for b in best if b["status"] == "chosen"]
    assert len(chosen) >= 5, [b["kind"] for b in best]
    for b in chosen:
        assert _f(b, "bytes") <= BUDGET, b
        fitting = [r for r in data if r["kind"] == b["kind"] and _f(r, "bytes") <= BUDGET]
        assert fitting and _f(b, "rmse") == min(_f(r, "rmse") for r in fitting), b["kind"]
        mark = [r for r in data if r["kind"] == b["kind"] and r["chosen"] == "True"]
        assert [r["setting"] for r in mark] == [b["setting"]]
        assert _f(b, "rmse_low") <= _f(b, "rmse") <= _f(b, "rmse_high")
        assert b["indicative"] == "True" and int(b["configurations"]) == 2
    # a kind's settings were measured beyond the budget too, and kinds that do not fit say so
    assert any(_f(r, "bytes") > BUDGET for r in data)
    for b in best:
        if b["status"] != "chosen":
            assert b["status"].startswith("does not fit")
            assert all(_f(r, "bytes") > BUDGET for r in data if r["kind"] == b["kind"])
    # every kind with settings that fit is chosen: none is missed
    fits = {r["kind"] for r in data if _f(r, "bytes") <= BUDGET}
    assert fits == {b["kind"] for b in chosen}


def test_fixed_size_kinds_are_screened_at_their_measured_bytes(volume):
    """A fixed-size kind's screened bytes are its measured ones, the largest over the
    configurations: two lights that cover different shares of the map (the first map's
    occupancy alone under-estimated the other's bytes and skipped the largest fitting size)."""
    from avsm_dr import build
    from experiments import budget
    P = dict(budget.QUICK, volume=str(volume), box=[float(v) for v in BOX], bytes=BUDGET,
             light=["0.8,-1,0.3", "dir_a"], resolution=64, seeds=1)
    spec, cfgs = budget._scene(P), budget._configurations(P)
    caps = [c.capture(spec, P["resolution"])[1] for c in cfgs]
    occupancy = [budget._occupancy(c) for c in caps]
    assert occupancy[1] > occupancy[0], occupancy            # the second light covers more texels
    tried, _ = budget.screen_configurations(spec, cfgs, P)
    fixed = [s for s in tried if s["kind"] in ("avsm", "fom", "osm")]
    assert len(fixed) >= 6
    for s in fixed:
        measured = max(build(s["kind"], c.segments, **s["params"]).nbytes_sparse_per_texel for c in caps)
        assert s["screened_bytes"] == pytest.approx(measured, rel=1e-6), s["setting"]
    # the largest AVSM node count within the budget is among the settings measured
    n = max(s["params"]["nodes"] for s in tried if s["kind"] == "avsm" and s["screened_bytes"] <= BUDGET)
    params = next(s["params"] for s in tried if s["kind"] == "avsm" and s["params"]["nodes"] == n)
    nxt = max(build("avsm", c.segments, **{**params, "nodes": n + 1}).nbytes_sparse_per_texel for c in caps)
    assert nxt > BUDGET, (n, nxt)


def test_map_floor_is_the_exact_kinds_rmse(quick_run):
    folder, _ = quick_run
    data, best = _common.read_csv(folder / "data.csv"), _common.read_csv(folder / "best.csv")
    exact = [r for r in data if r["kind"] == "exact"]
    assert len(exact) == 1
    floor = _f(exact[0], "rmse")
    assert floor > 0
    assert all(_f(r, "map_floor") == floor for r in data + best)
    assert all(np.isfinite(_f(r, "depth_l2")) and _f(r, "build_ms") > 0 and _f(r, "lookup_ms") > 0 for r in data)


def test_order_signed_mean_leak_share_and_the_depth_l2_choice(quick_run):
    """Every setting (data.csv, best.csv) carries its order ('depth' for the AVSM family,
    '-' for kinds that do not depend on it), signed mean and leak share; configurations.csv
    per configuration; the summary names the depth-L2 choice and whether it differs."""
    from experiments.error_curves.labels import order_dependent
    folder, _ = quick_run
    data, best = _common.read_csv(folder / "data.csv"), _common.read_csv(folder / "best.csv")
    per = _common.read_csv(folder / "configurations.csv")
    for r in data + [b for b in best if b["status"] == "chosen"]:
        assert r["order"] == ("depth" if order_dependent(r["kind"]) else "-"), r
        assert np.isfinite(_f(r, "signed_mean")) and 0 <= _f(r, "leak_share") <= 1
    assert {r["order"] for r in per} == {"depth"} and all(0 <= _f(r, "leak_share") <= 1 for r in per)
    s = json.loads((folder / "meta.json").read_text())["summary"]
    fit = [r for r in data if r["kind"] != "exact" and _f(r, "bytes") <= BUDGET]
    least = min(fit, key=lambda r: (_f(r, "depth_l2"), _f(r, "bytes")))
    assert s["lowest_depth_l2"].startswith(f"{least['kind']} {least['setting']}:")
    top = min((b for b in best if b["status"] == "chosen"), key=lambda b: _f(b, "rmse"))
    assert s["metric_dependent"] == ((top["kind"], top["setting"]) != (least["kind"], least["setting"]))


def test_the_run_prints_a_table_and_where_its_files_are(quick_run):
    folder, printed = quick_run
    best = _common.read_csv(folder / "best.csv")
    head = "kind           setting"
    assert head in printed and "map floor" in printed and "lookup ms" in printed
    assert "INDICATIVE" in printed and "{" not in printed
    table = printed[printed.index(head):]
    for b in best:
        line = next(ln for ln in table.splitlines() if ln.startswith(b["kind"] + " "))
        if b["status"] == "chosen":
            assert b["setting"] in line and f"{_f(b, 'rmse'):.3g}" in line
        else:
            assert "does not fit" in line
    assert printed.rstrip().splitlines()[-1].startswith(f"wrote {folder}/ (")    # where the files are, last
    assert (folder / "table.txt").read_text().strip() in printed
    assert (folder / "error_vs_bytes.png").is_file() and (folder / "error_vs_bytes.pdf").is_file()
    meta = json.loads((folder / "meta.json").read_text())
    assert meta["params"]["bytes"] == BUDGET and meta["params"]["box"] == [float(v) for v in BOX]
    assert len(meta["params"]["volume_sha256"]) == 64


def test_help_names_the_options_and_files():
    p = subprocess.run([sys.executable, "-m", "experiments", "budget", "--help"], capture_output=True, text=True,
                       cwd=ROOT, timeout=300)
    assert p.returncode == 0, p.stderr
    for word in ("--volume", "--bytes", "--box", "--density-scale", "--light", "--quick", "--out",
                 "nbytes_sparse_per_texel", "data.csv", "best.csv", "DIR/budget/"):
        assert word in p.stdout, word


@pytest.mark.parametrize("args, want", [
    (["--bytes", "0"], "experiments: error: --bytes: expected a finite number > 0"),
    (["--bytes", "-3"], "experiments: error: --bytes: expected a finite number > 0"),
    (["--volume", "no_such_file.vol"], "experiments: error: --volume: no such file"),
    (["--volume", "VOLUME", "--box", "0", "0", "0", "1", "-1", "1"], "experiments: error: --box: expected X1 > X0"),
])
def test_bad_options_are_one_line_errors(args, want, volume, tmp_path):
    args = [str(volume) if a == "VOLUME" else a for a in args]
    p = subprocess.run([sys.executable, "-m", "experiments", "budget", "--quick", "--out", str(tmp_path), *args],
                       capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert p.returncode == 2, p.stderr
    assert "Traceback" not in p.stderr and p.stderr.count("\n") == 1 and p.stderr.startswith(want), p.stderr
    assert not any((tmp_path / "budget").iterdir())                   # nothing written


def test_run_refuses_bad_values_before_any_work(tmp_path):
    from experiments import budget
    with pytest.raises(ValueError, match=r"^--bytes: "):
        budget.run(quick=True, out=tmp_path / "b", bytes=float("nan"))
    with pytest.raises(ValueError, match=r"^--box: expected 6 numbers"):
        budget.STUDY.params(True, box=[0, 0, 1])
    with pytest.raises(ValueError, match=r"^--volume: expected a \.vol or \.npy file"):
        budget.STUDY.params(True, volume=__file__)
    assert not (tmp_path / "b").exists()

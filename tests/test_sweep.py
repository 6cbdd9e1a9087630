"""Sweeps as cells (:mod:`avsm_dr.sweep`): serial order, per-cell cache and resume, argument
checks, the CLI's --workers/--address, and a local Ray run equal to the serial one."""
from __future__ import annotations

import pytest

from avsm_dr import cli, sweep
from avsm_dr.experiments import _common, error_curves


def _square(cell):
    return {"cell": cell, "value": cell["x"] ** 2}


class _Boom(RuntimeError):
    pass


def test_serial_results_follow_the_cells_order():
    cells = [{"x": x} for x in (3, 1, 2)]
    assert [r["value"] for r in sweep.run_cells(_square, cells)] == [9, 1, 4]


def test_interrupted_sweep_resumes_from_its_cached_cells(tmp_path):
    calls = []

    def flaky(cell):
        calls.append(cell["x"])
        if cell["x"] == 2 and calls.count(2) == 1:
            raise _Boom("interrupted")
        return cell["x"] * 10

    cells = [{"x": x} for x in range(4)]
    with pytest.raises(_Boom):
        sweep.run_cells(flaky, cells, cache_dir=tmp_path, key={"p": 1})
    assert calls == [0, 1, 2]
    assert len(list(tmp_path.glob("*.pkl"))) == 2                     # cells 0 and 1 were kept
    out = sweep.run_cells(flaky, cells, cache_dir=tmp_path, key={"p": 1})
    assert out == [0, 10, 20, 30]
    assert calls == [0, 1, 2, 2, 3]                                  # only the missing cells ran
    sweep.run_cells(flaky, cells, cache_dir=tmp_path, key={"p": 2})  # another key: all recomputed
    assert calls[5:] == [0, 1, 2, 3]


@pytest.mark.parametrize("workers,address,msg", [(0, None, "workers"), (1.5, None, "workers"),
                                                 (True, None, "workers"), (None, "", "address"),
                                                 (None, 3, "address")])
def test_bad_workers_and_address_are_rejected(workers, address, msg):
    with pytest.raises(ValueError, match=f"^{msg}:"):
        sweep.run_cells(_square, [{"x": 1}], workers=workers, address=address)


def test_cli_rejects_workers_for_serial_experiments(capsys, tmp_path):
    assert "error_curves" in cli.sweep_experiments()
    assert cli.main(["ordering", "--quick", "--workers", "2", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "--workers" in err and "error_curves" in err
    assert cli.main(["error_curves", "--quick", "--workers", "0", "--out", str(tmp_path)]) == 2
    assert "workers:" in capsys.readouterr().err


#: Columns that measure time, not results (differ between any two runs).
TIMING = {"build_lookup_cpu_s"}


def test_ray_sweep_equals_the_serial_sweep(tmp_path):
    """Bit-identical rows for node kinds.  (Linear kinds sum their coefficients with float32
    atomic adds whose order follows the thread schedule: two serial runs already differ in
    the last bits, measured 3e-8 in T for FOM-8, so they are left out of this comparison.)"""
    pytest.importorskip("ray")
    opts = dict(quick=True, scenes=["plume"], kinds=["exact", "avsm"])
    serial = error_curves.run(out=tmp_path / "serial", **opts)
    ray_run = error_curves.run(out=tmp_path / "ray", workers=2, **opts)
    a = _common.read_csv(tmp_path / "serial" / "data.csv")
    b = _common.read_csv(tmp_path / "ray" / "data.csv")
    assert len(a) == len(b) > 0 and {x["method"] for x in a} == {"exact", "avsm", "truth_vs_mitsuba"}
    drop = lambda r: {k: v for k, v in r.items() if k not in TIMING}  # noqa: E731
    assert [drop(x) for x in a] == [drop(y) for y in b]     # same rows, same order, same digits
    assert serial["summary"] == ray_run["summary"]          # the claims' verdicts
    assert not (tmp_path / "ray" / "cells").exists()        # a complete run leaves no cells behind

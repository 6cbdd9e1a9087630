"""Sweeps as cells (:mod:`experiments._sweep`): serial order, per-cell cache and resume, argument
checks, the CLI's --workers/--address, and a local Ray run equal to the serial one."""
from __future__ import annotations

import json

import pytest

from experiments import _sweep as sweep
from experiments import _cli as cli
from experiments import _common, error_curves


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
    assert len(list(tmp_path.glob("*.npz"))) == 2                     # cells 0 and 1 were kept
    out = sweep.run_cells(flaky, cells, cache_dir=tmp_path, key={"p": 1})
    assert out == [0, 10, 20, 30]
    assert calls == [0, 1, 2, 2, 3]                                  # only the missing cells ran
    sweep.run_cells(flaky, cells, cache_dir=tmp_path, key={"p": 2})  # another key: all recomputed
    assert calls[5:] == [0, 1, 2, 3]


@pytest.mark.parametrize("workers,address,msg", [(0, None, "workers"), (1.5, None, "workers"),
                                                 (True, None, "workers"), (None, "", "address"),
                                                 (None, 3, "address"), (10**9, None, "workers"),
                                                 (None, "garbage", "address"), (None, "ray://h:99999", "address"),
                                                 (None, "host:port", "address")])
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


@pytest.mark.slow   # 22 s: starts a local Ray instance (the optional cluster path)
def test_ray_sweep_equals_the_serial_sweep(tmp_path):
    """Bit-identical rows for node and linear kinds: the linear kinds' builds sum each
    texel's segments in CSR order without atomics (the same bits on one Dr.Jit thread per
    Ray worker as on the driver's pool; float atomic adds differed by 3e-8 in T for FOM-8)."""
    pytest.importorskip("ray")
    opts = dict(quick=True, scenes=["plume"], kinds=["exact", "avsm", "moments", "osm", "basis"])
    serial = error_curves.run(out=tmp_path / "serial", **opts)
    ray_run = error_curves.run(out=tmp_path / "ray", workers=2, **opts)
    a = _common.read_csv(tmp_path / "serial" / "data.csv")
    b = _common.read_csv(tmp_path / "ray" / "data.csv")
    assert len(a) == len(b) > 0 and {x["method"] for x in a} >= {"exact", "avsm", "moments", "osm", "basis"}
    drop = lambda r: {k: v for k, v in r.items() if k not in TIMING}  # noqa: E731
    assert [drop(x) for x in a] == [drop(y) for y in b]     # same rows, same order, same digits
    assert serial["summary"] == ray_run["summary"]          # the claims' verdicts
    assert not (tmp_path / "ray" / "cells").exists()        # a complete run leaves no cells behind


#: Linear kinds (every projection path: power and trigonometric moments, Legendre, slices,
#: Fourier, the Beer sum): their builds must not depend on what ran before them.
LINEAR = ["moments", "basis", "osm", "fom", "beer"]


@pytest.mark.slow   # 16 s: two error_curves runs
def test_interrupted_error_curves_resume_equals_the_serial_run(tmp_path, monkeypatch):
    """An error_curves run interrupted after its first cell and resumed (in a process where
    other kinds were built in between, on another Dr.Jit thread count) writes the rows and
    findings of an uninterrupted run, digit for digit.  With float atomic adds in the
    linear projections the resumed trigonometric moments-3 tau_mean_error read -0.002088
    against -0.002116."""
    import drjit as dr

    import avsm_dr as ad
    opts = dict(quick=True, scenes=["plume"], kinds=LINEAR)
    serial = error_curves.run(out=tmp_path / "serial", **opts)
    real, calls = error_curves._cell, []

    def interrupted(job):
        calls.append(job["seed"])
        if len(calls) == 2:
            raise _Boom("interrupted")
        return real(job)

    monkeypatch.setattr(error_curves, "_cell", interrupted)
    with pytest.raises(_Boom):
        error_curves.run(out=tmp_path / "resumed", **opts)
    assert (tmp_path / "resumed" / "cells").is_dir()          # the first cell was kept
    monkeypatch.setattr(error_curves, "_cell", real)
    seg = ad.Segments.from_arrays([0, 2, 3], [0.1, 0.2, 0.5], [0.4, 0.3, 0.9], optical_depth=[0.5, 1.0, 2.0])
    for kind in ("avsm", "dsm", "fom", "moments"):              # other builds in this process
        ad.build(kind, seg)
    threads = dr.thread_count()
    try:
        dr.set_thread_count(1 if threads > 1 else 3)
        resumed = error_curves.run(out=tmp_path / "resumed", **opts)
    finally:
        dr.set_thread_count(threads)
    a = _common.read_csv(tmp_path / "serial" / "data.csv")
    b = _common.read_csv(tmp_path / "resumed" / "data.csv")
    assert len(a) == len(b) > 0 and {x["method"] for x in a} >= set(LINEAR)
    drop = lambda r: {k: v for k, v in r.items() if k not in TIMING}  # noqa: E731
    assert [drop(x) for x in a] == [drop(y) for y in b]
    assert serial["summary"] == resumed["summary"]
    fa = (tmp_path / "serial" / "findings.json").read_text()
    fb = (tmp_path / "resumed" / "findings.json").read_text()
    timing = ("run_seconds", "cells_seconds")
    strip = lambda t: {k: v for k, v in json.loads(t).items() if k not in timing}  # noqa: E731
    assert strip(fa) == strip(fb)


# ------------------------------------------------------------------ cell cache: data only
def _rich(cell):
    """A result with every type the cell files hold (error_curves' cells: rows, a store
    keyed by tuples of float32 arrays, NaN statistics)."""
    import numpy as np
    x = cell["x"]
    return {"rows": [{"x": x, "rmse": 0.1 * x, "nan": float("nan"), "inf": -float("inf"), "ok": x > 1,
                      "none": None, "np64": np.float64(x) / 3, "i64": np.int64(x), "neg0": -0.0}],
            "store": {("plume", f"s{x}", "in_volume"): (np.arange(x + 1, dtype=np.float32) / 7,
                                                         np.float32(x) / 3)},
            "nested": [1, (2.5, "a"), [np.zeros((2, 0))]], "big": 2 ** 70 + x}


def _same(a, b) -> bool:
    """Equal values of equal types, bit for bit (NaN equal to NaN, -0.0 not equal to 0.0)."""
    import math

    import numpy as np
    if type(a) is not type(b):
        return False
    if isinstance(a, dict):
        return list(a) == list(b) and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, np.ndarray):
        return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    if isinstance(a, (float, np.floating)):
        return (math.isnan(a) and math.isnan(b)) or (a == b and math.copysign(1, a) == math.copysign(1, b))
    return a == b


def test_cached_cells_equal_the_computed_ones_exactly(tmp_path):
    cells = [{"x": x} for x in (3, 1, 2)]
    first = sweep.run_cells(_rich, cells, cache_dir=tmp_path, key={"p": 1})
    assert [p.suffix for p in tmp_path.iterdir()] == [".npz"] * 3        # no temporary files left
    again = sweep.run_cells(lambda c: pytest.fail("recomputed"), cells, cache_dir=tmp_path, key={"p": 1})
    assert _same(first, again) and _same(first, [_rich(c) for c in cells])


def test_uncachable_result_is_a_clear_error(tmp_path):
    with pytest.raises(TypeError, match="cannot cache the result of cell .*holds a builtins.set"):
        sweep.run_cells(lambda c: {"s": {1, 2}}, [{"x": 1}], cache_dir=tmp_path, key=1)


def _npz(path, **members):
    import numpy as np
    with open(path, "wb") as fh:
        np.savez(fh, **members)


def _meta(obj):
    import numpy as np
    return np.frombuffer(json.dumps(obj).encode(), np.uint8)


def _crafted(tmp_path, case, cell, key):
    """Write a hostile or stale file where the cell's result would be cached."""
    import pickle

    import numpy as np
    path = sweep._cache_path(tmp_path, sweep.key_hash(key), cell)
    good = {"schema": sweep.SCHEMA, "key": sweep.key_digest(key), "cell": json.dumps(cell, sort_keys=True)}
    if case == "pickle_runs_a_command":
        class Evil:
            def __reduce__(self):
                import os
                return (os.system, (f"touch {tmp_path / 'pwned'}",))
        path.write_bytes(pickle.dumps(Evil()))
    elif case == "pickle_of_none":
        path.write_bytes(pickle.dumps(None))
    elif case == "unknown_module":
        path.write_bytes(b"\x80\x04\x95\x15\x00\x00\x00\x00\x00\x00\x00\x8c\x06nomodx\x8c\x03att\x93\x94.")
    elif case == "object_array":
        with open(path, "wb") as fh:
            np.savez(fh, meta=_meta(dict(good, value=None)), a0=np.array([None, print], dtype=object))
    elif case == "huge_length":                 # a valid zip whose .npy header announces 10^12 float64
        import io
        import zipfile
        meta, head = io.BytesIO(), io.BytesIO()
        np.save(meta, _meta(dict(good, value={"array": 0, "dtype": "<f8", "shape": [10 ** 12]})))
        np.lib.format.write_array_header_1_0(head, {"descr": "<f8", "fortran_order": False, "shape": (10 ** 12,)})
        with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as z:
            z.writestr("meta.npy", meta.getvalue())
            z.writestr("a0.npy", head.getvalue() + bytes(32))
    elif case == "huge_length_pickle":          # BINBYTES8 announcing 2^62 bytes
        path.write_bytes(b"\x80\x04\x8e" + (2 ** 62).to_bytes(8, "little") + b".")
    elif case == "valid_none_for_another_key":
        _npz(path, meta=_meta(dict(good, key=sweep.key_digest({"other": 1}), value=None)))
    elif case == "another_cells_file":
        _npz(path, meta=_meta(dict(good, cell=json.dumps({"x": 99}), value=None)))
    elif case == "old_schema":
        _npz(path, meta=_meta(dict(good, schema=0, value=None)))
    elif case == "malformed_tree":
        _npz(path, meta=_meta(dict(good, value={"array": 5, "dtype": "<f4", "shape": [1]})))
    elif case == "truncated":
        sweep._store(path, _rich(cell), sweep.key_digest(key), cell)
        path.write_bytes(path.read_bytes()[:-40])
    return path


CRAFTED = ["pickle_runs_a_command", "pickle_of_none", "unknown_module", "object_array", "huge_length",
           "huge_length_pickle", "valid_none_for_another_key", "another_cells_file", "old_schema", "malformed_tree",
           "truncated"]


@pytest.mark.parametrize("case", CRAFTED)
def test_hostile_or_stale_cell_files_are_named_and_recomputed(tmp_path, case):
    """Nothing in a cell file is executed or trusted: a crafted pickle runs no command, a
    file for another key or cell (even a valid ``None``) is not taken as the result, a
    corrupt or huge one does not abort the sweep; each is named in a warning, recomputed
    and overwritten."""
    cell, key = {"x": 2}, {"p": 1}
    path = _crafted(tmp_path, case, cell, key)
    with pytest.warns(sweep.CellCacheWarning, match=f"ignoring cached cell '{path}'"):
        out = sweep.run_cells(_rich, [cell], cache_dir=tmp_path, key=key)
    assert not (tmp_path / "pwned").exists()
    assert _same(out, [_rich(cell)])
    assert _same(sweep._load(path, sweep.key_digest(key), cell), (True, _rich(cell)))   # overwritten


def test_crafted_pickle_runs_nothing_in_a_fresh_process(tmp_path):
    """The crafted file of the issue, resumed in its own process: no command, exit 0."""
    import subprocess
    import sys
    key = {"p": 1}
    code = ("import avsm_dr; from experiments import _sweep as sweep; "
            f"print(sweep.run_cells(abs, [-2], cache_dir={str(tmp_path)!r}, key={key!r}))")
    _crafted(tmp_path, "pickle_runs_a_command", -2, key)
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip().splitlines()[-1] == "[2]" and "ignoring cached cell" in p.stderr
    assert not (tmp_path / "pwned").exists()


def test_ray_start_failures_name_the_option(monkeypatch):
    """Ray's own errors (unreachable cluster, missing ray[client]) become ValueErrors naming
    ``address`` / ``workers`` (the CLI prints them in one line)."""
    import sys
    import types

    def init(**kw):
        raise ConnectionError("Could not connect to the cluster\nsecond line")
    fake = types.SimpleNamespace(is_initialized=lambda: False, init=init, shutdown=lambda: None)
    monkeypatch.setitem(sys.modules, "ray", fake)
    with pytest.raises(ValueError, match=r"^address: cannot connect to the Ray cluster at 'ray://h:1': "
                                         r"Could not connect to the cluster$"):
        sweep.run_cells(_square, [{"x": 1}], address="ray://h:1")
    with pytest.raises(ValueError, match=r"^workers: cannot start a local Ray instance with 2 workers"):
        sweep.run_cells(_square, [{"x": 1}], workers=2)

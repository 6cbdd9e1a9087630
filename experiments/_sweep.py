"""Sweeps as grids of independent cells: serial, or through Ray on a local pool or a cluster.

An experiment lists its cells (scene x seed x light x ..., plain JSON-able values) and a
module-level function ``fn(cell) -> result``.  :func:`run_cells` returns the results in
the order of the cells, the same whichever way it ran:

* serial (default, ``workers=None`` and ``address=None``): one cell after another in
  this process; nothing beyond the package is needed;
* ``workers=N``: a local Ray instance with N worker processes (the optional extra
  ``pip install avsm_dr[cluster]``), each cell a Ray task of one CPU whose Dr.Jit uses
  ``cpu_count // N`` threads;
* ``address="ray://host:10001"`` (or ``"auto"`` on a cluster node): an existing Ray
  cluster.  The workers need this package installed, the repository's ``experiments``
  importable (same version: the cache key holds the source hash of both) and Dr.Jit's
  libLLVM (see README); results come back to the driver.

Resuming: with ``cache_dir``, each finished cell's result is written to
``cache_dir/<key>-<cell hash>.npz`` as it arrives; a later run with the same ``key`` (the
experiment's parameters, the package's source hash and library versions) loads those
cells instead of recomputing them, so an interrupted sweep resumes where it stopped.  The
tqdm bar counts cells (cached ones included, at once).  The cell files hold data only,
never code (nothing is unpickled): an uncompressed ``.npz`` read with ``allow_pickle=False``
whose ``meta`` member is UTF-8 JSON ``{"schema", "key", "cell", "value"}`` - the format
version, the SHA-256 of the sweep's key, the cell itself, and the result as a tree of
None / bool / int / float / str, lists, ``{"tuple": [...]}``, ``{"dict": [[k, v], ...]}``,
``{"float": "nan" | "inf" | "-inf"}`` and ``{"array" | "scalar": i, "dtype", "shape"}``
(NumPy arrays and scalars: member ``a<i>``).  A file that does not match (another key or
cell, an unknown schema, a malformed tree, arrays larger than the file) is reported by a
:class:`CellCacheWarning` naming it and recomputed.

Pointing it at a cluster: start Ray on the head node (``ray start --head``) and workers
(``ray start --address=HEAD:6379``), install ``avsm_dr`` and a clone of this repository on every node, then run
``python -m experiments error_curves --address ray://HEAD:10001`` from the driver.
"""
from __future__ import annotations

import contextlib
import hashlib
import io
import json
import math
import os
import re
import warnings
import zipfile
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
from tqdm import tqdm

#: Version of the cell file format (module docstring); files of another version are recomputed.
SCHEMA = 1
#: Local Ray workers per CPU of this machine, at most (more only adds idle processes).
WORKERS_PER_CPU = 4
#: Ray addresses: ``auto``, ``local``, ``ray://HOST[:PORT]`` (Ray client) or ``HOST:PORT`` (GCS).
_ADDRESS = re.compile(r"(auto|local|ray://(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9._-]+)(:\d{1,5})?"
                      r"|(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9._-]+):\d{1,5})")


class CellCacheWarning(UserWarning):
    """A cached cell file was ignored (named in the message) and its cell is recomputed."""


def _cpus() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def check_workers(workers, address) -> tuple[int | None, str | None]:
    """Validated (workers, address): workers a positive int or None, address a non-empty
    str or None; ValueError naming the argument."""
    if workers is not None:
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
            raise ValueError(f"workers: expected a positive integer, got {workers!r}")
        cpus = _cpus()
        if workers > WORKERS_PER_CPU * cpus:
            raise ValueError(f"workers: expected an integer in [1, {WORKERS_PER_CPU * cpus}] ({WORKERS_PER_CPU} "
                             f"per CPU, this machine has {cpus}; a larger sweep needs a Ray cluster: "
                             f"address), got {workers}")
    if address is not None and (not isinstance(address, str) or not _ADDRESS.fullmatch(address)
                                or (address.rsplit(":", 1)[-1].isdigit()
                                    and not 1 <= int(address.rsplit(":", 1)[-1]) <= 65535)):
        raise ValueError(f"address: expected a Ray address such as 'ray://host:10001', 'host:6379' or 'auto', "
                         f"got {address!r}")
    return workers, address


def cell_hash(cell: Any) -> str:
    """Stable short hash of a cell (its JSON form; tuples and lists alike)."""
    return hashlib.sha256(json.dumps(cell, sort_keys=True, default=str).encode()).hexdigest()[:16]


def key_hash(key: Any) -> str:
    """Short hash of the sweep's identity (parameters, source hash, versions)."""
    return hashlib.sha256(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()[:12]


def _canonical(x: Any) -> str:
    return json.dumps(x, sort_keys=True, default=str)


def key_digest(key: Any) -> str:
    """Full SHA-256 of the sweep's key, stored inside each cell file."""
    return hashlib.sha256(_canonical(key).encode()).hexdigest()


def _cache_path(cache_dir: Path, key: str, cell: Any) -> Path:
    return cache_dir / f"{key}-{cell_hash(cell)}.npz"


# ------------------------------------------------------------- cell files (data only)
class _Corrupt(ValueError):
    """A cell file that is not what this sweep wrote for this cell."""


#: NumPy dtype kinds a cell file may hold (no objects: nothing to unpickle).
_ARRAY_KINDS = "biufcU"


def _encode(v: Any, arrays: list) -> Any:
    """``v`` as a JSON tree (module docstring); NumPy arrays and scalars appended to ``arrays``."""
    if v is None or isinstance(v, (bool, str)):
        return v
    if isinstance(v, int) and not isinstance(v, np.integer):
        return int(v)
    if isinstance(v, float) and not isinstance(v, np.floating):
        return float(v) if math.isfinite(v) else {"float": repr(float(v))}
    if isinstance(v, (np.ndarray, np.generic)):
        a = np.asarray(v)
        if a.dtype.kind not in _ARRAY_KINDS:
            raise TypeError(f"a NumPy array of dtype {a.dtype}")
        arrays.append(a)
        return {"array" if isinstance(v, np.ndarray) else "scalar": len(arrays) - 1, "dtype": a.dtype.str,
                "shape": list(a.shape)}
    if isinstance(v, list):
        return [_encode(x, arrays) for x in v]
    if isinstance(v, tuple):
        return {"tuple": [_encode(x, arrays) for x in v]}
    if isinstance(v, dict):
        return {"dict": [[_encode(k, arrays), _encode(x, arrays)] for k, x in v.items()]}
    raise TypeError(f"a {type(v).__module__}.{type(v).__qualname__}")


def _decode(t: Any, arrays: dict) -> Any:
    """Inverse of :func:`_encode`; ``_Corrupt`` for anything it would not have written."""
    if t is None or isinstance(t, (bool, int, float, str)):
        return t
    if isinstance(t, list):
        return [_decode(x, arrays) for x in t]
    if not isinstance(t, dict) or len(t) not in (1, 3):
        raise _Corrupt(f"unexpected node {str(t)[:60]!r}")
    if "tuple" in t and len(t) == 1 and isinstance(t["tuple"], list):
        return tuple(_decode(x, arrays) for x in t["tuple"])
    if "dict" in t and len(t) == 1 and isinstance(t["dict"], list):
        if not all(isinstance(kv, list) and len(kv) == 2 for kv in t["dict"]):
            raise _Corrupt("a dict entry is not a [key, value] pair")
        out = {}
        for k, x in t["dict"]:
            k, x = _decode(k, arrays), _decode(x, arrays)
            try:
                out[k] = x
            except TypeError:                                   # unhashable key
                raise _Corrupt(f"unhashable dict key {str(k)[:60]!r}") from None
        return out
    if t.get("float") in ("nan", "inf", "-inf") and len(t) == 1:
        return float(t["float"])
    tag = "array" if "array" in t else "scalar" if "scalar" in t else None
    if tag is None or set(t) != {tag, "dtype", "shape"}:
        raise _Corrupt(f"unexpected node {str(t)[:60]!r}")
    a = arrays.get(t[tag]) if isinstance(t[tag], int) and not isinstance(t[tag], bool) else None
    if a is None or a.dtype.str != t["dtype"] or list(a.shape) != t["shape"] \
            or (tag == "scalar" and a.shape != ()):
        raise _Corrupt(f"{tag} {t[tag]!r}: missing or not of dtype {t['dtype']} and shape {t['shape']}")
    return a[()] if tag == "scalar" else a


def _read_members(path: Path) -> tuple[bytes, dict]:
    """(meta JSON bytes, {i: array}) of a cell file; every member's size is checked against
    the file before it is read (no allocation larger than the file, no pickles)."""
    with zipfile.ZipFile(path) as z:
        meta, arrays = None, {}
        for info in z.infolist():
            if info.compress_type != zipfile.ZIP_STORED or info.file_size != info.compress_size:
                raise _Corrupt(f"member {info.filename!r} is compressed (cell files are stored)")
            if info.file_size > path.stat().st_size:
                raise _Corrupt(f"member {info.filename!r} announces {info.file_size} bytes, more than the file")
            name = info.filename.removesuffix(".npy")
            if name != "meta" and not re.fullmatch(r"a\d{1,9}", name):
                raise _Corrupt(f"unexpected member {info.filename!r}")
            f = io.BytesIO(z.read(info))             # at most the file's size (checked above), CRC checked
            version = np.lib.format.read_magic(f)
            header = {(1, 0): np.lib.format.read_array_header_1_0,
                      (2, 0): np.lib.format.read_array_header_2_0}.get(version)
            if header is None:
                raise _Corrupt(f"member {info.filename!r}: .npy version {version}")
            shape, _, dtype = header(f)
            if dtype.hasobject or dtype.kind not in _ARRAY_KINDS:
                raise _Corrupt(f"member {info.filename!r} has dtype {dtype}")
            if math.prod(shape) * dtype.itemsize > info.file_size:
                raise _Corrupt(f"member {info.filename!r} announces shape {shape}, larger than its data")
            f.seek(0)
            a = np.lib.format.read_array(f, allow_pickle=False)
            if name == "meta":
                if a.dtype != np.uint8 or a.ndim != 1:
                    raise _Corrupt("member 'meta' is not UTF-8 bytes")
                meta = a.tobytes()
            else:
                arrays[int(name[1:])] = a
    if meta is None:
        raise _Corrupt("no 'meta' member")
    return meta, arrays


def _load(path: Path, digest: str, cell: Any):
    """(True, result) from a valid cell file for ``cell`` under key ``digest``; else (False,
    None), with a :class:`CellCacheWarning` naming the file unless there is none."""
    if not path.exists():
        return False, None
    try:
        raw, arrays = _read_members(path)
        meta = json.loads(raw.decode("utf-8"))
        if not isinstance(meta, dict) or set(meta) != {"schema", "key", "cell", "value"}:
            raise _Corrupt("its meta is not {schema, key, cell, value}")
        if meta["schema"] != SCHEMA:
            raise _Corrupt(f"schema {meta['schema']!r}, expected {SCHEMA}")
        if meta["key"] != digest:
            raise _Corrupt("it belongs to another sweep key")
        if meta["cell"] != _canonical(cell):
            raise _Corrupt("it holds another cell")
        return True, _decode(meta["value"], arrays)
    except Exception as exc:              # corrupt, truncated, crafted: never fatal, never trusted
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        warnings.warn(f"sweep: ignoring cached cell {str(path)!r} ({reason}); recomputing it",
                      CellCacheWarning, stacklevel=3)
        return False, None


def _store(path: Path, value, digest: str, cell: Any) -> None:
    """Write ``value`` as the cell file of ``cell`` (atomic: an interrupted write leaves no cell)."""
    arrays: list = []
    try:
        tree = _encode(value, arrays)
    except TypeError as exc:
        raise TypeError(f"sweep: cannot cache the result of cell {_canonical(cell)[:80]}: it holds {exc}; "
                        f"cell files store None, bool, int, float, str, list, tuple, dict and NumPy "
                        f"arrays / scalars") from None
    meta = json.dumps({"schema": SCHEMA, "key": digest, "cell": _canonical(cell), "value": tree})
    members = {"meta": np.frombuffer(meta.encode("utf-8"), np.uint8)}
    members.update({f"a{i}": a for i, a in enumerate(arrays)})
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    buf = io.BytesIO()
    np.savez(buf, **members)
    tmp.write_bytes(buf.getvalue())
    os.replace(tmp, path)


def _run_with_threads(fn: Callable, cell: Any, threads: int | None):
    """A Ray task: set Dr.Jit's thread count (share of the machine), then run the cell."""
    if threads:
        from avsm_dr import backend  # noqa: F401  (libLLVM before drjit)
        import drjit as dr
        dr.set_thread_count(threads)
    return fn(cell)


@contextlib.contextmanager
def pool(workers: int | None = None, address: str | None = None):
    """Ray, initialised for the block (local with ``workers`` CPUs, or the cluster at
    ``address``) unless it already is; yields the ``ray`` module, or None for a serial run.
    An experiment with several sweeps wraps them in one ``pool`` to start Ray once."""
    workers, address = check_workers(workers, address)
    if workers is None and address is None:
        yield None
        return
    try:
        import ray
    except ImportError:
        raise ValueError("workers: Ray is not installed; install the optional extra "
                         "(pip install 'avsm_dr[cluster]') or run without --workers/--address") from None
    started = False
    if not ray.is_initialized():
        try:
            if address is not None:
                ray.init(address=address, log_to_driver=False)
            else:
                ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
        except Exception as exc:        # Ray's own errors (format, missing ray[client], no cluster)
            what = (f"address: cannot connect to the Ray cluster at {address!r}" if address is not None
                    else f"workers: cannot start a local Ray instance with {workers} workers")
            raise ValueError(f"{what}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from None
        started = True
    try:
        yield ray
    finally:
        if started:
            ray.shutdown()


def run_cells(fn: Callable[[Any], Any], cells: Sequence[Any], *, desc: str = "cells", cache_dir=None,
              key: Any = None, workers: int | None = None, address: str | None = None) -> list:
    """``[fn(c) for c in cells]``, serially or through Ray (module docstring), with
    per-cell caching under ``cache_dir`` when given."""
    workers, address = check_workers(workers, address)
    cells = list(cells)
    results: list = [None] * len(cells)
    done = [False] * len(cells)
    kh, digest = key_hash(key), key_digest(key)
    cache = Path(cache_dir) if cache_dir is not None else None
    if cache is not None:
        cache.mkdir(parents=True, exist_ok=True)
        for i, c in enumerate(cells):
            done[i], results[i] = _load(_cache_path(cache, kh, c), digest, c)
    todo = [i for i in range(len(cells)) if not done[i]]
    with tqdm(total=len(cells), initial=len(cells) - len(todo), desc=desc, unit="cell") as bar:
        def finish(i, value):
            results[i] = value
            if cache is not None:
                _store(_cache_path(cache, kh, cells[i]), value, digest, cells[i])
            bar.update(1)

        if workers is None and address is None:
            for i in todo:
                finish(i, fn(cells[i]))
            return results
        with pool(workers, address) as ray:
            threads = max(1, (os.cpu_count() or 1) // workers) if workers else None
            task = ray.remote(num_cpus=1)(_run_with_threads)
            pending = {task.remote(fn, cells[i], threads): i for i in todo}
            while pending:
                ready, _ = ray.wait(list(pending), num_returns=1)
                for ref in ready:
                    finish(pending.pop(ref), ray.get(ref))
    return results

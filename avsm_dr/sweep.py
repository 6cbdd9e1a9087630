"""Sweeps as grids of independent cells: serial, or through Ray on a local pool or a cluster.

An experiment lists its cells (scene x seed x light x ..., plain picklable values) and a
module-level function ``fn(cell) -> result``.  :func:`run_cells` returns the results in
the order of the cells, the same whichever way it ran:

* serial (default, ``workers=None`` and ``address=None``): one cell after another in
  this process; nothing beyond the package is needed;
* ``workers=N``: a local Ray instance with N worker processes (the optional extra
  ``pip install avsm_dr[cluster]``), each cell a Ray task of one CPU whose Dr.Jit uses
  ``cpu_count // N`` threads;
* ``address="ray://host:10001"`` (or ``"auto"`` on a cluster node): an existing Ray
  cluster.  The workers need this package installed (same version: the cache key holds the
  package's source hash) and Dr.Jit's libLLVM (see README); results come back to the driver.

Resuming: with ``cache_dir``, each finished cell's result is pickled to
``cache_dir/<key>-<cell hash>.pkl`` as it arrives; a later run with the same ``key`` (the
experiment's parameters, the package's source hash and library versions) loads those
cells instead of recomputing them, so an interrupted sweep resumes where it stopped.  The
tqdm bar counts cells (cached ones included, at once).

Pointing it at a cluster: start Ray on the head node (``ray start --head``) and workers
(``ray start --address=HEAD:6379``), install ``avsm_dr`` on every node, then run
``python -m avsm_dr error_curves --address ray://HEAD:10001`` from the driver.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import pickle
from pathlib import Path
from typing import Any, Callable, Sequence

from tqdm import tqdm


def check_workers(workers, address) -> tuple[int | None, str | None]:
    """Validated (workers, address): workers a positive int or None, address a non-empty
    str or None; ValueError naming the argument."""
    if workers is not None:
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
            raise ValueError(f"workers: expected a positive integer, got {workers!r}")
    if address is not None and (not isinstance(address, str) or not address.strip()):
        raise ValueError(f"address: expected a Ray address such as 'ray://host:10001' or 'auto', got {address!r}")
    return workers, address


def cell_hash(cell: Any) -> str:
    """Stable short hash of a cell (its JSON form; tuples and lists alike)."""
    return hashlib.sha256(json.dumps(cell, sort_keys=True, default=str).encode()).hexdigest()[:16]


def key_hash(key: Any) -> str:
    """Short hash of the sweep's identity (parameters, source hash, versions)."""
    return hashlib.sha256(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()[:12]


def _cache_path(cache_dir: Path, key: str, cell: Any) -> Path:
    return cache_dir / f"{key}-{cell_hash(cell)}.pkl"


def _load(path: Path):
    try:
        with path.open("rb") as f:
            return True, pickle.load(f)
    except (OSError, EOFError, pickle.UnpicklingError):
        return False, None


def _store(path: Path, value) -> None:
    tmp = path.with_suffix(".tmp")
    with tmp.open("wb") as f:
        pickle.dump(value, f, protocol=pickle.HIGHEST_PROTOCOL)
    os.replace(tmp, path)                         # atomic: an interrupted write leaves no cell


def _run_with_threads(fn: Callable, cell: Any, threads: int | None):
    """A Ray task: set Dr.Jit's thread count (share of the machine), then run the cell."""
    if threads:
        from . import backend  # noqa: F401  (libLLVM before drjit)
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
        if address is not None:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
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
    kh = key_hash(key)
    cache = Path(cache_dir) if cache_dir is not None else None
    if cache is not None:
        cache.mkdir(parents=True, exist_ok=True)
        for i, c in enumerate(cells):
            done[i], results[i] = _load(_cache_path(cache, kh, c))
    todo = [i for i in range(len(cells)) if not done[i]]
    with tqdm(total=len(cells), initial=len(cells) - len(todo), desc=desc, unit="cell") as bar:
        def finish(i, value):
            results[i] = value
            if cache is not None:
                _store(_cache_path(cache, kh, cells[i]), value)
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

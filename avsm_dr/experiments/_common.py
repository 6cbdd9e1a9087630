"""Shared plumbing for experiments: the output folder and its cache, CSV/JSON writers, the
timer (:func:`measure`, :func:`timed`) and the memory meter (:class:`Meter`).

Cache: an experiment reuses ``<out>/data.csv`` when ``meta.json`` there records the same
parameters *and* the same :func:`cache_key` (hash of the package source, Dr.Jit / Mitsuba /
NumPy versions, backend), so results never survive a code or version change.
"""
from __future__ import annotations

import csv
import functools
import gc
import hashlib
import json
import os
import platform
import statistics
import subprocess
import time
from pathlib import Path
from typing import Any, Callable, Iterable

import drjit as dr
import numpy as np

#: The package's root folder (``avsm_dr/``); its ``*.py`` files make the source hash.
PACKAGE_DIR = Path(__file__).resolve().parents[1]


# =============================================================== reproducibility
@functools.lru_cache(maxsize=None)
def source_hash() -> str:
    """SHA-256 (hex, first 16 digits) of every ``avsm_dr/**/*.py`` file, names and contents,
    computed once per process (the code that runs is the code imported at start-up)."""
    h = hashlib.sha256()
    for path in sorted(PACKAGE_DIR.rglob("*.py")):
        h.update(path.relative_to(PACKAGE_DIR).as_posix().encode())
        h.update(b"\0")
        h.update(path.read_bytes())
        h.update(b"\0")
    return h.hexdigest()[:16]


def _dist_version(name: str) -> str | None:
    """Installed version of distribution ``name`` (metadata only: nothing is imported)."""
    from importlib import metadata
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def versions() -> dict:
    """Versions of the libraries results depend on (Mitsuba read lazily, never imported)."""
    return {"drjit": dr.__version__, "mitsuba": _dist_version("mitsuba"), "numpy": np.__version__}


def git_commit() -> str | None:
    """``git rev-parse HEAD`` of the checkout holding the package, or None (no git, not a
    checkout, or an installed copy)."""
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=PACKAGE_DIR, capture_output=True, text=True,
                             timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    sha = out.stdout.strip()
    return sha if out.returncode == 0 and sha else None


def cache_key() -> dict:
    """What, besides the parameters, must match for cached results to be reused:
    source hash, library versions and the Dr.Jit backend."""
    from .. import backend
    return {"source": source_hash(), **versions(), "backend": backend.get_backend()}


# ======================================================================== results
class Results:
    """``<out>/`` (default ``results/<name>/``) with ``data.csv``, ``meta.json`` and figures.

    ``out`` is the experiment's own folder; one holding another experiment's results is
    refused (``ValueError``), so two experiments never mix their files (the CLI passes
    ``<--out>/<name>/``)."""

    def __init__(self, name: str, out: str | Path | None, quick: bool, params: dict[str, Any]):
        if out is not None and not str(out).strip():
            raise ValueError(f"out: expected a folder, got {str(out)!r}")
        self.name = name
        self.dir = Path(out) if out is not None else Path("results") / name
        if self.dir.exists() and not self.dir.is_dir():
            raise ValueError(f"out: {str(self.dir)!r} is a file, expected a folder")
        self.dir.mkdir(parents=True, exist_ok=True)
        other = self._meta().get("experiment")
        if other not in (None, name):
            raise ValueError(f"out: {str(self.dir)!r} holds the results of experiment {other!r}; "
                             f"give {name!r} its own folder")
        self.quick = quick
        self.params = dict(params, quick=quick)
        self.figures: list[str] = []

    def _meta(self) -> dict:
        try:
            meta = json.loads((self.dir / "meta.json").read_text())
        except (OSError, ValueError):
            return {}
        return meta if isinstance(meta, dict) else {}

    def exists(self, csv_name: str = "data.csv") -> bool:
        """True when ``csv_name`` and a ``meta.json`` with the same parameters and the same
        :func:`cache_key` are there."""
        if not (self.dir / csv_name).exists():
            return False
        meta = self._meta()
        same = json.loads(json.dumps(self.params, default=str))
        return bool(meta) and meta.get("params") == same and meta.get("cache_key") == cache_key()

    def cached(self, force: bool = False, csv_name: str = "data.csv") -> dict | None:
        """The result of an earlier identical run (``{'csv', 'out', 'cached': True}``), or
        None when the experiment must run (``force``, or nothing reusable)."""
        if force or not self.exists(csv_name):
            return None
        return {"csv": str(self.dir / csv_name), "out": str(self.dir), "cached": True}

    def write_csv(self, rows: Iterable[dict], csv_name: str = "data.csv") -> Path:
        """Rows (dicts; columns in order of first appearance) as ``csv_name``."""
        rows = list(rows)
        path = self.dir / csv_name
        fields: list[str] = []
        for r in rows:
            for k in r:
                if k not in fields:
                    fields.append(k)
        with path.open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=fields)
            w.writeheader()
            for r in rows:
                w.writerow({k: _fmt(v) for k, v in r.items()})
        return path

    def save_figure(self, fig, filename: str) -> Path:
        """Save a Matplotlib figure as ``filename`` and close it."""
        path = self.dir / filename
        fig.savefig(path, dpi=110, bbox_inches="tight")
        import matplotlib.pyplot as plt
        plt.close(fig)
        self.figures.append(str(path))
        return path

    def write_meta(self, summary: dict | None = None) -> Path:
        """``meta.json``: parameters, summary, figures, cache key, git commit, versions,
        backend and machine."""
        from .. import backend
        meta = {
            "experiment": self.name,
            "params": self.params,
            "summary": summary or {},
            "figures": [Path(f).name for f in self.figures],
            "cache_key": cache_key(),
            "git_commit": git_commit(),
            **versions(),
            "backend": backend.get_backend(),
            "machine": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "cpus": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        }
        path = self.dir / "meta.json"
        path.write_text(json.dumps(meta, indent=2, default=str))
        return path


def read_csv(path: str | Path) -> list[dict]:
    """Rows of a CSV written by :meth:`Results.write_csv` (values as strings)."""
    with Path(path).open() as fh:
        return list(csv.DictReader(fh))


def _fmt(v):
    if isinstance(v, float):
        return f"{v:.9g}"
    return v


# ========================================================================= timing
def sync(out=None):
    """Evaluate ``out`` (if it holds Dr.Jit arrays) and wait for the active backend's
    queued kernels (``dr.sync_thread``: CPU worker threads or the CUDA stream)."""
    if out is not None:
        try:
            dr.eval(out)
        except Exception:                 # not a Dr.Jit PyTree (NumPy, plain objects)
            pass
    dr.sync_thread()


def _jit_kernels(hist):
    return [k for k in hist if k["type"] == dr.KernelType.JIT]


def measure(fns: dict, repeats: int = 3, warmup: int = 1) -> dict:
    """Time each callable in ``fns`` (name -> fn): a first call (JIT compile included),
    ``warmup - 1`` more, then ``repeats`` rounds run interleaved across ``fns`` (so load
    from other processes hits each alike).  Every call is followed by :func:`sync`.

    Returns name -> dict(wall_s, cpu_s (process CPU time, all threads), kernel_s (Dr.Jit
    kernel execution from ``dr.kernel_history``), first_s, first_cpu_s, jit_s (codegen +
    backend compile of the first call), compiled, from_disk, kernels (JIT launches per
    call), out (last result)); medians over the repeats (``repeats=0``: the first call)."""
    flag = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    res = {}
    try:
        for name, fn in fns.items():
            dr.kernel_history()                                   # clear
            c0, t0 = time.process_time(), time.perf_counter()
            out = fn()
            sync(out)
            first, first_cpu = time.perf_counter() - t0, time.process_time() - c0
            jit = _jit_kernels(dr.kernel_history())
            res[name] = dict(first_s=first, first_cpu_s=first_cpu, out=out, wall=[], cpu=[], kern=[], kernels=0,
                             jit_s=sum(k.get("codegen_time", 0) + k.get("backend_time", 0) for k in jit) / 1e3,
                             compiled=sum(1 for k in jit if not k.get("cache_hit")),
                             from_disk=sum(1 for k in jit if k.get("cache_disk")))
            for _ in range(max(warmup - 1, 0)):
                sync(fn())
        for _ in range(repeats):
            for name, fn in fns.items():
                dr.kernel_history()
                c0, t0 = time.process_time(), time.perf_counter()
                out = fn()
                sync(out)
                w, c = time.perf_counter() - t0, time.process_time() - c0
                jit = _jit_kernels(dr.kernel_history())
                r = res[name]
                r["wall"].append(w)
                r["cpu"].append(c)
                r["kern"].append(sum(k.get("execution_time", 0) for k in jit) / 1e3)
                r["kernels"] = len(jit)
                r["out"] = out
    finally:
        dr.kernel_history()
        dr.set_flag(dr.JitFlag.KernelHistory, flag)
    for r in res.values():
        r["wall_s"] = statistics.median(r.pop("wall")) if repeats else r["first_s"]
        r["cpu_s"] = statistics.median(r.pop("cpu")) if repeats else r["first_cpu_s"]
        r["kernel_s"] = statistics.median(r.pop("kern")) if repeats else float("nan")
    return res


def timed(fn: Callable[[], Any], repeats: int = 5, warmup: int = 1) -> tuple[float, float, Any]:
    """(median wall seconds after warm-up, first-call seconds incl. JIT compile, last
    result) of :func:`measure` for one callable."""
    r = measure({"fn": fn}, repeats, warmup)["fn"]
    return r["wall_s"], r["first_s"], r["out"]


# ================================================================== memory meter
def _status_kb() -> dict:
    """``VmRSS`` / ``VmHWM`` of this process in KiB (Linux; empty elsewhere)."""
    out = {}
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(("VmRSS:", "VmHWM:")):
                    key, val = line.split(":")
                    out[key] = int(val.split()[0])
    except OSError:
        pass
    return out


def _jit_backend():
    from .. import backend
    return dr.JitBackend.CUDA if backend.get_backend() == "cuda" else dr.JitBackend.LLVM


class Meter:
    """Time and peak memory of a block, for the active backend::

        with Meter() as m:
            out = fn(); dr.eval(out)
        m.seconds, m.cpu_seconds, m.heap_bytes, m.rss_bytes

    On entry: garbage collected, device synchronised, Dr.Jit's allocation cache freed and
    its statistics reset.  On exit (after ``dr.sync_thread``): ``heap_bytes`` = growth of
    Dr.Jit's allocator watermark (``dr.detail.malloc_watermark`` of the active backend:
    host buffers on LLVM, device memory on CUDA); ``rss_bytes`` = growth of the process's
    peak resident set above its size at entry (Linux ``VmHWM`` reset through
    ``/proc/self/clear_refs``; NaN where that is unavailable; includes NumPy, temporaries
    and kernel stacks).  Evaluate the block's results inside it."""

    def __enter__(self):
        gc.collect()
        dr.sync_thread()
        dr.flush_malloc_cache()
        dr.detail.malloc_clear_statistics()
        self._backend = _jit_backend()
        self._heap0 = dr.detail.malloc_watermark(self._backend)
        try:
            with open("/proc/self/clear_refs", "w") as fh:
                fh.write("5")                     # reset VmHWM to the current RSS
            self._rss0 = _status_kb().get("VmRSS")
        except OSError:
            self._rss0 = None
        self._c0, self._t0 = time.process_time(), time.perf_counter()
        return self

    def __exit__(self, *exc):
        dr.sync_thread()
        self.seconds = time.perf_counter() - self._t0
        self.cpu_seconds = time.process_time() - self._c0
        self.heap_bytes = float(dr.detail.malloc_watermark(self._backend) - self._heap0)
        hwm = _status_kb().get("VmHWM")
        self.rss_bytes = float((hwm - self._rss0) * 1024) if self._rss0 is not None and hwm is not None \
            else float("nan")
        return False

    @property
    def heap_mb(self) -> float:
        """``heap_bytes`` in MB (1e6 bytes)."""
        return self.heap_bytes / 1e6

    @property
    def rss_mb(self) -> float:
        """``rss_bytes`` in MB (1e6 bytes)."""
        return self.rss_bytes / 1e6

    @property
    def peak_bytes(self) -> float:
        """The larger of the two measures (they overlap: Dr.Jit's host buffers are in RSS)."""
        return max(self.heap_bytes, self.rss_bytes) if self.rss_bytes == self.rss_bytes else self.heap_bytes

"""Shared plumbing for experiments: the output folder and its cache, CSV/JSON writers, the
timer (:func:`measure`, :func:`timed`, re-exported from :mod:`avsm_dr.evaluation.timing`)
and the memory meter (:class:`Meter`).

Cache: an experiment reuses ``<out>/data.csv`` when ``meta.json`` there records the same
parameters *and* the same :func:`cache_key` (hash of the package source, Dr.Jit / Mitsuba /
NumPy versions, backend), so results never survive a code or version change, and when every
file meta records still has its SHA-256 (and tables their row count).  Every file is written
atomically (a temporary file, then ``os.replace``) and meta.json last.
"""
from __future__ import annotations

import csv
import functools
import gc
import hashlib
import json
import os
import platform
import subprocess
import time
from pathlib import Path
from typing import Any, Iterable

import avsm_dr
import drjit as dr
import numpy as np

#: The installed package's folder (``avsm_dr/``) and the studies' folder (``experiments/``):
#: their ``*.py`` files make the source hash.
PACKAGE_DIR = Path(avsm_dr.__file__).resolve().parent
STUDIES_DIR = Path(__file__).resolve().parent


# =============================================================== reproducibility
@functools.lru_cache(maxsize=None)
def source_hash() -> str:
    """SHA-256 (hex, first 16 digits) of every ``avsm_dr/**/*.py`` and ``experiments/**/*.py``
    file, names and contents, computed once per process (the code that runs is the code
    imported at start-up)."""
    h = hashlib.sha256()
    for root in (PACKAGE_DIR, STUDIES_DIR):
        for path in sorted(root.rglob("*.py")):
            h.update(f"{root.name}/{path.relative_to(root).as_posix()}".encode())
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
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=STUDIES_DIR, capture_output=True, text=True,
                             timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    sha = out.stdout.strip()
    return sha if out.returncode == 0 and sha else None


def git_dirty() -> bool | None:
    """Whether tracked files of the checkout differ from ``HEAD`` (``git status --porcelain
    --untracked-files=no``), or None where :func:`git_commit` is None."""
    try:
        out = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=STUDIES_DIR,
                             capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None
    return bool(out.stdout.strip()) if out.returncode == 0 else None


def cache_key() -> dict:
    """What, besides the parameters, must match for cached results to be reused:
    source hash, library versions and the Dr.Jit backend."""
    from avsm_dr import backend
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
        other = self.meta().get("experiment")
        if other not in (None, name):
            raise ValueError(f"out: {str(self.dir)!r} holds the results of experiment {other!r}; "
                             f"give {name!r} its own folder")
        self.quick = quick
        #: recompute requested (``force``; set by :meth:`Study.run <experiments._study.Study.run>`)
        self.force = False
        self.params = dict(params, quick=quick)
        self.figures: list[str] = []
        #: file name -> {"sha256", "bytes"[, "rows"]} of what this run wrote (recorded in meta.json)
        self.files: dict[str, dict] = {}
        # the code this run starts with (a commit taken when meta.json is written, minutes or hours
        # later, could name code the run never executed)
        self._started = time.perf_counter()
        self._provenance = {"cache_key": cache_key(), "git_commit": git_commit(), "git_dirty": git_dirty()}

    def meta(self) -> dict:
        """The folder's ``meta.json`` as a dict (empty when missing or unreadable)."""
        try:
            meta = json.loads((self.dir / "meta.json").read_text())
        except (OSError, ValueError):
            return {}
        return meta if isinstance(meta, dict) else {}

    def exists(self, csv_name: str = "data.csv") -> bool:
        """True when ``csv_name`` and a ``meta.json`` with the same parameters and the same
        :func:`cache_key` are there, and every file that meta records (``csv_name`` among
        them) still has its recorded SHA-256 and, for tables, row count: a table left
        truncated or replaced by an interrupted run is never reused."""
        if not (self.dir / csv_name).exists():
            return False
        meta = self.meta()
        same = json.loads(json.dumps(self.params, default=str))
        if not (meta and meta.get("params") == same and meta.get("cache_key") == self._provenance["cache_key"]):
            return False
        files = meta.get("files")
        if not isinstance(files, dict) or csv_name not in files:
            return False
        return all(self._intact(name, rec) for name, rec in files.items())

    def _intact(self, name, rec) -> bool:
        """``name`` (a plain file name in this folder) matches its meta record."""
        if not (isinstance(name, str) and isinstance(rec, dict) and Path(name).name == name):
            return False
        path = self.dir / name
        try:
            if path.stat().st_size != rec.get("bytes") or file_sha256(path) != rec.get("sha256"):
                return False
            return "rows" not in rec or len(read_csv(path)) == rec["rows"]
        except (OSError, ValueError, csv.Error):
            return False

    def cached(self, force: bool = False, csv_name: str = "data.csv") -> dict | None:
        """The result of an earlier identical run (``{'csv', 'out', 'cached': True}``), or
        None when the experiment must run (``force``, or nothing reusable)."""
        if force or not self.exists(csv_name):
            return None
        return {"csv": str(self.dir / csv_name), "out": str(self.dir), "cached": True}

    def write_csv(self, rows: Iterable[dict], csv_name: str = "data.csv") -> Path:
        """Rows (dicts; columns in order of first appearance) as ``csv_name``."""
        rows = list(rows)
        fields: list[str] = []
        for r in rows:
            for k in r:
                if k not in fields:
                    fields.append(k)
        def write(tmp):
            with tmp.open("w", newline="") as fh:
                w = csv.DictWriter(fh, fieldnames=fields)
                w.writeheader()
                for r in rows:
                    w.writerow({k: _fmt(v) for k, v in r.items()})
        return self.write_file(csv_name, write, rows=len(rows))

    def write_file(self, filename: str, write, **extra) -> Path:
        """Write ``filename`` atomically (``write(tmp)``, then ``os.replace``) and record its
        checksum for meta.json."""
        path = self.dir / filename
        atomic_write(path, write)
        self.record(filename, **extra)
        return path

    def record(self, filename: str, **extra) -> None:
        """Record the SHA-256 and size of ``filename`` (written by this run) for meta.json."""
        path = self.dir / filename
        self.files[filename] = {"sha256": file_sha256(path), "bytes": path.stat().st_size, **extra}

    def write_text(self, filename: str, text: str) -> Path:
        """``text`` as ``filename`` (atomic, recorded)."""
        return self.write_file(filename, lambda tmp: tmp.write_text(text))

    def write_json(self, filename: str, obj, **dumps) -> Path:
        """``json.dumps(obj, **dumps)`` as ``filename`` (atomic, recorded)."""
        return self.write_text(filename, json.dumps(obj, **dumps))

    def write_npz(self, filename: str, compressed: bool = True, **arrays) -> Path:
        """NumPy arrays as ``filename`` (``np.savez[_compressed]``; atomic, recorded)."""
        save = np.savez_compressed if compressed else np.savez

        def write(tmp):
            with tmp.open("wb") as fh:            # a file object: NumPy adds no second suffix
                save(fh, **arrays)
        return self.write_file(filename, write)

    def save_figure(self, fig, filename: str) -> Path:
        """Save a Matplotlib figure as ``filename`` (a ``.png``) and, for print, as the vector
        PDF beside it (``experiments._plotstyle.render``: fixed metadata; atomic, both recorded),
        then close it."""
        from . import _plotstyle as plotstyle
        if Path(filename).suffix != ".png":
            raise ValueError(f"filename: expected a .png name (a .pdf is written beside it), got {filename!r}")
        path = self.write_file(filename, lambda tmp: plotstyle.render(fig, tmp, "png"))
        self.write_file(str(Path(filename).with_suffix(".pdf")), lambda tmp: plotstyle.render(fig, tmp, "pdf"))
        import matplotlib.pyplot as plt
        plt.close(fig)
        self.figures.append(str(path))
        return path

    def write_meta(self, summary: dict | None = None) -> Path:
        """``meta.json``: parameters, summary, figures, the files this run wrote (SHA-256,
        bytes, rows of tables), cache key, git commit and whether tracked files differed from it
        (``git_dirty``), all three as at the start of the run, its wall seconds (``run_seconds``),
        versions, backend and machine.  Written last, atomically: it is what makes the folder a
        cached result."""
        from avsm_dr import backend
        meta = {
            "experiment": self.name,
            "params": self.params,
            "summary": summary or {},
            "figures": [Path(f).name for f in self.figures],
            "files": self.files,
            **self._provenance,
            "run_seconds": round(time.perf_counter() - self._started, 1),
            **versions(),
            "backend": backend.get_backend(),
            "machine": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "cpus": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        }
        path = self.dir / "meta.json"
        text = json.dumps(meta, indent=2, default=str)
        atomic_write(path, lambda tmp: tmp.write_text(text))
        return path


def atomic_write(path: Path, write) -> None:
    """``write(tmp)`` to a temporary file beside ``path`` (same suffix), then ``os.replace``:
    readers see the old file or the whole new one, never a part (removed on failure)."""
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def run_text(run_dir: str | Path, name: str) -> str:
    """The text of ``run_dir/name``, or of ``run_dir/name.gz`` where only that exists (a
    committed run keeps its tables gzipped)."""
    import gzip
    plain, packed = Path(run_dir) / name, Path(run_dir) / (name + ".gz")
    if not plain.exists() and packed.exists():
        return gzip.decompress(packed.read_bytes()).decode()
    return plain.read_text()


def file_sha256(path: str | Path) -> str:
    """SHA-256 (hex) of a file's bytes."""
    h = hashlib.sha256()
    with Path(path).open("rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _fmt(v):
    if isinstance(v, float):
        return f"{v:.9g}"
    return v


# ================================================================ timing, memory
# The timer lives in the public harness; re-exported for the studies.
from avsm_dr.evaluation.timing import measure, sync, timed  # noqa: E402,F401
from avsm_dr.evaluation.table import read_csv  # noqa: E402,F401


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
    from avsm_dr import backend
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


def front_to_back_first(orders, allowed) -> list[str]:
    """The insertion orders of a study's ``--orders``: each checked against ``allowed``
    (ValueError naming ``orders``), duplicates dropped, ``'depth'`` (the headline's, front to
    back) always first."""
    orders = list(orders or ["depth"])
    bad = [o for o in orders if o not in allowed]
    if bad:
        raise ValueError(f"orders: unknown insertion order {bad[0]!r}; expected some of {list(allowed)}")
    return ["depth"] + [o for o in dict.fromkeys(orders) if o != "depth"]


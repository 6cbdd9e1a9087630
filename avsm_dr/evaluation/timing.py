"""Timing and memory of device work, for the active backend: :func:`measure` / :func:`timed`
(wall, CPU and Dr.Jit kernel time after warm-up, JIT compile time apart) and :class:`Meter`
(time and peak memory of a block).  Every timed call is followed by :func:`sync`, since Dr.Jit
arrays are lazy: a bare wall clock around them times the tracing, not the work."""
from __future__ import annotations

import gc
import statistics
import time
from typing import Any, Callable

import drjit as dr


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


def jit_kernels(history) -> list:
    """The JIT kernel launches of a ``dr.kernel_history()`` list."""
    return [k for k in history if k["type"] == dr.KernelType.JIT]


def _run(fn):
    """(result, wall seconds, CPU seconds, JIT launches) of one synced call of ``fn``."""
    dr.kernel_history()                                           # clear
    c0, t0 = time.process_time(), time.perf_counter()
    out = fn()
    sync(out)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return out, wall, cpu, jit_kernels(dr.kernel_history())


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
            out, first, first_cpu, jit = _run(fn)
            res[name] = dict(first_s=first, first_cpu_s=first_cpu, out=out, wall=[], cpu=[], kern=[], kernels=0,
                             jit_s=sum(k.get("codegen_time", 0) + k.get("backend_time", 0) for k in jit) / 1e3,
                             compiled=sum(1 for k in jit if not k.get("cache_hit")),
                             from_disk=sum(1 for k in jit if k.get("cache_disk")))
            for _ in range(max(warmup - 1, 0)):
                sync(fn())
        for _ in range(repeats):
            for name, fn in fns.items():
                out, w, c, jit = _run(fn)
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

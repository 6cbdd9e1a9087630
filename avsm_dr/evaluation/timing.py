"""Timing of device work, for the active backend: :func:`measure` / :func:`timed` (wall, CPU
and Dr.Jit kernel time after warm-up, JIT compile time apart).  Every timed call is followed
by :func:`sync`, since Dr.Jit arrays are lazy: a bare wall clock around them times the
tracing, not the work."""
from __future__ import annotations

import contextlib
import statistics
import time
from typing import Any, Callable

import drjit as dr


def sync(out=None):
    """Evaluate ``out`` (if it holds Dr.Jit arrays) and wait for the active backend's
    queued kernels (``dr.sync_thread``: CPU worker threads or the CUDA stream)."""
    if out is not None:
        with contextlib.suppress(Exception):     # not a Dr.Jit PyTree (NumPy, plain objects)
            dr.eval(out)
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


def measure(fns: dict, repeats: int = 3) -> dict:
    """Time each callable in ``fns`` (name -> fn): a first call (the warm-up, JIT compile
    included), then ``repeats`` rounds run interleaved across ``fns`` (so load from other
    processes hits each alike).  Every call is followed by :func:`sync`.

    Returns name -> dict(wall_s, cpu_s (process CPU time, all threads), kernel_s (Dr.Jit
    kernel execution from ``dr.kernel_history``), first_s, first_cpu_s, jit_s (codegen +
    backend compile of the first call), compiled, from_disk, kernels (JIT launches per
    call), out (last result)); medians over the repeats (``repeats=0``: the first call)."""
    res = {}
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        for name, fn in fns.items():
            out, first, first_cpu, jit = _run(fn)
            res[name] = dict(first_s=first, first_cpu_s=first_cpu, out=out, wall=[], cpu=[], kern=[], kernels=0,
                             jit_s=sum(k.get("codegen_time", 0) + k.get("backend_time", 0) for k in jit) / 1e3,
                             compiled=sum(1 for k in jit if not k.get("cache_hit")),
                             from_disk=sum(1 for k in jit if k.get("cache_disk")))
        for _ in range(repeats):
            for name, fn in fns.items():
                out, w, c, jit = _run(fn)
                r = res[name]
                r["wall"].append(w)
                r["cpu"].append(c)
                r["kern"].append(sum(k.get("execution_time", 0) for k in jit) / 1e3)
                r["kernels"] = len(jit)
                r["out"] = out
        dr.kernel_history()                                        # cleared for the next reader
    for r in res.values():
        r["wall_s"] = statistics.median(r.pop("wall")) if repeats else r["first_s"]
        r["cpu_s"] = statistics.median(r.pop("cpu")) if repeats else r["first_cpu_s"]
        r["kernel_s"] = statistics.median(r.pop("kern")) if repeats else float("nan")
    return res


def timed(fn: Callable[[], Any], repeats: int = 5) -> tuple[float, float, Any]:
    """(median wall seconds after warm-up, first-call seconds incl. JIT compile, last
    result) of :func:`measure` for one callable."""
    r = measure({"fn": fn}, repeats)["fn"]
    return r["wall_s"], r["first_s"], r["out"]

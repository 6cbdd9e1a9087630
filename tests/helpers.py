"""Helpers of the test suite (not part of the package): the kernel-reuse counter, the
in-process quick run of a study, the Monte Carlo agreement check and a basis kind's
reconstructed optical depth."""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import avsm_dr  # noqa: F401  (selects a working libLLVM before drjit loads)
import drjit as dr
import numpy as np
from avsm_dr import _arrays as A



def compiled_kernels(fn: Callable, *, disk_hits_are_new: bool = True) -> int:
    """Number of JIT kernels new to this process (not in Dr.Jit's in-memory kernel cache)
    while ``fn()`` runs and its result is evaluated: the check that a second call with new
    sizes or data reuses the kernels of the first (a literal size or a misaligned mapped
    input in the kernel hash recompiles).  ``disk_hits_are_new`` (default): a kernel loaded
    from Dr.Jit's disk cache (``~/.drjit``) counts as new, since on a machine whose disk
    cache lacks it (a fresh one) it is compiled: otherwise the count depends on what earlier
    runs left on disk (a test passed after any run that had compiled the kernel, and failed
    on a fresh machine).  Warm up by evaluating ``fn()`` once, as this count does."""
    dr.kernel_history_clear()
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.eval(fn())
        dr.sync_thread()
        hist = dr.kernel_history()
    return sum(1 for k in hist if k["type"] == dr.KernelType.JIT
               and (not k["cache_hit"] or (disk_hits_are_new and k.get("cache_disk", False))))


def quick_cli_run(name: str, out) -> Path:
    """``python -m experiments NAME --quick --out OUT`` in this process, as a user runs it: checks
    that the CLI discovers the experiment and exits 0; returns its result folder ``OUT/NAME``."""
    from experiments import _cli as cli
    assert name in cli.experiment_names(), name
    assert cli.main([name, "--quick", "--out", str(out)]) == 0, name
    return Path(out) / name


def build_peak(kind: str, arrays: Callable, **params):
    """(rep, peak bytes, output bytes) of ``build(kind, ...)`` on the benchmark's memory map
    at its quick size (64^2 texels, ~0.4 M segments): peak = the larger of process RSS growth
    and Dr.Jit's allocator watermark growth (``Meter``), compiled outside the measurement;
    ``arrays(rep)`` lists the representation's arrays to evaluate inside it."""
    from experiments._common import Meter
    from experiments.bench.settings import counts_map
    seg = counts_map(64, 100)
    dr.eval(seg.z0, seg.z1, seg.optical_depth)
    avsm_dr.build(kind, counts_map(4, 100), **params)          # compile outside the measurement
    with Meter() as m:
        rep = avsm_dr.build(kind, seg, **params)
        dr.eval(*arrays(rep))
    return rep, m, rep.nbytes_per_texel * seg.n_texels


def optical_depth(rep, texel, depth):
    """A basis kind's reconstructed optical depth D = sum_k a_k g_k(u) (before exp and clamp)
    at (K,) texel indices (not validated) and (K,) or scalar depths: Float (K,)."""
    tex = texel if A.is_drjit(texel) else A.to_uint32(np.asarray(texel).astype(np.uint32))
    if A.is_drjit(depth):
        d = A.to_float(depth, rep.Float)
    else:
        d = A.to_float(np.broadcast_to(np.asarray(depth, np.float64), (dr.width(tex),)), rep.Float)
    return rep._optical_depth(tex, d)

"""Helpers of the test suite (not part of the package): the kernel-reuse counter, the
in-process quick run of a study and the Monte Carlo agreement check."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import avsm_dr  # noqa: F401  (selects a working libLLVM before drjit loads)
import drjit as dr
import numpy as np

from avsm_dr import validation as V


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


@dataclass
class MCAgreement:
    """Result of :func:`mc_agreement`: the statistics and which checks failed."""
    n: int
    fraction_within: float      #: share of elements with |e| <= k SE + floor
    z: float                    #: sum(e) / sqrt(sum SE^2) (0 when every SE is 0 or inf)
    rms_ratio: float            #: sqrt(mean e^2 / mean SE^2) (inf when every SE is 0)
    rel_mean: float             #: mean of |e| / max(|ref|, rel_floor)
    rel_max: float              #: max of |e| / max(|ref|, rel_floor)
    worst: float                #: max |e| / (k SE + floor) (> 1: outside the band)
    failures: list = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True when every requested check passed."""
        return not self.failures

    def __str__(self) -> str:
        state = "ok" if self.ok else "FAILED: " + "; ".join(self.failures)
        return (f"MC agreement {state} (n={self.n}, within={self.fraction_within:.4f}, z={self.z:.3g}, "
                f"rms_ratio={self.rms_ratio:.3g}, rel_mean={self.rel_mean:.3g}, rel_max={self.rel_max:.3g}, "
                f"worst={self.worst:.3g})")


def mc_agreement(estimate, reference, stderr, *, k: float = 3.0, min_fraction: float = 0.98,
                 max_z: float = 4.0, floor: float = 0.0, max_rms_ratio: float | None = None,
                 rel_floor: float = 1e-2, mean_rtol: float | None = None,
                 max_rtol: float | None = None) -> MCAgreement:
    """Agreement of ``estimate`` (any shape) with ``reference`` given the estimate's
    standard errors ``stderr`` (same shape, or a scalar: one noise level for all).

    Checks (``e = estimate - reference``, ``n`` elements):

    * per element ``|e| <= k * SE + floor`` for at least ``min_fraction`` of them.
      Default 3 SE and 98 %: ratio-tracking weights are skewed, so even an exact
      estimator leaves a few in a thousand outside 3 SE (measured 0.25-0.65 %);
    * bias: ``|sum e| <= max_z * sqrt(sum SE^2) + n * floor`` (``Z`` standard normal
      for an unbiased estimator; ``floor`` a deterministic error allowed per element,
      e.g. the float32 rounding of the reference);
    * ``max_rms_ratio``: ``sqrt(mean e^2 / mean SE^2) <= max_rms_ratio`` (~1 when the SE is
      honest; a deterministic mismatch of ``d`` SE raises it to ``sqrt(1 + d^2)``);
    * ``mean_rtol`` / ``max_rtol``: mean / max of ``|e| / max(|reference|, rel_floor)``.

    Optional checks are skipped when None.  Returns an :class:`MCAgreement`.
    """
    est = V.array(estimate, "estimate")
    ref = V.array(reference, "reference")
    if est.shape != ref.shape or est.size == 0:
        raise ValueError(f"reference: expected the estimate's shape {est.shape} (non-empty), got {ref.shape}")
    se = np.asarray(V.array(stderr, "stderr", finite=False), np.float64)
    if np.any(np.isnan(se)) or np.any(se < 0):
        raise ValueError("stderr: expected standard errors >= 0 (inf allowed), got NaN or negative values")
    try:
        se = np.broadcast_to(se, est.shape)
    except ValueError:
        raise ValueError(f"stderr: expected a scalar or shape {est.shape}, got {se.shape}") from None
    limits = (("k", k, None, True), ("min_fraction", min_fraction, 1, False), ("max_z", max_z, None, True),
              ("floor", floor, None, False), ("rel_floor", rel_floor, None, True))     # (name, value, max, > 0)
    k, min_fraction, max_z, floor, rel_floor = (V.real(v, name, 0, hi, open_min=o) for name, v, hi, o in limits)
    for name, val in (("max_rms_ratio", max_rms_ratio), ("mean_rtol", mean_rtol), ("max_rtol", max_rtol)):
        if val is not None:
            V.real(val, name, 0, open_min=True)

    e = (est - ref).ravel()
    se = se.ravel()
    n = e.size
    band = k * se + floor
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(band > 0, np.abs(e) / band, np.where(e == 0, 0.0, np.inf))
    within = float(np.mean(np.abs(e) <= band))
    finite = np.isfinite(se)
    var = float(np.sum(se[finite] ** 2))
    # elements with an infinite SE (e.g. one sample) carry no information about the bias
    bias_sum = float(np.sum(e[finite]))
    z = bias_sum / math.sqrt(var) if var > 0 else 0.0
    mse_se = float(np.mean(se ** 2))
    rms_ratio = math.sqrt(float(np.mean(e * e)) / mse_se) if mse_se > 0 else math.inf
    rel = np.abs(e) / np.maximum(np.abs(ref.ravel()), rel_floor)
    out = MCAgreement(n, within, z, rms_ratio, float(rel.mean()), float(rel.max()), float(ratio.max()))

    if within < min_fraction:
        out.failures.append(f"{within:.4f} of elements within {k:g} SE + {floor:g}, need {min_fraction:g}")
    if abs(bias_sum) > max_z * math.sqrt(var) + int(finite.sum()) * floor:
        out.failures.append(f"bias: |Z| = {abs(z):.3g} > {max_z:g}" + (f" (+ floor {floor:g})" if floor else ""))
    if max_rms_ratio is not None and not rms_ratio <= max_rms_ratio:
        out.failures.append(f"RMS error / RMS SE = {rms_ratio:.3g} > {max_rms_ratio:g}")
    if mean_rtol is not None and out.rel_mean > mean_rtol:
        out.failures.append(f"mean relative error {out.rel_mean:.3g} > {mean_rtol:g}")
    if max_rtol is not None and out.rel_max > max_rtol:
        out.failures.append(f"max relative error {out.rel_max:.3g} > {max_rtol:g}")
    return out

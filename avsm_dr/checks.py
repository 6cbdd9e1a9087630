"""The library's checks, for tests and for package code: gradients and Monte Carlo agreement.

:func:`check_gradients`: a reverse-mode gradient against central finite differences and
against forward mode along a random direction (forward mode needs no loop-bound hint, so a
symbolic loop whose ``max_iterations`` is too small, silently wrong in reverse mode only,
shows up).  It returns a report (``.ok``, ``.failures``, the numbers) instead of asserting,
so tests write ``assert r.ok, r`` and package code (e.g.
:func:`avsm_dr.reconstruction.gradient_check`) can act on it.  :func:`mc_agreement`: a Monte
Carlo estimate against a reference given its standard errors (per-element band, bias Z,
RMS ratio), reported the same way.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import drjit as dr
import numpy as np

from . import validation as V


@dataclass
class GradientCheck:
    """Result of :func:`check_gradients`.

    ``gradient``: reverse-mode dL/dx (float64, shape of x); ``indices``: the coordinates
    finite-differenced (tuples), ``fd`` their central differences, ``skipped`` how many
    were rejected by ``accept``; ``reverse`` = gradient . v and ``forward`` = forward-mode
    dL/dx . v along the random direction v (NaN when not run)."""
    gradient: np.ndarray
    indices: list = field(default_factory=list)
    fd: np.ndarray = field(default_factory=lambda: np.zeros(0))
    skipped: int = 0
    reverse: float = math.nan
    forward: float = math.nan
    failures: list = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True when every requested check passed."""
        return not self.failures

    @property
    def fd_error(self) -> float:
        """Largest |reverse - finite difference| over the checked coordinates (0 if none)."""
        if not self.indices:
            return 0.0
        g = np.array([self.gradient[i] for i in self.indices])
        return float(np.abs(g - self.fd).max())

    def summary(self) -> dict:
        """JSON-friendly numbers: reverse, forward, error (|reverse - forward|), fd_checked,
        fd_max_error, ok."""
        return {"reverse": self.reverse, "forward": self.forward, "error": abs(self.reverse - self.forward),
                "fd_checked": len(self.indices), "fd_max_error": self.fd_error, "ok": self.ok}

    def __str__(self) -> str:
        state = "ok" if self.ok else "FAILED: " + "; ".join(self.failures)
        return (f"gradient check {state} (reverse.v={self.reverse:.10g}, forward.v={self.forward:.10g}, "
                f"fd checked={len(self.indices)}, skipped={self.skipped}, fd max error={self.fd_error:.3g})")


def _scalar(value) -> float:
    """A width-1 Dr.Jit array (or a Python number) as a float."""
    return float(np.asarray(dr.detach(value) if dr.is_array_v(value) else value, np.float64).ravel()[0])


def check_gradients(loss: Callable, x, *, fd: int | Sequence[int] = 8, eps: float = 1e-6,
                    fd_rtol: float = 1e-6, fd_atol: float = 1e-7, forward: bool = True,
                    rtol: float = 1e-9, atol: float = 1e-12, primal: Callable | None = None,
                    accept: Callable | None = None, rng: np.random.Generator | None = None) -> GradientCheck:
    """Check the gradient of ``loss(x)`` (a width-1 Dr.Jit array) at ``x`` (a Dr.Jit
    float array or tensor; the checker differentiates fresh copies of it).

    fd: number of coordinates to finite-difference (half of them the largest |dL/dx|,
    the others random) or a sequence of flat indices; 0: none.  Central differences
    ``(f(x + eps e_i) - f(x - eps e_i)) / (2 eps)`` of ``primal`` (a function of a
    NumPy array of x's shape returning a float; default ``loss`` itself) must satisfy
    ``|g_i - fd_i| <= fd_atol + fd_rtol |fd_i|`` (defaults for float64: truncation
    ``O(eps^2 f''')`` and cancellation ``~1e-16 |f| / eps`` stay far below).
    accept(x_plus, x_minus) -> bool: False skips a coordinate whose difference straddles a
    non-differentiable point (e.g. a change of AVSM's node layout); at least 3/4 of the
    coordinates (all without ``accept``) must remain.  forward: also compare ``g . v`` with
    forward mode's ``dL/dx . v``, ``|rev - fwd| <= atol + rtol max(|rev|, |fwd|)`` (same
    arithmetic in another order)."""
    rng = np.random.default_rng(0) if rng is None else rng
    eps = V.real(eps, "eps", 0, open_min=True)
    for name, val in (("fd_rtol", fd_rtol), ("fd_atol", fd_atol), ("rtol", rtol), ("atol", atol)):
        V.real(val, name, 0)
    if not dr.is_array_v(x) or not dr.is_float_v(x):
        raise ValueError(f"x: expected a Dr.Jit float array or tensor, got {type(x).__name__}")
    Type = type(x)
    host = np.array(dr.detach(x).numpy())

    def fresh(arr, grad):
        y = Type(np.asarray(arr, host.dtype))
        if grad:
            dr.enable_grad(y)
        return y

    xr = fresh(host, True)
    dr.backward(loss(xr))
    g = np.array(dr.grad(xr).numpy(), np.float64).reshape(host.shape)
    out = GradientCheck(g)
    if not np.all(np.isfinite(g)):
        out.failures.append("reverse-mode gradient is not finite")

    # ---- central finite differences
    if isinstance(fd, (int, np.integer)) and not isinstance(fd, bool):
        n = min(int(fd), host.size)
        if n < 0:
            raise ValueError(f"fd: expected a count >= 0 or a sequence of indices, got {fd!r}")
        order = np.argsort(-np.abs(g).ravel(), kind="stable")
        top, rest = np.split(order, [(n + 1) // 2])
        pick = np.concatenate([top, rng.choice(rest, n - top.size, replace=False)]).astype(np.int64)
    else:
        pick = np.asarray(fd, np.int64).ravel()
        if np.any(pick < 0) or np.any(pick >= host.size):
            raise ValueError(f"fd: indices must lie in [0, {host.size}), got {fd!r}")
    f = primal if primal is not None else (lambda arr: _scalar(loss(fresh(arr, False))))
    fds = []
    for j in pick:
        idx = np.unravel_index(int(j), host.shape)
        xp, xm = host.astype(np.float64), host.astype(np.float64)
        xp[idx] += eps
        xm[idx] -= eps
        if accept is not None and not accept(xp, xm):
            out.skipped += 1
            continue
        d = (f(xp) - f(xm)) / (2 * eps)
        out.indices.append(idx)
        fds.append(d)
        if not abs(g[idx] - d) <= fd_atol + fd_rtol * abs(d):
            out.failures.append(f"finite difference at {tuple(map(int, idx))}: reverse {g[idx]:.10g} vs fd {d:.10g}")
    out.fd = np.array(fds, np.float64)
    need = pick.size if accept is None else (3 * pick.size + 3) // 4
    if len(out.indices) < need:
        out.failures.append(f"only {len(out.indices)} coordinates finite-differenced ({out.skipped} skipped), "
                            f"need {need}")

    # ---- reverse vs forward mode along a random direction
    if forward:
        v = rng.normal(size=host.shape)
        xf = fresh(host, True)
        L = loss(xf)
        dr.set_grad(xf, Type(v.astype(host.dtype)))
        dr.forward_to(L)
        out.forward = _scalar(dr.grad(L))
        out.reverse = float(np.sum(g * v))
        err = abs(out.reverse - out.forward)
        if not err <= atol + rtol * max(abs(out.reverse), abs(out.forward)):
            out.failures.append(f"reverse . v = {out.reverse:.10g} vs forward mode {out.forward:.10g} "
                                f"(|diff| {err:.3g})")
    return out


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

    Optional checks are skipped when None.  Returns an :class:`MCAgreement`."""
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

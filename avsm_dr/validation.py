"""Argument checks shared by the public entry points: one rule for numbers, vectors, points.

Every check raises ``ValueError("<name>: expected ..., got ...")`` naming the argument
(DESIGN.md habit 6); kernels behind the boundary trust their input.

The rule (the same as the representations' parameter schema):

* a *real number* is a Python or NumPy real scalar (``numbers.Real``: ``int``,
  ``float``, ``np.float32``, ``np.int64``, ...), never ``bool``, ``str`` or an array
  (``np.array([2.0])`` is refused: say ``2.0``); finite unless stated;
* an *integer* is a Python or NumPy integral scalar (``numbers.Integral``), never ``bool``;
* an *array* is numeric (integer or floating dtype; Dr.Jit arrays are copied to the host),
  never boolean, string or object-typed.
"""
from __future__ import annotations

import contextlib
import difflib
import math
import os
from numbers import Integral, Real
from typing import Any, Callable

import drjit as dr
import numpy as np

from . import _arrays as A


def _is_bool(value) -> bool:
    return isinstance(value, (bool, np.bool_))


def _fmt(v) -> str:
    return str(v) if isinstance(v, Integral) else f"{v:g}"


def _range_text(lo, hi, open_lo: bool, open_hi: bool) -> str:
    if lo is not None and hi is not None:
        return f" in {'(' if open_lo else '['}{_fmt(lo)}, {_fmt(hi)}{')' if open_hi else ']'}"
    if lo is not None:
        return f" {'>' if open_lo else '>='} {_fmt(lo)}"
    if hi is not None:
        return f" {'<' if open_hi else '<='} {_fmt(hi)}"
    return ""


def _in_range(x, lo, hi, open_lo: bool, open_hi: bool) -> bool:
    return ((lo is None or (x > lo if open_lo else x >= lo))
            and (hi is None or (x < hi if open_hi else x <= hi)))


def real(value: Any, name: str, min: float | None = None, max: float | None = None, *,
         open_min: bool = False, open_max: bool = False, finite: bool = True) -> float:
    """``value`` as a Python float after the rule above and the range ``[min, max]``
    (``open_min``/``open_max`` exclude the bound; ``finite=False`` admits +-inf, never NaN)."""
    ok = isinstance(value, Real) and not _is_bool(value)
    x = float(value) if ok else math.nan
    ok = ok and not math.isnan(x) and (not finite or math.isfinite(x)) \
        and _in_range(x, min, max, open_min, open_max)
    if not ok:
        what = "a finite real number" if finite else "a real number (not NaN)"
        raise ValueError(f"{name}: expected {what}{_range_text(min, max, open_min, open_max)}, "
                         f"got {value!r}")
    return x


def integer(value: Any, name: str, min: int | None = None, max: int | None = None) -> int:
    """``value`` as a Python int: an integral scalar (not bool) in ``[min, max]``."""
    if not (isinstance(value, Integral) and not _is_bool(value)
            and _in_range(int(value), min, max, False, False)):
        raise ValueError(f"{name}: expected an integer{_range_text(min, max, False, False)}, "
                         f"got {value!r}")
    return int(value)


def array(value: Any, name: str, dtype=np.float64, finite: bool = True) -> np.ndarray:
    """A NumPy copy of a numeric array (NumPy, nested lists, scalar or Dr.Jit) as ``dtype``;
    boolean, string and object input is refused, and NaN/inf unless ``finite=False``."""
    out = A.host(value, name, dtype, "a numeric array", copy=True)
    if finite and out.size and not np.all(np.isfinite(out)):
        A.check_finite(out if A.is_drjit(value) else np.asarray(value), name)      # NaN / inf given
        raise ValueError(f"{name}: values beyond the {np.dtype(dtype).name} range "
                         f"(largest {np.finfo(dtype).max:.3g})")
    return out


def vec3(value: Any, name: str) -> np.ndarray:
    """(3,) float64 of three finite real numbers."""
    with contextlib.suppress(ValueError):
        a = array(value, name).reshape(-1)
        if a.shape == (3,):
            return a
    raise ValueError(f"{name}: expected 3 finite numbers, got {value!r}")


def unit_vector(value: Any, name: str) -> np.ndarray:
    """(3,) float64 unit vector along three finite numbers, not all zero.

    Normalised after scaling by the largest magnitude, so directions whose norm
    overflows (1e300, 1e300, 0) or underflows (1e-320, 0, 0) still normalise exactly.
    """
    a = vec3(value, name)
    m = float(np.max(np.abs(a)))
    if m == 0:
        raise ValueError(f"{name}: must be non-zero, got {value!r}")
    a = a / m
    return a / np.linalg.norm(a)


def points(value: Any, name: str = "points", allow_empty: bool = False) -> np.ndarray:
    """(K, 3) finite float64 copy of world points; a single (3,) point becomes (1, 3).

    K = 0 is refused unless ``allow_empty``.
    """
    p = array(value, name)
    if p.ndim == 1 and p.size == 3:
        p = p.reshape(1, 3)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (K, 3), got {p.shape}")
    if p.shape[0] == 0 and not allow_empty:
        raise ValueError(f"{name}: no points given (empty array)")
    return p


def did_you_mean(value: Any, known) -> str:
    """``"; did you mean 'x'?"`` naming the closest of ``known`` to a misspelt string
    ``value`` (:func:`difflib.get_close_matches`, cutoff 0.6), else ``""``."""
    if not isinstance(value, str):
        return ""
    close = difflib.get_close_matches(value, [str(k) for k in known], n=1, cutoff=0.6)
    return f"; did you mean {close[0]!r}?" if close else ""


def one_of(value: Any, name: str, choices) -> Any:
    """``value`` when it is one of ``choices`` (compared as strings are: by equality)."""
    if not (isinstance(value, str) and value in choices):
        raise ValueError(f"{name}: expected one of {tuple(choices)}, got {value!r}")
    return value


def _grid_kind(value) -> tuple[str, str]:
    """(NumPy dtype kind, dtype name) of a grid without copying NumPy input."""
    if A.is_drjit(value):
        vt = dr.type_v(value)
        if vt in (dr.VarType.Float16, dr.VarType.Float32, dr.VarType.Float64):
            return "f", str(vt).split(".")[-1].lower()
        return ("b" if vt == dr.VarType.Bool else "i"), str(vt).split(".")[-1].lower()
    dt = value.dtype if isinstance(value, np.ndarray) else np.asarray(value).dtype
    return dt.kind, dt.name


def grid_dtype(value: Any, name: str = "density") -> None:
    """Refuse a density grid that is not floating point (NumPy, nested lists or Dr.Jit).

    A grid holds extinction per world unit; an integer or boolean grid (e.g. uint8 voxels
    0..255) has no unit, so it is refused rather than read as extinction 0..255: convert it
    with an explicit scale.
    """
    try:
        kind, dname = _grid_kind(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: expected a floating-point (z, y, x) array ({exc})") from None
    if kind in "iub":
        how = ("np.where(grid, sigma, 0).astype(np.float32)" if kind == "b" else     # voxel formats: 0..max
               f"grid.astype(np.float32) * (sigma_max / {np.iinfo(dname).max})" if np.dtype(dname).itemsize <= 2
               else "grid.astype(np.float32) * scale")
        raise ValueError(f"{name}: {'boolean' if kind == 'b' else 'integer'} grid (dtype {dname}) refused: a "
                         f"density grid holds extinction per world unit as floating point; convert it "
                         f"with an explicit scale, e.g. {how}")
    if kind != "f":
        raise ValueError(f"{name}: expected a floating-point (z, y, x) array, got dtype {dname}")


def density_grid(value: Any, name: str = "density", dtype=np.float32) -> np.ndarray:
    """(nz, ny, nx) NumPy copy of a density grid (extinction per world unit) as ``dtype``.

    The one rule every entry point taking a grid applies (scenes, capture, ground truth,
    Mitsuba media, the fluid solver): floating-point input (:func:`grid_dtype`: integer and
    boolean grids are refused), 3-D, non-empty, finite in ``dtype``, >= 0.
    """
    grid_dtype(value, name)
    drjit = A.is_drjit(value)
    if drjit and not dr.is_tensor_v(value):
        raise ValueError(f"{name}: a Dr.Jit density must be a 3-D tensor (TensorXf) of shape (z, y, x)")
    raw = A.host(value, name, None) if drjit else np.asarray(value)       # its own dtype
    if raw.ndim != 3:
        raise ValueError(f"{name}: expected a 3-D (z, y, x) array, got shape {raw.shape}")
    if min(raw.shape) < 1:
        raise ValueError(f"{name}: empty grid of shape {raw.shape}")
    out = array(raw, name, dtype)
    lo = float(out.min())
    if lo < 0:
        raise ValueError(f"{name}: negative extinction {lo:g} (densities must be >= 0)")
    return out


class MemoryBudgetError(ValueError):
    """A build refused before allocating: its estimated peak exceeds :func:`memory_budget`."""


class WorkLimitError(ValueError):
    """A build refused before computing: its work estimate ``work`` exceeds the kind's ``limit``
    (``optimal``'s ``MAX_WORK`` or ``MAX_POINTS``); the message says what fits."""

    def __init__(self, message: str, work: float, limit: float):
        super().__init__(message)
        self.work, self.limit = float(work), float(limit)


#: Bytes one build may allocate; None (default): :data:`MEMORY_FRACTION` of the smaller of
#: the physical memory (``os.sysconf``) and the process' address-space limit
#: (``RLIMIT_AS``), a number that depends on the machine, not on its load.
MEMORY_BUDGET_BYTES: int | None = None
#: Share of that memory a build's estimate may take (the rest: the caller's data, the
#: segments, Dr.Jit's caches, the lookups).
MEMORY_FRACTION = 0.75


def memory_budget() -> int:
    """The bytes one build may allocate (:data:`MEMORY_BUDGET_BYTES`, or its default)."""
    if MEMORY_BUDGET_BYTES is not None:
        return int(MEMORY_BUDGET_BYTES)
    total = math.inf
    with contextlib.suppress(AttributeError, ValueError, OSError):      # not POSIX: only the limit below
        total = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    with contextlib.suppress(ImportError, ValueError, OSError):
        import resource
        limit = resource.getrlimit(resource.RLIMIT_AS)[0]
        if limit != resource.RLIM_INFINITY:
            total = min(total, limit)
    return int(MEMORY_FRACTION * total) if math.isfinite(total) else 2**62


def _gib(n: float) -> str:
    return f"{n / 2**30:.3g} GiB"


def check_memory(name: str, value, need: Callable[[Any], float], lo=None, what: str = "",
                 allowed: Callable[[Any], bool] | None = None) -> None:
    """:class:`MemoryBudgetError` (a ValueError) naming ``name`` when ``need(value)`` (estimated peak bytes of a build)
    exceeds :func:`memory_budget`, saying which value fits: the largest in ``[lo, value]``
    (bisection; ``need`` non-decreasing in the value; integers for an integer value, the
    largest one ``allowed`` accepts), or that none does.  ``lo`` None: no value is
    searched (the message asks for less input)."""
    budget, bytes_ = memory_budget(), float(need(value))
    if bytes_ <= budget:
        return
    where = (f"MEMORY_FRACTION = {MEMORY_FRACTION:g} of min(physical memory, RLIMIT_AS)"
             if MEMORY_BUDGET_BYTES is None else "set")
    head = (f"{name}: {value!r}{' ' + what if what else ''} needs ~{_gib(bytes_)} to build (estimate), above "
            f"the {_gib(budget)} budget (avsm_dr.validation.MEMORY_BUDGET_BYTES: {where}); ")
    fit = None
    if lo is not None and float(need(lo)) <= budget:
        a, b = lo, value                                  # need(a) fits, need(b) does not
        integral = isinstance(value, Integral)
        for _ in range(200):
            if (b - a <= 1) if integral else (b - a <= 1e-6 * abs(b)):
                break
            m = (a + b) // 2 if integral else 0.5 * (a + b)
            a, b = (m, b) if float(need(m)) <= budget else (a, m)
        fit = a
        while integral and allowed is not None and fit >= lo and not allowed(fit):
            fit -= 1
        fit = fit if fit >= lo else None
    shown = fit if fit is None or isinstance(fit, Integral) else float(f"{fit:.6g}")
    tail = (f"{name} <= {shown!r} fits" if fit is not None else
            "no value fits: build fewer texels at a time (Segments.select_texels) or raise the budget")
    raise MemoryBudgetError(head + tail)

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

import math
from numbers import Integral, Real
from typing import Any

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
    if lo is not None and (x <= lo if open_lo else x < lo):
        return False
    if hi is not None and (x >= hi if open_hi else x > hi):
        return False
    return True


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
    if A.is_drjit(value):
        out = A.host(value, name, dtype)
    else:
        try:
            raw = np.asarray(value)
        except (TypeError, ValueError) as exc:                # ragged nesting
            raise ValueError(f"{name}: expected a numeric array ({exc})") from None
        if raw.dtype.kind not in "iuf":
            raise ValueError(f"{name}: expected a numeric array, got dtype {raw.dtype}")
        if finite:
            A.check_finite(raw, name)
        with np.errstate(over="ignore", invalid="ignore"):
            out = raw.astype(dtype)
        if finite and out.dtype.kind == "f" and out.size and not np.all(np.isfinite(out)):
            raise ValueError(f"{name}: values beyond the {np.dtype(dtype).name} range "
                             f"(largest {np.finfo(dtype).max:.3g})")
        return out
    if finite:
        A.check_finite(out, name)
    return out


def vec3(value: Any, name: str) -> np.ndarray:
    """(3,) float64 of three finite real numbers."""
    try:
        a = array(value, name).reshape(-1)
    except ValueError:
        a = None
    if a is None or a.shape != (3,):
        raise ValueError(f"{name}: expected 3 finite numbers, got {value!r}")
    return a


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


def one_of(value: Any, name: str, choices) -> Any:
    """``value`` when it is one of ``choices`` (compared as strings are: by equality)."""
    if not (isinstance(value, str) and value in choices):
        raise ValueError(f"{name}: expected one of {tuple(choices)}, got {value!r}")
    return value

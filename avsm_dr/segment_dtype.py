"""Storage-dtype rules of :class:`~avsm_dr.segments.Segments` depths and optical depths
(:mod:`avsm_dr.segments`): finite once stored in float32 / float64 (``ValueError`` naming the
argument otherwise), values below the dtype's smallest normal number set to 0.
"""
from __future__ import annotations

import drjit as dr
import numpy as np

#: Suffix of the overflow ValueError: the way out for each storage dtype.
OVERFLOW_HINT = {"float32": " or use dtype='float64'", "float64": ""}


def check_in_dtype(arr: np.ndarray, name: str, dtype: str) -> np.ndarray:
    """``arr`` (float64 host values, finite) checked to be finite once stored in
    ``dtype``; returns it with subnormal values (in ``dtype``) set to 0."""
    info = np.finfo(dtype)
    with np.errstate(over="ignore"):
        bad = ~np.isfinite(arr.astype(info.dtype))
    if bad.any():
        what = (f"{float(arr[0]):g} overflows" if arr.size == 1 else
                f"{int(np.count_nonzero(bad))} value(s) overflow (e.g. {float(arr[bad][0]):g})")
        raise ValueError(f"{name}: {what} the {dtype} storage (|x| <= {float(info.max):.6g}); "
                         f"rescale the scene{OVERFLOW_HINT[dtype]}")
    return check_tiny(arr, dtype)


def check_tiny(arr: np.ndarray, dtype: str) -> np.ndarray:
    """``arr`` with values below the smallest normal number of ``dtype`` set to 0."""
    tiny = float(np.finfo(dtype).tiny)
    return np.where(np.abs(arr) < tiny, 0.0, arr) if arr.size else arr


def check_span(lo: float, hi: float, dtype: str, name: str, what: str, hint: str = "") -> None:
    """ValueError naming ``name`` when ``hi - lo`` (``what``) overflows the ``dtype`` storage."""
    with np.errstate(over="ignore"):
        span = np.dtype(dtype).type(hi) - np.dtype(dtype).type(lo)
    if not np.isfinite(span):
        raise ValueError(f"{name}: {what} = {hi - lo:.6g} overflows the {dtype} storage{hint}")


def has_subnormal(host_arr: np.ndarray, dtype: str) -> bool:
    """True when ``host_arr`` holds a nonzero value below the smallest normal of ``dtype``."""
    tiny = float(np.finfo(dtype).tiny)
    return bool(host_arr.size and np.any((host_arr != 0) & (np.abs(host_arr) < tiny)))


def flushed(x, dtype: str):
    """Dr.Jit ``x`` with values below the smallest normal number of ``dtype`` set to 0."""
    tiny = float(np.finfo(dtype).tiny)
    return dr.select(dr.abs(x) < tiny, 0.0, x)

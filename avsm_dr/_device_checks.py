"""Lookup arguments validated on the device (Dr.Jit arrays, and NumPy depths once converted).

The host checks' rules (finite, in range) reduce to one flag per argument (``dr.all``, one
readback); :func:`point_lookup` checks inside the lookup's own kernel, and
:func:`host_point_lookup` skips the flag where the extremes of NumPy input prove it valid.
The checks are *sufficient*, not exact: anything they do not accept (including what the
host checks would fix up, such as subnormal depths) returns ``None`` so the caller reruns
the host checks, which raise their usual ``ValueError``.
"""
from __future__ import annotations

import functools
import operator

import drjit as dr
import numpy as np

from . import _arrays as A
from . import backend

_INT_TYPES = (dr.VarType.UInt32, dr.VarType.Int32, dr.VarType.UInt64, dr.VarType.Int64)
_FLOAT_TYPES = (dr.VarType.Float16, dr.VarType.Float32, dr.VarType.Float64)


def flat(x) -> bool:
    """True for a non-empty flat (1-D, non-tensor) numeric Dr.Jit JIT array."""
    return (dr.is_array_v(x) and dr.is_jit_v(x) and dr.depth_v(x) == 1 and not dr.is_tensor_v(x)
            and dr.type_v(x) in _INT_TYPES + _FLOAT_TYPES and dr.width(x) > 0)


def texel_mask(texel, n_texels: int):
    """Per-lane Bool: ``texel`` is an integer in ``[0, n_texels)`` (finite for floats)."""
    t = dr.detach(texel)
    if dr.type_v(t) in _FLOAT_TYPES:
        return dr.isfinite(t) & (t == dr.round(t)) & (t >= 0) & (t < n_texels)
    ok = t < n_texels
    return ok & (t >= 0) if dr.type_v(t) in (dr.VarType.Int32, dr.VarType.Int64) else ok


def depth_mask(depth, dtype: str, strict: bool = False):
    """Per-lane Bool: ``depth`` is finite, within the storage dtype's range, and not a
    nonzero value below its smallest normal number (those the host path flushes to 0).
    strict: also refuse exactly the smallest normal number, for depths already rounded to
    the storage dtype (a smaller float64 value may have rounded up to it)."""
    info = np.finfo(np.float32 if dtype == "float32" else np.float64)
    d = dr.detach(depth)
    if dr.type_v(d) in _INT_TYPES:     # |int| < 2^64: finite and normal in either dtype
        return dr.full(dr.mask_t(d), True, dr.width(d))
    a = dr.abs(d)
    normal = a > float(info.tiny) if strict else a >= float(info.tiny)
    return dr.isfinite(d) & (a <= float(info.max)) & ((d == 0) | normal)


#: NumPy dtypes (native byte order) that :func:`host_point_lookup` takes.
_NP_TYPES = frozenset(np.dtype(t) for t in (np.int32, np.int64, np.uint32, np.uint64, np.float32, np.float64))


def _plain(x, kinds: str, native: bool = True) -> bool:
    """True for a non-empty 1-D NumPy array of dtype kind in ``kinds`` (``native``: a dtype of
    :data:`_NP_TYPES`)."""
    return (isinstance(x, np.ndarray) and x.ndim == 1 and x.size > 0 and x.dtype.kind in kinds
            and (not native or x.dtype in _NP_TYPES))


def host_texels(texel, n_texels: int):
    """NumPy integer texel indices (1-D, non-empty) in ``[0, n_texels)`` as a Dr.Jit UInt32
    array (checked by their min and max: no float64 copy), else None."""
    if not _plain(texel, "iu", native=False) or int(texel.min()) < 0 or int(texel.max()) >= n_texels:
        return None
    return A.to_uint32(texel)


def host_depth(depth, Float):
    """NumPy float depths (1-D, non-empty) converted once to ``Float`` (checked afterwards
    with ``depth_mask(..., strict=True)``), else None."""
    if not _plain(depth, "f", native=False):
        return None
    with np.errstate(over="ignore", invalid="ignore"):      # an overflow becomes inf: refused later
        return A.to_float(depth, Float)


def host_point_lookup(eval_texels, texel, depth, n_texels: int, dtype: str, Float):
    """T of a point lookup of NumPy texels and depths that need no per-lane check, or None.

    Sufficient checks by the extremes: integer texels in ``[0, n_texels)`` (the maximum
    read as unsigned, so negatives are huge); depths, converted once to the storage dtype
    (NumPy rounding, as the checked path), finite and all of one sign beyond its smallest
    normal number (no zero or subnormal to flush).  T is bit for bit that of the checked
    path.  Lengths equal, or one of them 1.  None for anything else."""
    if not (_plain(texel, "iu") and _plain(depth, "f")):
        return None
    if texel.size != depth.size and 1 not in (texel.size, depth.size):
        return None
    if int(texel.view(np.uint64 if texel.itemsize == 8 else np.uint32).max()) >= n_texels:
        return None
    ft = np.dtype(np.float32 if dtype == "float32" else np.float64)
    info = np.finfo(ft)
    d_h = A.aligned(depth, ft)
    lo, hi = float(d_h.min()), float(d_h.max())                   # NaN fails every comparison below
    if not (-float(info.max) <= lo and hi <= float(info.max) and (lo > float(info.tiny) or hi < -float(info.tiny))):
        return None
    tex, d = _broadcast(backend.types().UInt32(A.aligned(texel, np.uint32)), Float(d_h))   # alive to the sync
    T = eval_texels(tex, d)
    dr.eval(T)
    dr.sync_thread()       # the inputs may be the caller's memory: released after the kernel (see point_lookup)
    return T


def _broadcast(tex, d):
    """``tex`` and ``d`` (lengths equal, or one of them 1) at their common length."""
    n = max(dr.width(tex), dr.width(d))
    return (tex if dr.width(tex) == n else tex + dr.zeros(type(tex), n),
            d if dr.width(d) == n else d + dr.zeros(type(d), n))


def all_true(*masks) -> bool:
    """``dr.all`` of every mask, read back as one Python bool."""
    return bool(functools.reduce(operator.and_, (dr.all(m) for m in masks))[0])


def point_lookup(eval_texels, texel, texel_checked: bool, depth, strict: bool, n_texels: int, dtype: str, Float):
    """T of a point lookup whose arguments are checked *in the lookup's own kernel*: invalid
    lanes read texel 0 at depth 0 and add 1 to a one-element counter (``dr.scatter_reduce``),
    evaluated with T in one launch; returns T (evaluated), or None when any lane was
    invalid (the caller then raises through the host checks).

    texel_checked: ``texel`` was already checked on the host (NumPy min / max); strict: see
    :func:`depth_mask`.  ``texel`` and ``depth`` have equal lengths, or one of them 1."""
    UInt32 = backend.types().UInt32
    ok = md = depth_mask(depth, dtype, strict)
    tex = A.to_uint32(dr.detach(texel))
    if not texel_checked:
        mt = texel_mask(texel, n_texels)
        tex = dr.select(mt, tex, 0)
        ok = ok & mt
    d = dr.select(ok if texel_checked else md, A.to_float(depth, Float), 0)
    tex, d = _broadcast(tex, d)
    T = eval_texels(tex, d)
    bad = dr.zeros(UInt32, 1)
    dr.scatter_reduce(dr.ReduceOp.Add, bad, UInt32(1), UInt32(0), ~ok)
    dr.eval(T, bad)
    # Wait for the kernel before the inputs can be released: a NumPy-backed input freed while
    # its kernel is queued is released by a host task that the next lookup can wait behind.
    dr.sync_thread()
    return T if int(bad[0]) == 0 else None

"""Dr.Jit backend selection: LLVM (CPU) by default, CUDA when a GPU is present.

``set_backend("llvm" | "cuda")`` chooses (``with use_backend(name):`` for a block);
``types()`` returns the Dr.Jit AD module (``drjit.llvm.ad`` or ``drjit.cuda.ad``) every kernel
uses.  ``AVSM_DR_BACKEND`` in the environment sets the initial choice (``llvm`` or ``cuda``).
"""
from __future__ import annotations

import os
from contextlib import contextmanager
from types import ModuleType
from typing import Iterator

import drjit as dr

from . import _llvm

_llvm.check_loaded()  # which libLLVM did Dr.Jit load (it chooses once, at `import drjit`)?

_BACKENDS = ("llvm", "cuda")
_current: str | None = None


def available_backends() -> list[str]:
    """Backends usable in this process, e.g. ``['llvm']`` or ``['llvm', 'cuda']``."""
    usable = {"llvm": dr.has_backend(dr.JitBackend.LLVM) and _llvm.LIBLLVM is not None,
              "cuda": dr.has_backend(dr.JitBackend.CUDA)}
    return [name for name in _BACKENDS if usable[name]]


def default_backend() -> str:
    """``$AVSM_DR_BACKEND`` if set, else ``cuda`` when a GPU is usable, else ``llvm``."""
    env = os.environ.get("AVSM_DR_BACKEND")
    if env:
        if env not in _BACKENDS:
            raise ValueError(f"AVSM_DR_BACKEND: expected one of {_BACKENDS} (or unset: cuda when a GPU "
                             f"is usable, else llvm), got {env!r}")
        return env
    return "cuda" if "cuda" in available_backends() else "llvm"  # llvm raises the install hint


def set_backend(name: str) -> None:
    """Select the Dr.Jit backend for every kernel built afterwards."""
    global _current
    if name not in _BACKENDS:
        raise ValueError(f"backend: expected one of {_BACKENDS}, got {name!r}")
    if name not in available_backends():
        # the LLVM backend counts only with a libLLVM >= 16: LLVM 15 aborts the process
        hint = (_llvm.PROBLEM or _llvm.INSTALL_HINT) if name == "llvm" else "no CUDA device/driver was found"
        raise RuntimeError(f"backend {name!r} is not available: {hint}")
    _current = name


def get_backend() -> str:
    """Name of the backend in use (chosen lazily on first use)."""
    if _current is None:
        name = default_backend()
        try:
            set_backend(name)
        except RuntimeError as exc:
            if os.environ.get("AVSM_DR_BACKEND"):
                raise RuntimeError(f"AVSM_DR_BACKEND={name!r}: {exc}") from None
            raise
    return _current  # type: ignore[return-value]


@contextmanager
def use_backend(name: str | None) -> Iterator[str | None]:
    """Select backend ``name`` inside a ``with`` block and restore the previous choice
    (also an unmade one: ``None`` leaves the choice to :func:`get_backend`) on exit."""
    global _current
    previous = _current
    if name is not None:
        set_backend(name)
    else:
        _current = None
    try:
        yield name
    finally:
        _current = previous


def types() -> ModuleType:
    """The Dr.Jit AD type module of the current backend (``drjit.<backend>.ad``)."""
    if get_backend() == "cuda":
        import drjit.cuda.ad as mod
    else:
        import drjit.llvm.ad as mod
    return mod


@contextmanager
def exact_float64(Float) -> Iterator[None]:
    """Trace float64 work on CUDA with Dr.Jit's fast math off (``JitFlag.FastMath``, on by default):
    with it on, float64 ``rcp`` / ``rsqrt``, tanh and the derivatives of sqrt, log, acos, ... (recorded
    when the forward op is traced) are good to ~1e-6 relative only (measured on an H200).  Float32 and
    LLVM keep the flag (off, float32 AVSM and OSM builds on the H200 took 1.3-1.6x the kernel time)."""
    off = dr.backend_v(Float) == dr.JitBackend.CUDA and dr.type_v(Float) == dr.VarType.Float64
    with dr.scoped_set_flag(dr.JitFlag.FastMath, dr.flag(dr.JitFlag.FastMath) and not off):
        yield


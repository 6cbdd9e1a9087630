"""Optional NVIDIA Warp import shared by the Warp peers (``pip install "avsm_dr[bench]"``).

Warp compiles each kernel module on its first launch (C++ through its bundled Clang,
cached in ``~/.cache/warp``); the peers load their module explicitly before the first
launch so that this compile is timed apart from the work (``compile_seconds``)."""
from __future__ import annotations

try:
    import warp
except ImportError:  # pragma: no cover - exercised where warp is absent
    warp = None

import numpy as np

_READY = []


def int32_array(a, name: str) -> np.ndarray:
    """``a`` as contiguous int32 (Warp's ``range`` counters are 32-bit), or ValueError naming it."""
    a = np.asarray(a)
    if a.size and (a.min() < 0 or a.max() >= 2 ** 31):
        raise ValueError(f"{name}: Warp's loop counters are 32-bit, values must lie in [0, 2^31)")
    return np.ascontiguousarray(a, np.int32)


def require(module=warp, peer: str | None = None):
    """``module`` (a peer's warp), initialised quietly, or ImportError saying how to install
    Warp when None.  ``peer``: the calling module's name, whose kernels are then compiled
    forward only (no adjoint kernels: the peers are never differentiated)."""
    if module is None:
        raise ImportError("warp is not installed: pip install 'avsm_dr[bench]' (warp-lang>=1.19)")
    if not _READY:
        module.config.log_level = module.LOG_WARNING    # no banner / per-module load lines
        module.init()
        _READY.append(True)
    if peer is not None:
        module.set_module_options({"enable_backward": False}, module=peer)
    return module

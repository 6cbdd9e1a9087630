"""Optional Numba import shared by the Numba peers (``pip install "avsm_dr[bench]"``)."""
from __future__ import annotations

import os

# Numba's OpenMP threads spin after each parallel region by default; that burns the
# cores (and the process CPU time) of whatever runs next, e.g. the kernel it is compared with.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

try:
    import numba
except ImportError:  # pragma: no cover - exercised where numba is absent
    numba = None


def require(module=numba):
    """``module`` (a peer's numba), or ImportError saying how to install Numba when None."""
    if module is None:
        raise ImportError("numba is not installed: pip install 'avsm_dr[bench]' (numba>=0.60)")
    return module

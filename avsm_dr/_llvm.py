"""Find a libLLVM that Dr.Jit's LLVM backend can use, before ``drjit`` is imported.

Dr.Jit 1.5 on LLVM 15 aborts the whole process at the first ``dr.maximum`` /
``dr.minimum`` ("Cannot select: fmaximum"); LLVM >= 16 works.  This module points
``DRJIT_LIBLLVM_PATH`` at the newest libLLVM >= 16 it can find, unless the user
already set the variable.
"""
from __future__ import annotations

import glob
import os
import re
import sys

MIN_VERSION = 16

INSTALL_HINT = (
    "avsm_dr needs libLLVM >= 16 for Dr.Jit's LLVM (CPU) backend; the system's LLVM 15 "
    "crashes Dr.Jit 1.5. Install it with:  apt-get install -y libllvm19   "
    "(or set DRJIT_LIBLLVM_PATH=/path/to/libLLVM.so.<16 or newer>)."
)

_SEARCH_PATTERNS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
    "/opt/homebrew/opt/llvm/lib/libLLVM*.dylib",
    "/usr/local/opt/llvm/lib/libLLVM*.dylib",
)


def _major_version(path: str) -> int | None:
    """LLVM major version encoded in a library file name, e.g. libLLVM.so.19.1 -> 19."""
    name = os.path.basename(path)
    match = re.search(r"libLLVM[-.](?:so\.)?(\d+)", name)
    return int(match.group(1)) if match else None


def find_libllvm(min_version: int = MIN_VERSION) -> str | None:
    """Path of the newest libLLVM with major version >= ``min_version``, or None."""
    best: tuple[int, str] | None = None
    for pattern in _SEARCH_PATTERNS:
        for path in glob.glob(pattern):
            version = _major_version(path)
            if version is None or version < min_version or not os.path.isfile(path):
                continue
            if best is None or version > best[0]:
                best = (version, path)
    return best[1] if best else None


#: The libLLVM Dr.Jit was pointed at (None: none >= 16 found, or drjit was imported first).
LIBLLVM: str | None = None


def ensure_libllvm() -> str | None:
    """Set ``DRJIT_LIBLLVM_PATH`` to a working libLLVM unless the user set it.

    Returns the path in use, or None when none was found; the LLVM backend then
    raises :class:`RuntimeError` with :data:`INSTALL_HINT` when it is selected.
    Does nothing once ``drjit`` is imported: the variable is read at import.
    """
    global LIBLLVM
    current = os.environ.get("DRJIT_LIBLLVM_PATH")
    if current:
        LIBLLVM = current
        return current
    if "drjit" in sys.modules:
        return None
    path = find_libllvm()
    if path is not None:
        os.environ["DRJIT_LIBLLVM_PATH"] = path
    LIBLLVM = path
    return path


if __name__ == "__main__":  # used by scripts/setup.sh before the package is installed
    found = find_libllvm()
    print(found or "")
    sys.exit(0 if found else 1)

"""Find a libLLVM that Dr.Jit's LLVM backend can use, before ``drjit`` is imported.

Dr.Jit 1.5 on LLVM 15 aborts the process at the first ``dr.maximum`` ("Cannot select:
fmaximum"); LLVM >= 16 works.  Dr.Jit loads its libLLVM once, in ``import drjit``
(``DRJIT_LIBLLVM_PATH``, else its own search): :func:`ensure_libllvm` points that variable
at the newest libLLVM >= 16 unless the user set it; :func:`check_loaded` then asks Dr.Jit
which LLVM it loaded (:data:`PROBLEM` names the import order when drjit came first)."""
from __future__ import annotations

import contextlib
import ctypes
import glob
import os
import re
import sys

MIN_VERSION = 16

INSTALL_HINT = ("avsm_dr needs libLLVM >= 16 for Dr.Jit's LLVM (CPU) backend; the system's LLVM 15 "
                "crashes Dr.Jit 1.5. Install it with:  apt-get install -y libllvm19   "
                "(or set DRJIT_LIBLLVM_PATH=/path/to/libLLVM.so.<16 or newer>).")

_SEARCH_PATTERNS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*", "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*", "/usr/lib64/libLLVM*.so*", "/usr/local/lib/libLLVM*.so*",
    "/opt/homebrew/opt/llvm/lib/libLLVM*.dylib", "/usr/local/opt/llvm/lib/libLLVM*.dylib")


def _major_version(path: str) -> int | None:
    """LLVM major version encoded in a library file name, e.g. libLLVM.so.19.1 -> 19."""
    match = re.search(r"libLLVM[-.](?:so\.)?(\d+)", os.path.basename(path))
    return int(match.group(1)) if match else None


def find_libllvm() -> str | None:
    """Path of the newest libLLVM with major version >= :data:`MIN_VERSION`, or None."""
    found = [(v, path) for pattern in _SEARCH_PATTERNS for path in glob.glob(pattern)
             if (v := _major_version(path)) is not None and v >= MIN_VERSION and os.path.isfile(path)]
    return max(found, key=lambda f: f[0])[1] if found else None     # the first of the newest


#: The libLLVM Dr.Jit loaded when it is >= 16 (its path where the OS tells, else a
#: description), None when the LLVM backend is unusable (:data:`PROBLEM` says why).
LIBLLVM: str | None = None
#: Why the LLVM backend is unusable, '' when it is usable or not checked yet.
PROBLEM: str = ""
#: True when ``drjit`` was imported before ``avsm_dr`` (Dr.Jit had already chosen its libLLVM).
DRJIT_IMPORTED_FIRST = False
_USER_PATH: str | None = None


def ensure_libllvm() -> None:
    """Set ``DRJIT_LIBLLVM_PATH`` to a libLLVM >= 16 unless the user set it or ``drjit``
    is already imported (too late: Dr.Jit loads its libLLVM at import)."""
    global DRJIT_IMPORTED_FIRST, _USER_PATH
    DRJIT_IMPORTED_FIRST = "drjit" in sys.modules
    _USER_PATH = os.environ.get("DRJIT_LIBLLVM_PATH") or None
    if not (_USER_PATH or DRJIT_IMPORTED_FIRST) and (path := find_libllvm()) is not None:
        os.environ["DRJIT_LIBLLVM_PATH"] = path


def _loaded_path() -> str | None:
    """Path of the libLLVM mapped into this process (Linux /proc only), else None."""
    paths = set()
    with contextlib.suppress(OSError), open("/proc/self/maps") as f:
        paths = {line.split()[-1] for line in f if "libLLVM" in line}
    return sorted(paths)[0] if len(paths) == 1 else None


def problem(version: tuple | None, drjit_first: bool, user_path: str | None, found: str | None) -> str:
    """Why Dr.Jit's LLVM backend is unusable ('' when it is).

    version: the (major, minor, patch) Dr.Jit loaded, None or major < 0 when none;
    drjit_first: ``drjit`` was imported before ``avsm_dr``; user_path: the user's
    ``DRJIT_LIBLLVM_PATH``; found: a libLLVM >= 16 on this machine (:func:`find_libllvm`)."""
    if version is not None and version[0] >= MIN_VERSION:
        return ""
    what = (f"libLLVM {'.'.join(map(str, version))}" if version is not None and version[0] >= 0
            else "no libLLVM")
    fix = (f"DRJIT_LIBLLVM_PATH={found}" if found else "DRJIT_LIBLLVM_PATH=/path/to/libLLVM.so.<16 or newer>")
    if user_path:
        return (f"Dr.Jit loaded {what} from DRJIT_LIBLLVM_PATH={user_path}, but its LLVM backend needs "
                f"libLLVM >= {MIN_VERSION} (LLVM 15 aborts the process at dr.maximum). Set {fix} "
                "before starting Python, or unset it (avsm_dr, imported before drjit, then finds one).")
    if drjit_first:
        return (f"drjit was imported before avsm_dr and loaded {what}; its LLVM backend needs libLLVM >= "
                f"{MIN_VERSION} (LLVM 15 aborts the process at dr.maximum). Dr.Jit picks its libLLVM once, "
                "at `import drjit`, so the import order is the cause: `import avsm_dr` before `import drjit` "
                f"(and before `import mitsuba`), or set {fix} before starting Python."
                + ("" if found else " " + INSTALL_HINT))
    return INSTALL_HINT


def _llvm_version(dr) -> tuple | None:
    """The LLVM version Dr.Jit loaded (None: it cannot tell), asked through ctypes, which
    releases the GIL: Dr.Jit's init thread holds its lock while it logs (a refused libLLVM)
    through a Python callback that takes the GIL, so a first query holding it can deadlock."""
    with contextlib.suppress(OSError, AttributeError):              # Linux: libdrjit-core.so
        lib, v = ctypes.CDLL(os.path.join(os.path.dirname(dr.__file__), "libdrjit-core.so")), (ctypes.c_int * 3)()
        lib._Z16jit_llvm_versionPiS_S_(*(ctypes.byref(v, 4 * i) for i in range(3)))
        return tuple(v)
    with contextlib.suppress(AttributeError, RuntimeError):
        return tuple(dr.detail.llvm_version())     # else None


#: Appended to Dr.Jit's LLVM target features, which its kernels' IR quotes verbatim
#: (``"target-features"="..."``): it closes that string and adds the attribute ``"stackrealign"``,
#: so LLVM aligns each kernel's stack frame to its vector registers and spills with aligned moves.
#: Without it spill slots keep the caller's 16-byte alignment: the thread's stack position (ASLR,
#: per process) decided how many 32-byte spills straddle cache lines, and AVSM-8's build ran at
#: 39-61 M insertions/CPU-s by process, 63-64 M with it (docs/performance.md).
STACK_REALIGN = '" "stackrealign'
#: Whether :func:`realign_stack` took effect (False: no such Dr.Jit entry points, e.g. not Linux).
STACK_REALIGNED = False


def core():
    """Dr.Jit's core library (``libdrjit-core.so``) with its LLVM target functions typed (OSError
    where there is none, AttributeError where it lacks them)."""
    import drjit as dr
    lib = ctypes.CDLL(os.path.join(os.path.dirname(dr.__file__), "libdrjit-core.so"))
    lib._Z19jit_llvm_target_cpuv.restype = lib._Z24jit_llvm_target_featuresv.restype = ctypes.c_char_p
    lib._Z21jit_llvm_vector_widthv.restype = ctypes.c_uint32
    lib._Z19jit_llvm_set_targetPKcS0_j.argtypes = (ctypes.c_char_p, ctypes.c_char_p, ctypes.c_uint32)
    return lib


def realign_stack() -> None:
    """Append :data:`STACK_REALIGN` to Dr.Jit's LLVM target (same CPU, features and vector width) for
    every kernel compiled afterwards, once per process; sets :data:`STACK_REALIGNED`."""
    global STACK_REALIGNED
    tag = STACK_REALIGN.encode()
    with contextlib.suppress(OSError, AttributeError):
        lib = core()
        cpu, feats = lib._Z19jit_llvm_target_cpuv(), lib._Z24jit_llvm_target_featuresv() or b""
        if cpu and not feats.endswith(tag):
            lib._Z19jit_llvm_set_targetPKcS0_j(cpu, feats + tag, lib._Z21jit_llvm_vector_widthv())
        STACK_REALIGNED = bool(cpu) and (lib._Z24jit_llvm_target_featuresv() or b"").endswith(tag)


def check_loaded() -> None:
    """Ask Dr.Jit (already imported) which libLLVM it loaded; set :data:`LIBLLVM` and
    :data:`PROBLEM`; where it is usable, :func:`realign_stack`."""
    global LIBLLVM, PROBLEM
    import drjit as dr
    if (version := _llvm_version(dr)) is None:  # no such query: trust DRJIT_LIBLLVM_PATH
        path = os.environ.get("DRJIT_LIBLLVM_PATH")
        version = (_major_version(path) or 0, 0, 0) if path else None
    PROBLEM = problem(version, DRJIT_IMPORTED_FIRST, _USER_PATH, find_libllvm())
    LIBLLVM = None if PROBLEM else (_loaded_path() or os.environ.get("DRJIT_LIBLLVM_PATH")
                                    or f"libLLVM {'.'.join(map(str, version))}")
    if not PROBLEM:
        realign_stack()


if __name__ == "__main__":  # used by scripts/setup.sh before the package is installed
    found = find_libllvm()
    print(found or "")
    sys.exit(0 if found else 1)

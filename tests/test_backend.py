"""libLLVM discovery, import order (drjit before or after avsm_dr) and backend choice."""
import glob
import os
import re
import subprocess
import sys

import numpy as np
import pytest

import avsm_dr as ad
import drjit as dr
from avsm_dr import _llvm
from avsm_dr import backend as backend_mod


def test_libllvm_found_and_recent():
    assert _llvm.LIBLLVM is not None and _llvm.PROBLEM == ""
    assert (_llvm._major_version(_llvm.LIBLLVM) or 99) >= 16
    assert dr.detail.llvm_version()[0] >= 16


def test_kernels_realign_their_stack_frame():
    """On Linux (where Dr.Jit's core library exports its LLVM target functions) the target features end with the
    ``"stackrealign"`` attribute and a compiled kernel's IR carries it as a function attribute next
    to (not inside) its target features; a second call appends nothing."""
    if not sys.platform.startswith("linux"):
        pytest.skip("libdrjit-core.so and its exported LLVM target functions: Linux")
    assert _llvm.STACK_REALIGNED
    lib = _llvm.core()
    _llvm.realign_stack()
    feats = lib._Z24jit_llvm_target_featuresv().decode()
    assert feats.endswith(_llvm.STACK_REALIGN) and feats.count("stackrealign") == 1
    x = dr.llvm.Float(np.linspace(0, 1, 37, dtype=np.float32))
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history()
        dr.eval(dr.sqrt(x) * 3.25 + 0.125)       # a kernel not in this process's cache
        ir = next(k["ir"].getvalue() for k in dr.kernel_history() if "ir" in k)
    attrs = next(line for line in ir.splitlines() if line.startswith("attributes #0"))
    assert re.search(r'"target-features"="[^"]*" "stackrealign"', attrs), attrs


@pytest.mark.parametrize("name, version", [
    ("libLLVM.so.19.1", 19), ("libLLVM-15.so.1", 15), ("libLLVM-17.so", 17), ("libLLVM.dylib", None)])
def test_version_from_file_name(name, version):
    assert _llvm._major_version("/usr/lib/" + name) == version


def test_llvm_backend_refused_without_good_libllvm(monkeypatch):
    monkeypatch.setattr(_llvm, "LIBLLVM", None)
    monkeypatch.setattr(_llvm, "PROBLEM", "")
    with pytest.raises(RuntimeError, match="libllvm19"):
        backend_mod.set_backend("llvm")
    monkeypatch.setattr(_llvm, "PROBLEM", "drjit was imported before avsm_dr and loaded libLLVM 15.0.6")
    with pytest.raises(RuntimeError, match="imported before avsm_dr"):
        backend_mod.set_backend("llvm")


def test_problem_names_the_cause():
    good = "/usr/lib/libLLVM.so.19.1"
    assert _llvm.problem((19, 1, 7), True, None, good) == ""
    order = _llvm.problem((15, 0, 6), True, None, good)
    assert "drjit was imported before avsm_dr" in order and "libLLVM 15.0.6" in order
    assert "import order is the cause" in order and f"DRJIT_LIBLLVM_PATH={good}" in order
    assert "no libLLVM" in _llvm.problem((-1, -1, -1), True, None, None)
    assert "libllvm19" in _llvm.problem((-1, -1, -1), True, None, None)          # nothing to point at
    user = _llvm.problem((15, 0, 6), False, "/x/libLLVM-15.so.1", good)
    assert "DRJIT_LIBLLVM_PATH=/x/libLLVM-15.so.1" in user and "import order" not in user
    assert _llvm.problem((15, 0, 6), False, None, None) == _llvm.INSTALL_HINT


_PROBE = """
import os, sys
first = sys.argv[1]
if first == "drjit":
    import drjit as dr
    import avsm_dr as ad
else:
    import avsm_dr as ad
    import drjit as dr
import numpy as np
from avsm_dr import _llvm
seg = ad.Segments.from_arrays(np.array([0, 2]), np.array([0.1, 0.3]), np.array([0.2, 0.4]),
                              optical_depth=np.array([0.5, 0.25]))
T = ad.build("avsm", seg, nodes=2).eval(np.array([0]), np.array([1.0]))   # dr.maximum inside
print(ad.get_backend(), _llvm.DRJIT_IMPORTED_FIRST, dr.detail.llvm_version()[0], float(T[0]))
"""


def _probe(first: str, env=None):
    e = {k: v for k, v in os.environ.items() if k != "DRJIT_LIBLLVM_PATH"}
    e.update(env or {})
    return subprocess.run([sys.executable, "-c", _PROBE, first], capture_output=True, text=True,
                          timeout=300, env=e)


@pytest.mark.parametrize("first", ["avsm_dr", "drjit"])
def test_either_import_order_works(first):
    """drjit imported first keeps its own libLLVM choice (LLVM 19 on this machine) and
    avsm_dr accepts it instead of reporting a missing libLLVM."""
    out = _probe(first)
    if first == "drjit" and out.returncode != 0 and "import order is the cause" in out.stderr:
        pytest.skip("Dr.Jit's own search picks an LLVM < 16 on this machine (the next test covers the error)")
    assert out.returncode == 0, out.stderr
    name, drjit_first, major, T = out.stdout.split()
    assert name == "llvm" and drjit_first == str(first == "drjit") and int(major) >= 16
    assert float(T) == pytest.approx(np.exp(-0.75), rel=1e-6)


def test_drjit_first_with_old_llvm_names_the_import_order():
    """Dr.Jit picking LLVM 15 by itself (simulated: DRJIT_LIBLLVM_PATH set for its import,
    then removed before avsm_dr looks): the error names the import order as the cause."""
    old = sorted(p for pattern in _llvm._SEARCH_PATTERNS for p in glob.glob(pattern)
                 if (_llvm._major_version(p) or 99) < 16)
    if not old:
        pytest.skip("no libLLVM < 16 on this machine to simulate the failure with")
    code = (f"import os; os.environ['DRJIT_LIBLLVM_PATH'] = {old[0]!r}\n"
            "import drjit\n"
            "del os.environ['DRJIT_LIBLLVM_PATH']\n"
            "import avsm_dr as ad\n"
            "assert 'llvm' not in ad.available_backends()\n"
            "ad.set_backend('llvm')\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         env={k: v for k, v in os.environ.items() if k != "DRJIT_LIBLLVM_PATH"})
    assert out.returncode != 0
    assert "drjit was imported before avsm_dr" in out.stderr and "import order is the cause" in out.stderr
    assert "RuntimeError" in out.stderr and "Cannot select" not in out.stderr      # refused, not aborted


def test_first_drjit_call_waits_for_its_init_without_the_gil():
    """Dr.Jit's background init holds its lock and logs a refused libLLVM through a Python
    callback that needs the GIL: a first Dr.Jit call holding the GIL then waits forever (3
    of 5 children hung with ``drjit.detail.llvm_version()`` right after ``import drjit``,
    the GIL held by a long switch interval).  ``_llvm._llvm_version`` asks through ctypes, without
    the GIL, and reports the same version."""
    import drjit as dr
    if sys.platform != "linux":
        pytest.skip("the GIL-free wait looks up libdrjit-core.so (Linux)")
    assert _llvm._llvm_version(dr) == tuple(dr.detail.llvm_version())
    old = sorted(p for pattern in _llvm._SEARCH_PATTERNS for p in glob.glob(pattern)
                 if (_llvm._major_version(p) or 99) < 16)
    if not old:
        pytest.skip("no libLLVM < 16 on this machine to make Dr.Jit log at init")
    code = ("import importlib.util, os, sys\n"
            f"spec = importlib.util.spec_from_file_location('llvm_alone', {_llvm.__file__!r})\n"
            "L = importlib.util.module_from_spec(spec); spec.loader.exec_module(L)\n"
            f"sys.setswitchinterval(1000); os.environ['DRJIT_LIBLLVM_PATH'] = {old[0]!r}\n"
            "import drjit\n"
            "L._llvm_version(drjit)\n"
            "print(tuple(drjit.detail.llvm_version()), flush=True)\n"
            "os._exit(0)\n")
    for _ in range(3):
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
        assert out.returncode == 0 and out.stdout.strip(), out.stderr


def test_set_backend_validates_name():
    with pytest.raises(ValueError, match="backend"):
        ad.set_backend("metal")
    ad.set_backend("llvm")
    assert ad.get_backend() == "llvm"


@pytest.mark.parametrize("value, msg", [
    ("garbage", r"ValueError: AVSM_DR_BACKEND: expected one of \('llvm', 'cuda'\) \(or unset.*got 'garbage'"),
    ("LLVM", r"ValueError: AVSM_DR_BACKEND: .*got 'LLVM'")])
def test_backend_variable_is_named_in_its_error(value, msg):
    """A bad ``AVSM_DR_BACKEND`` names the variable (it read "backend: ..." before)."""
    code = "import avsm_dr as ad; ad.get_backend()"
    env = dict(os.environ, AVSM_DR_BACKEND=value)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env)
    assert out.returncode == 1 and re.search(msg, out.stderr.strip().splitlines()[-1]), out.stderr


def test_unavailable_backend_variable_is_named(monkeypatch):
    monkeypatch.setenv("AVSM_DR_BACKEND", "cuda")
    monkeypatch.setattr(backend_mod, "available_backends", lambda: ["llvm"])
    with backend_mod.use_backend(None):
        with pytest.raises(RuntimeError, match=r"^AVSM_DR_BACKEND='cuda': backend 'cuda' is not available"):
            backend_mod.get_backend()


def test_use_backend_restores_the_previous_choice():
    ad.set_backend("llvm")
    with backend_mod.use_backend("llvm") as name:
        assert name == "llvm" and ad.get_backend() == "llvm"
    with backend_mod.use_backend(None):
        assert backend_mod._current is None
    assert backend_mod._current == "llvm"


def test_backend_fixture_selects_each_available_backend(backend):
    """The contract-test fixture: one run per available backend, that backend selected and
    its types used by the kernels."""
    assert backend in ad.available_backends() and ad.get_backend() == backend
    seg = ad.Segments.from_arrays(np.array([0, 1]), np.array([0.1]), np.array([0.2]),
                                  optical_depth=np.array([0.5]))
    T = ad.build("exact", seg).eval(np.array([0]), np.array([1.0]))
    assert dr.backend_v(T) == (dr.JitBackend.CUDA if backend == "cuda" else dr.JitBackend.LLVM)
    assert float(T[0]) == pytest.approx(np.exp(-0.5), rel=1e-6)


def test_float64_on_cuda_is_traced_without_fast_math():
    """Dr.Jit's CUDA fast math gives float64 rcp, rsqrt, tanh and the derivatives of sqrt, log,
    acos, ... about 1e-6 relative accuracy (measured on an H200; a moments gradient was 7e-4 off).
    ``exact_float64`` turns the flag off for float64 CUDA types only, and restores it.  The types
    exist without a GPU, so the decision is tested here; the gradients themselves are checked on
    a GPU host by the CUDA contract tests (tests/test_representations.py, marker gpu)."""
    import drjit as dr
    import drjit.cuda.ad as cuda
    import drjit.llvm.ad as llvm
    from avsm_dr.backend import exact_float64
    fast = dr.JitFlag.FastMath
    assert dr.flag(fast)                                          # Dr.Jit's default
    for Float, on_inside in ((cuda.Float64, False), (cuda.Float32, True), (llvm.Float64, True), (llvm.Float32, True)):
        with exact_float64(Float):
            assert dr.flag(fast) is on_inside, Float
        assert dr.flag(fast)
    with dr.scoped_set_flag(fast, False), exact_float64(llvm.Float32):
        assert not dr.flag(fast)                                  # a caller's choice is kept

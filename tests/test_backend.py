"""libLLVM discovery and backend choice."""
import pytest

import avsm_dr as ad
from avsm_dr import _llvm, backend


def test_libllvm_found_and_recent():
    assert _llvm.LIBLLVM is not None
    assert (_llvm._major_version(_llvm.LIBLLVM) or 99) >= 16


@pytest.mark.parametrize("name, version", [
    ("libLLVM.so.19.1", 19), ("libLLVM-15.so.1", 15), ("libLLVM-17.so", 17), ("libLLVM.dylib", None)])
def test_version_from_file_name(name, version):
    assert _llvm._major_version("/usr/lib/" + name) == version


def test_llvm_backend_refused_without_good_libllvm(monkeypatch):
    monkeypatch.setattr(_llvm, "LIBLLVM", None)
    with pytest.raises(RuntimeError, match="libllvm19"):
        backend.set_backend("llvm")


def test_set_backend_validates_name():
    with pytest.raises(ValueError, match="backend"):
        ad.set_backend("metal")
    ad.set_backend("llvm")
    assert ad.get_backend() == "llvm"

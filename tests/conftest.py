"""Shared fixtures: backend, JIT state, optional ../shared data."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

import avsm_dr as ad  # noqa: F401  (sets DRJIT_LIBLLVM_PATH before drjit loads)
import drjit as dr

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


@pytest.fixture(autouse=True)
def _clean_jit():
    """Each test starts with the default (llvm) backend and leaves no pending JIT state."""
    yield
    dr.sync_thread()


@pytest.fixture
def shared_dir() -> Path:
    """../shared beside the checkout; tests using it skip cleanly when absent."""
    path = Path(os.environ.get("AVSM_DR_SHARED", SHARED))
    if not path.is_dir():
        pytest.skip("../shared is not present")
    return path


@pytest.fixture
def rng():
    import numpy as np
    return np.random.default_rng(12345)

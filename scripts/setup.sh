#!/usr/bin/env bash
# Take a fresh machine from clone to a working avsm_dr: libLLVM >= 16 for Dr.Jit's
# LLVM backend (the system LLVM 15 crashes drjit 1.5), then the package with test extras.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

if [ -z "${DRJIT_LIBLLVM_PATH:-}" ] && ! "$PY" avsm_dr/_llvm.py >/dev/null; then
    echo "[setup] no libLLVM >= 16 found: installing Debian's libllvm19" >&2
    SUDO=""
    if [ "$(id -u)" != 0 ]; then SUDO=sudo; fi
    $SUDO apt-get update -qq
    $SUDO apt-get install -y -qq libllvm19 >/dev/null
fi
echo "[setup] libLLVM: ${DRJIT_LIBLLVM_PATH:-$("$PY" avsm_dr/_llvm.py)}" >&2

"$PY" -m pip install -q --disable-pip-version-check -e ".[test,docs]"
echo "[setup] done" >&2

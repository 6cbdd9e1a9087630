#!/usr/bin/env bash
# Take a fresh machine from clone to a working avsm_dr: libLLVM >= 16 for Dr.Jit's
# LLVM backend (the system LLVM 15 crashes drjit 1.5), then the package with test extras.
# The interpreter: $PYTHON (default python3). An externally managed one (PEP 668: Debian's
# and Ubuntu's system Python, where pip refuses to install) gets a virtual environment .venv/
# beside the checkout instead; `. scripts/activate` then puts it first on PATH (a no-op
# without .venv, e.g. on a pyenv or conda Python, which is installed into directly).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ -x .venv/bin/python ]; then
    PY=.venv/bin/python
elif "$PY" - <<'PYEOF'
import os, sys, sysconfig
managed = os.path.exists(os.path.join(sysconfig.get_path("stdlib"), "EXTERNALLY-MANAGED"))
sys.exit(0 if managed and sys.prefix == sys.base_prefix else 1)
PYEOF
then
    echo "[setup] $PY is externally managed (PEP 668): installing into .venv/ (then: . scripts/activate)" >&2
    if ! "$PY" -m venv .venv 2>/dev/null; then          # a minimal Debian lacks ensurepip: python3.X-venv
        rm -rf .venv
        VENV_PKG="python$("$PY" -c 'import sys; print("%d.%d" % sys.version_info[:2])')-venv"
        echo "[setup] '$PY -m venv' failed: installing Debian's $VENV_PKG" >&2
        SUDO=""
        if [ "$(id -u)" != 0 ]; then SUDO=sudo; fi
        $SUDO apt-get update -qq
        $SUDO apt-get install -y -qq "$VENV_PKG" >/dev/null
        "$PY" -m venv .venv || { echo "[setup] error: '$PY -m venv' still fails after installing $VENV_PKG" >&2; exit 1; }
    fi
    PY=.venv/bin/python
fi

if [ -z "${DRJIT_LIBLLVM_PATH:-}" ] && ! "$PY" avsm_dr/_llvm.py >/dev/null; then
    echo "[setup] no libLLVM >= 16 found: installing Debian's libllvm19" >&2
    SUDO=""
    if [ "$(id -u)" != 0 ]; then SUDO=sudo; fi
    $SUDO apt-get update -qq
    $SUDO apt-get install -y -qq libllvm19 >/dev/null
fi
echo "[setup] libLLVM: ${DRJIT_LIBLLVM_PATH:-$("$PY" avsm_dr/_llvm.py)}" >&2

"$PY" -m pip install -q --disable-pip-version-check -e ".[test,docs]"
echo "[setup] done: $("$PY" -c "import sys; print(sys.executable)")" >&2

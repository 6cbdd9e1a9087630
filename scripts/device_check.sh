#!/usr/bin/env bash
# GPU readiness check: on a GPU host, the AVSM paper's Table 1 at equal work
# (experiments.bench.paper_table), the contract tests on the CUDA backend, `bench --quick` and
# `frame --quick`, each step timed, summarised in a Markdown
# table (device_check.md).  Budget: under 8 minutes on a GPU host.
#
#   bash scripts/device_check.sh [OUT]          # OUT default: results/device_check
#
# A GPU host has Python with numpy/scipy/matplotlib/tqdm/pytest but no drjit or mitsuba and
# no network: put drjit's cp312 wheel (and hypothesis, which the contract tests use) in .whl/
# and they are installed into /tmp/site.  Mitsuba is not needed: the package imports it
# lazily, and the steps here never ask for ground truth (bench's Mitsuba rows are skipped
# with a note when it is absent).
#
# Without CUDA the same steps run on the LLVM backend (CPU fallback).  DEVICE_CHECK_SMOKE=1
# shrinks them to seconds (one toy kind's contract tests, one scene at one resolution, no
# bench): the test suite runs that mode to keep this script working.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-results/device_check}
PY=${PYTHON:-python3}
SMOKE=${DEVICE_CHECK_SMOKE:-0}
mkdir -p "$OUT"

if compgen -G ".whl/*.whl" >/dev/null && ! "$PY" -c "import drjit" 2>/dev/null; then   # only where drjit is missing
    "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
    export PYTHONPATH="/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
if [ -z "${DRJIT_LIBCUDA_PATH:-}" ]; then    # Dr.Jit finds the driver by name; help it where it is not on the path
    lib=$(ldconfig -p 2>/dev/null | awk '/libcuda\.so(\.1)? /{print $NF; exit}' || true)
    [ -z "$lib" ] && lib=$(ls /usr/local/nvidia/lib64/libcuda.so* /usr/lib/x86_64-linux-gnu/libcuda.so* 2>/dev/null | head -n 1 || true)
    if [ -n "$lib" ]; then export DRJIT_LIBCUDA_PATH=$lib; fi
fi
STEP_TIMEOUT=${DEVICE_CHECK_STEP_TIMEOUT:-0}   # seconds per step, 0: none (a lease is short: one slow step must not take it all)
export PYTHONUNBUFFERED=1

BACKEND=$("$PY" -c "import avsm_dr; print('cuda' if 'cuda' in avsm_dr.available_backends() else 'llvm')")
export AVSM_DR_BACKEND=$BACKEND
STEPS="$OUT/steps.tsv"
printf 'step\tbackend\tseconds\tstatus\n' > "$STEPS"

step() {   # step NAME COMMAND...: run, time, record the exit status (a failed step does not stop the rest)
    local name=$1; shift
    local t0 t1 rc=0
    t0=$EPOCHREALTIME
    echo "[device_check] $name ($BACKEND)" >&2
    timeout "$STEP_TIMEOUT" "$@" > "$OUT/$name.log" 2>&1 || rc=$?
    t1=$EPOCHREALTIME
    awk -v n="$name" -v b="$BACKEND" -v a="$t0" -v z="$t1" -v r="$rc" 'BEGIN {printf "%s\t%s\t%.1f\t%s\n", n, b, z - a, r}' >> "$STEPS"
    tail -n 3 "$OUT/$name.log" >&2
}

# the AVSM paper's Table 1 at equal work first: the figure a GPU session exists for
if [ "$SMOKE" = 1 ]; then
    step paper_table "$PY" -m experiments.bench.paper_table --out "$OUT/paper_table" --sizes 16 --resolution 64 \
        --lookups 1000 --repeats 1
else
    step paper_table "$PY" -m experiments.bench.paper_table --out "$OUT/paper_table"
fi

if [ "$BACKEND" = cuda ]; then
    step contract_tests "$PY" -m pytest -q -p no:cacheprovider -m gpu tests/test_representations.py
elif [ "$SMOKE" = 1 ]; then
    step contract_tests "$PY" -m pytest -q -p no:cacheprovider tests/test_representations.py -k toy_beer
else
    step contract_tests "$PY" -m pytest -q -p no:cacheprovider tests/test_representations.py
fi

if [ "$SMOKE" = 1 ]; then
    step frame "$PY" -c "import sys; from experiments import frame; \
frame.run(quick=True, out=sys.argv[1], force=True, scenes=['plume'], resolutions=[64], methods=('march',), repeats=1)" \
        "$OUT/frame"
else
    step bench "$PY" -m experiments bench --quick --force --backend "$BACKEND" --out "$OUT"
    step frame "$PY" -m experiments frame --quick --force --backend "$BACKEND" --out "$OUT"
fi

"$PY" scripts/device_table.py "$OUT" > "$OUT/device_check.md"
cat "$OUT/device_check.md"
# the check fails when a step failed (after writing the table)
! awk -F'\t' 'NR > 1 && $4 != 0 {bad = 1} END {exit !bad}' "$STEPS"

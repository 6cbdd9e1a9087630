#!/usr/bin/env bash
# The guide's Performance section: throughput, peers (NumPy, Numba, Mitsuba at equal error),
# the machine's limit, scaling, skipped work and memory; capture cost against the bounding box;
# the whole frame (capture -> build -> lookups) per stage on the built-in scenes.
# Usage: bash experiments/guide_performance.sh [--quick] [--force] [--backend cuda]
# (pip install -e ".[bench]" adds the Numba peers.)  Writes ${OUT:-results}/{bench,bench_capture,frame}/.
set -euo pipefail
python -m avsm_dr bench --out "${OUT:-results}" "$@"
python -m avsm_dr bench_capture --out "${OUT:-results}" "$@"
python -m avsm_dr frame --out "${OUT:-results}" "$@"

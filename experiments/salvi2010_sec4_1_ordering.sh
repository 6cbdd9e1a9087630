#!/usr/bin/env bash
# Salvi et al., "Adaptive Volumetric Shadow Maps", EGSR 2010, section 4.1 (insertion order):
# AVSM error and frame-to-frame flicker under shuffled insertion, sorted against unsorted.
# Usage: bash experiments/salvi2010_sec4_1_ordering.sh [--quick] [--force]
# Writes ${OUT:-results}/ordering/.
set -euo pipefail
python -m avsm_dr ordering --out "${OUT:-results}" "$@"

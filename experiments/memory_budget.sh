#!/usr/bin/env bash
# A memory budget instead of a node count (issue "Research results no one has published", part 3):
# adaptive AVSM (per-texel node counts by complexity water-filling, CSR storage) against fixed-N AVSM,
# DSM at the same bytes and the best breakpoint subset, per built-in scene over seeds and lights;
# bytes saved at equal error.
# Usage: bash experiments/memory_budget.sh [--quick] [--force] [--backend cuda]
# Writes ${OUT:-results}/memory_budget/.
set -euo pipefail
python -m avsm_dr memory_budget --out "${OUT:-results}" "$@"

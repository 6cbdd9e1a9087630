#!/usr/bin/env bash
# AVSM's distance from the best N-node curve (issue "Beyond the seeds"): streaming AVSM against
# offline greedy Visvalingam-Whyatt and the best breakpoint subset (refitted), per scene and N,
# on the oracle's own objective and at in-volume receivers.
# Usage: bash experiments/avsm_gap.sh [--quick] [--force] [--backend cuda]
# Writes ${OUT:-results}/avsm_gap/.
set -euo pipefail
python -m avsm_dr avsm_gap --out "${OUT:-results}" "$@"

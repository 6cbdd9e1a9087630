#!/usr/bin/env bash
# A monotone depth warp learned by gradient descent for OSM, FOM and moments, trained on
# procedural smoke and tested on held-out seeds, a new light and other scene types (issue
# "Research results no one has published", part 2; no paper reports it).
# Usage: bash experiments/learned_warp.sh [--quick] [--force] [--backend cuda]
# Writes ${OUT:-results}/learned_warp/.
set -euo pipefail
python -m avsm_dr learned_warp --out "${OUT:-results}" "$@"

#!/usr/bin/env bash
# The guide's gradient results: cost of the backward pass against the forward pass per
# representation, and the inverse problem (a plume's density recovered from its shadows).
# Usage: bash experiments/guide_gradients.sh [--quick] [--force] [--backend cuda]
# Writes ${OUT:-results}/backward_cost/ and ${OUT:-results}/inverse/.
set -euo pipefail
python -m avsm_dr backward_cost --out "${OUT:-results}" "$@"
python -m avsm_dr inverse --out "${OUT:-results}" "$@"

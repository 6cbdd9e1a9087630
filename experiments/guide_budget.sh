#!/usr/bin/env bash
# The guide's spatial-vs-depth budget table: at a fixed number of bytes per shadow map,
# resolution against nodes / coefficients per texel, error against the true transmittance.
# Usage: bash experiments/guide_budget.sh [--quick] [--force] [--backend cuda]
# Writes ${OUT:-results}/budget/.
set -euo pipefail
python -m avsm_dr budget --out "${OUT:-results}" "$@"

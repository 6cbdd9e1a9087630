#!/usr/bin/env bash
# The guide's reliability table: NaN / inf counts, bound violations and error growth of every
# representation on adversarial rays (float32 and float64).
# Usage: bash experiments/guide_stress.sh [--quick] [--force]
# Writes ${OUT:-results}/stress/.
set -euo pipefail
python -m avsm_dr stress --out "${OUT:-results}" "$@"

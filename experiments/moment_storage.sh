#!/usr/bin/env bash
# 16-bit storage of 4 power moments (no paper reports it): the optimised quantisation of Peters and
# Klein, "Moment Shadow Mapping", I3D 2015, sec. 5 ('msm', 12 bytes) against per-texel scaling
# ('scaled', 14 bytes) in float16 and unorm16, vs float32 (20 bytes); alpha tuned per variant on a
# held-out seed, RMSE ratios with 95 % intervals over seeds x lights, and the opaque='separate'
# capture as the control for the inline blocker.
# Usage: bash experiments/moment_storage.sh [--quick] [--force] [--backend cuda]
# Writes ${OUT:-results}/moment_storage/.
set -euo pipefail
python -m avsm_dr moment_storage --out "${OUT:-results}" "$@"

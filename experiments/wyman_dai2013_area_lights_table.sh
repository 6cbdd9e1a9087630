#!/usr/bin/env bash
# Wyman and Dai, "Imperfect Voxelized Shadow Volumes", HPG 2013, timing / quality table:
# imperfect voxelized shadow volumes against naive per-VPL ones for area lights, against
# a Mitsuba reference.
# Usage: bash experiments/wyman_dai2013_area_lights_table.sh [--quick] [--force]
# Writes ${OUT:-results}/area_lights/.
set -euo pipefail
python -m avsm_dr area_lights --out "${OUT:-results}" "$@"

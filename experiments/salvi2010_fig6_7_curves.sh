#!/usr/bin/env bash
# Salvi et al., "Adaptive Volumetric Shadow Maps", EGSR 2010, figures 6-7: transmittance
# along single texels (hair in smoke; three smoke columns), exact curve against AVSM-4..16,
# FOM-16, OSM-32 and DSM.
# Usage: bash experiments/salvi2010_fig6_7_curves.sh [--quick] [--force]
# Writes ${OUT:-results}/curves/.
set -euo pipefail
python -m avsm_dr curves --out "${OUT:-results}" "$@"

#!/usr/bin/env bash
# Salvi et al., "Adaptive Volumetric Shadow Maps", EGSR 2010, figures 5-6 and the claims of
# sections 3-5: error of AVSM, FOM, OSM, DSM, moments against node / coefficient count and
# bytes per texel on the built-in scenes, the depth-range sweep, and findings.json.
# Usage: bash experiments/salvi2010_fig5_6_error_vs_memory.sh [--quick] [--force] [--backend cuda]
# Writes ${OUT:-results}/error_curves/ and ${OUT:-results}/runtime_vs_error/.
set -euo pipefail
python -m avsm_dr error_curves --out "${OUT:-results}" "$@"
python -m avsm_dr runtime_vs_error --out "${OUT:-results}" "$@"

#!/usr/bin/env bash
# Salvi, Vidimce, Lauritzen and Lefohn, "Adaptive Volumetric Shadow Maps", EGSR 2010,
# figures 4-5: shadowed images per representation next to a reference, with difference images.
# Usage: bash experiments/salvi2010_fig4_5_images.sh [--quick] [--force] [--backend cuda]
# Writes ${OUT:-results}/images/ (data.csv, meta.json, *.png).
set -euo pipefail
python -m avsm_dr images --out "${OUT:-results}" "$@"

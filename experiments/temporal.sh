#!/usr/bin/env bash
# Temporal stability under animation (issue "Research results no one has published", part 1):
# error per frame and flicker of every representation, at fixed receivers, while the
# stable-fluids smoke steps, the light turns, the camera orbits and hair sways; unsorted vs
# sorted AVSM and the engine-style avsm_march; GIFs of the shadow and its error.
# Usage: bash experiments/temporal.sh [--quick] [--force] [--backend cuda]
# Writes ${OUT:-results}/temporal/.
set -euo pipefail
python -m avsm_dr temporal --out "${OUT:-results}" "$@"

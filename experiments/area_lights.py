"""Area lights: imperfect voxelized shadow volumes vs naive per-VPL VSVs (seed 002).

    python experiments/area_lights.py [--quick] [--out DIR] [--force]

Same as ``python -m avsm_dr area_lights``; see avsm_dr/experiments/area_lights.py.
"""
from __future__ import annotations

import argparse

import avsm_dr  # noqa: F401  (points Dr.Jit at a working libLLVM before it loads)
from avsm_dr.experiments.area_lights import run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes, under a minute on 2 cores")
    ap.add_argument("--out", default="results/area_lights", help="output folder")
    ap.add_argument("--force", action="store_true", help="recompute even if results exist")
    a = ap.parse_args()
    result = run(quick=a.quick, out=a.out, force=a.force)
    print(f"csv: {result['csv']}")
    print(f"summary: {result['summary']}")


if __name__ == "__main__":
    main()

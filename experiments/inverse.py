"""Inverse problem: recover a plume's density grid from shadow images (FOM / AVSM / exact).

    python experiments/inverse.py [--quick] [--out DIR] [--force]

Same as ``python -m avsm_dr inverse``; see avsm_dr/experiments/inverse.py.
"""
import sys

from avsm_dr.cli import main

if __name__ == "__main__":
    sys.exit(main(["inverse", *sys.argv[1:]]))

"""Memory and time of the backward pass against the forward pass, per representation.

    python experiments/backward_cost.py [--quick] [--out DIR] [--force]

Same as ``python -m avsm_dr backward_cost``; see avsm_dr/experiments/backward_cost.py.
"""
import sys

from avsm_dr.cli import main

if __name__ == "__main__":
    sys.exit(main(["backward_cost", *sys.argv[1:]]))

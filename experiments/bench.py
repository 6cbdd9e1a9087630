"""Throughput benchmark (see avsm_dr/experiments/bench.py). Same as `python -m avsm_dr bench`."""
from avsm_dr.cli import main

if __name__ == "__main__":
    import sys
    raise SystemExit(main(["bench", *sys.argv[1:]]))

"""``python -m experiments <name> [--quick] [--out DIR] [--force]``: run one study."""
import sys

from experiments._cli import main

if __name__ == "__main__":
    sys.exit(main())

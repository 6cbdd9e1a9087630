"""``python -m avsm_dr`` (the ``avsm-dr`` script): ``python -m experiments`` from a checkout of the
repository; an installed copy without it says where the studies are."""
import sys


def main(argv=None) -> int:
    """Forward to ``experiments._cli.main`` when the repository's studies are importable."""
    try:
        from experiments._cli import main as run
    except ImportError:
        print("avsm_dr: the studies are not part of the installed package; from a clone of the "
              "repository run `python -m experiments --help`", file=sys.stderr)
        return 2
    return run(argv)


if __name__ == "__main__":
    sys.exit(main())

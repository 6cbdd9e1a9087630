"""Command line: ``python -m avsm_dr <experiment> [--quick] [--out DIR] [--force]``.

Each experiment is a module ``avsm_dr.experiments.<name>`` exposing
``run(quick=False, out=None, force=False) -> dict``; it writes PNG figures, a CSV of
every number and a JSON of its parameters into ``results/<name>/`` (or ``--out``).
"""
from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys


def experiment_names() -> list[str]:
    """Names of the experiment modules in avsm_dr.experiments."""
    from . import experiments
    return sorted(m.name for m in pkgutil.iter_modules(experiments.__path__) if not m.name.startswith("_"))


def main(argv: list[str] | None = None) -> int:
    """Parse the command line and run one experiment; returns the exit status."""
    names = experiment_names()
    parser = argparse.ArgumentParser(prog="avsm_dr", description=__doc__.splitlines()[0])
    parser.add_argument("experiment", choices=names, help="which experiment to run")
    parser.add_argument("--quick", action="store_true", help="small sizes, under a minute on 2 cores")
    parser.add_argument("--out", default=None, help="output folder (default results/<experiment>)")
    parser.add_argument("--force", action="store_true", help="recompute even if results exist")
    parser.add_argument("--backend", default=None, choices=("llvm", "cuda"), help="Dr.Jit backend")
    args = parser.parse_args(argv)
    if args.backend:
        from . import backend
        backend.set_backend(args.backend)
    module = importlib.import_module(f"avsm_dr.experiments.{args.experiment}")
    result = module.run(quick=args.quick, out=args.out, force=args.force)
    for key, value in (result or {}).items():
        if key in ("csv", "out", "summary", "figures"):
            print(f"{key}: {value}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Command line: ``python -m avsm_dr <experiment> [--quick] [--out DIR] [--force] [--backend B]``.

Each experiment is a module (or package) ``avsm_dr.experiments.<name>`` exposing
``run(quick=False, out=None, force=False) -> dict``; it writes PNG figures, a CSV of every
number and a ``meta.json`` (parameters, versions, git commit, machine) into its own folder
``<DIR>/<name>/`` (default ``results/<name>/``), so experiments sharing ``--out`` never
overwrite each other.  Results whose parameters, package source and library versions
match are reused unless ``--force``.  A bad option (``--out`` empty, a file or not
writable; ``--workers`` / ``--address`` Ray cannot use), a bad ``AVSM_DR_BACKEND`` and
any other ``ValueError`` are reported in one line with exit status 2.
"""
from __future__ import annotations

import argparse
import importlib
import inspect
import pkgutil
import sys
import tempfile
from pathlib import Path


def experiment_names() -> list[str]:
    """Names of the experiment modules and packages in avsm_dr.experiments."""
    from . import experiments
    return sorted(m.name for m in pkgutil.iter_modules(experiments.__path__) if not m.name.startswith("_"))


def sweep_experiments() -> list[str]:
    """Experiments whose ``run`` takes ``workers``/``address`` (cells through :mod:`avsm_dr.sweep`)."""
    out = []
    for n in experiment_names():
        run = getattr(importlib.import_module(f"avsm_dr.experiments.{n}"), "run", None)
        if run is not None and "workers" in inspect.signature(run).parameters:
            out.append(n)
    return out


def parser(names: list[str] | None = None) -> argparse.ArgumentParser:
    """The command line's argument parser (``names``: the experiments offered)."""
    names = experiment_names() if names is None else names
    p = argparse.ArgumentParser(prog="avsm_dr", description=__doc__.splitlines()[0],
                                epilog="Results go to DIR/<experiment>/ (data.csv, meta.json, *.png).")
    p.add_argument("experiment", choices=names, help="which experiment to run")
    p.add_argument("--quick", action="store_true", help="small sizes, under a minute on 2 cores")
    p.add_argument("--out", default="results", metavar="DIR",
                   help="parent folder; the experiment writes into DIR/<experiment>/ (default results/)")
    p.add_argument("--force", action="store_true", help="recompute even if results exist")
    p.add_argument("--backend", default=None, choices=("llvm", "cuda"), help="Dr.Jit backend")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="run the sweep's cells on a local Ray instance with N workers (extra 'cluster')")
    p.add_argument("--address", default=None, metavar="ADDR",
                   help="run the sweep's cells on the Ray cluster at ADDR (e.g. ray://head:10001 or auto)")
    return p


def output_folder(out: str, name: str) -> Path:
    """``<out>/<name>/``, created and checked writable; ValueError naming ``--out``
    (empty, a file, or a folder that cannot be created or written)."""
    if not str(out).strip():
        raise ValueError(f"--out: expected a folder, got {out!r}")
    base = Path(out)
    if base.exists() and not base.is_dir():
        raise ValueError(f"--out: {out!r} is a file, expected a folder")
    folder = base / name
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"--out: {str(folder)!r} is a file, expected a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise ValueError(f"--out: cannot write into {str(folder)!r}: {exc.strerror or exc}") from None
    return folder


#: Messages starting with these argument names are the command line's own options.
OPTIONS = ("out:", "workers:", "address:", "backend:")


def _error(exc: BaseException) -> int:
    """Print ``exc`` as one line on stderr (``--option: ...`` when it names an option); status 2."""
    msg = " ".join(str(exc).split()) or type(exc).__name__
    print(f"avsm_dr: error: {'--' if msg.startswith(OPTIONS) else ''}{msg}", file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    """Parse the command line and run one experiment; returns the exit status (2: a bad
    option, environment variable or argument - any ValueError - reported in one line on
    stderr, no traceback)."""
    args = parser().parse_args(argv)
    try:                                              # checked before anything is written
        from . import backend, sweep
        if args.backend:
            backend.set_backend(args.backend)
        backend.get_backend()                         # $AVSM_DR_BACKEND
        sweep.check_workers(args.workers, args.address)
        out = output_folder(args.out, args.experiment)
    except (ValueError, RuntimeError) as exc:         # RuntimeError: the backend is not available
        return _error(exc)
    module = importlib.import_module(f"avsm_dr.experiments.{args.experiment}")
    extra = {k: v for k, v in (("workers", args.workers), ("address", args.address)) if v is not None}
    if extra and not all(k in inspect.signature(module.run).parameters for k in extra):
        print(f"avsm_dr: error: --{next(iter(extra))}: experiment {args.experiment!r} runs serially only "
              f"(sweeps over cells: {', '.join(n for n in sweep_experiments())})", file=sys.stderr)
        return 2
    try:
        result = module.run(quick=args.quick, out=out, force=args.force, **extra)
    except ValueError as exc:
        return _error(exc)
    for key, value in (result or {}).items():
        if key in ("csv", "out", "summary", "figures", "cached"):
            print(f"{key}: {value}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

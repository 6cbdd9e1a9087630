"""Command line: ``python -m experiments <study> [--quick] [--out DIR] [--force] [--backend B]``.

Each study is a module (or package) ``experiments.<name>`` (this folder of the repository;
not installed with the package) declaring ``STUDY`` (an :class:`experiments._study.Study`:
its description, full and quick parameters, options and files; ``run = STUDY.run``); it
writes PNG figures, a CSV of every number and a ``meta.json`` (parameters, versions, git
commit, machine) into its own folder
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
import json
import pkgutil
import re
import sys
import tempfile
from pathlib import Path

from ._headline import generic
from ._study import Study


def experiment_names() -> list[str]:
    """Names of the experiment modules and packages in experiments."""
    import experiments
    return sorted(m.name for m in pkgutil.iter_modules(experiments.__path__) if not m.name.startswith("_"))


def study(name: str) -> Study:
    """The declared :class:`~experiments._study.Study` of ``experiments.<name>`` (its ``STUDY``)."""
    declared = getattr(importlib.import_module(f"experiments.{name}"), "STUDY", None)
    if not isinstance(declared, Study):
        raise TypeError(f"experiments.{name} declares no STUDY (an experiments._study.Study)")
    return declared


def preload(name: str) -> list[str]:
    """Import now what a run of study ``name`` imports lazily: the shared ``experiments._*`` modules
    and the study package's own modules (not its subpackages, e.g. the optional peer kernels), so
    a run keeps the source it started with when experiments/ is edited while it runs (a run once
    failed in its figures: its plotting module, read later, needed a newer ``_plotstyle`` than the
    one loaded at its start).  Returns the names imported."""
    import experiments
    names = [f"experiments.{m.name}" for m in pkgutil.iter_modules(experiments.__path__)
             if m.name.startswith("_") and m.name not in ("__main__", "_cli")]
    pkg = importlib.import_module(f"experiments.{name}")
    names += [f"{pkg.__name__}.{m.name}" for m in pkgutil.iter_modules(getattr(pkg, "__path__", []))
              if not m.ispkg]
    for n in names:
        importlib.import_module(n)
    return names


def sweep_experiments() -> list[str]:
    """Experiments declared ``sweep=True`` (``workers``/``address``: cells through :mod:`experiments._sweep`)."""
    return [n for n in experiment_names() if study(n).sweep]


_ROLES = re.compile(r":(?:mod|func|class|meth|attr|data|obj):`~?\.?([^`]+)`")


def plain(doc: str) -> str:
    """A docstring as terminal text: reST roles, double back-quotes and Markdown bold dropped."""
    return _ROLES.sub(lambda m: m.group(1), doc or "").replace("``", "").replace("**", "")


def about(name: str) -> str:
    """Study ``name``'s one-line description (its declared ``about``)."""
    return study(name).about


def _study_help(name: str) -> tuple[str, str]:
    """(description, epilog) of ``python -m experiments NAME --help``: the study's docstring,
    what it reproduces, its parameters and what it writes."""
    doc = inspect.getdoc(importlib.import_module(f"experiments.{name}")) or ""
    return study(name).help_text(plain, doc)


def parser(names: list[str] | None = None) -> argparse.ArgumentParser:
    """The command line's argument parser: one sub-command per study (``names``: the studies
    offered), each with its own ``--help`` and the options its :class:`Study` declares."""
    names = experiment_names() if names is None else names
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--quick", action="store_true", help="small sizes (a minute or two on 2 cores)")
    common.add_argument("--out", default="results", metavar="DIR",
                        help="parent folder; the study writes into DIR/<study>/ (default results/)")
    common.add_argument("--force", action="store_true", help="recompute even if identical results exist")
    common.add_argument("--backend", default=None, choices=("llvm", "cuda"), help="Dr.Jit backend")
    listing = "\n".join(f"  {n:<18} {about(n)}" for n in names)
    p = argparse.ArgumentParser(
        prog="python -m experiments", formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Run one study of avsm_dr from the repository root; each writes DIR/<study>/.\n\n"
                    "studies:\n" + listing,
        epilog="`python -m experiments <study> --help` describes a study, its options and what it writes.")
    sub = p.add_subparsers(dest="experiment", metavar="<study>", required=True)
    for n in names:
        s = study(n)
        desc, epilog = _study_help(n)
        sp = sub.add_parser(n, parents=[common], help=s.about, description=desc, epilog=epilog,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
        for o in s.options:
            sp.add_argument(f"--{o.name.replace('_', '-')}", dest=o.name, type=o.type, nargs=o.nargs,
                            default=None, metavar=o.metavar, help=o.help)
        where = "" if s.sweep else " (sweep studies only: this one runs serially)"
        sp.add_argument("--workers", type=int, default=None, metavar="N",
                        help=f"run the sweep's cells on a local Ray instance with N workers{where}")
        sp.add_argument("--address", default=None, metavar="ADDR",
                        help=f"run the sweep's cells on the Ray cluster at ADDR (ray://head:10001 or auto){where}")
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
    print(f"experiments: error: {'--' if msg.startswith(OPTIONS) else ''}{msg}", file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    """Parse the command line and run one experiment; returns the exit status (2: a bad
    option, environment variable or argument - any ValueError - reported in one line on
    stderr, no traceback)."""
    args = parser().parse_args(argv)
    try:                                              # checked before anything is written
        from avsm_dr import backend
        from . import _sweep as sweep
        if args.backend:
            backend.set_backend(args.backend)
        backend.get_backend()                         # $AVSM_DR_BACKEND
        sweep.check_workers(args.workers, args.address)
        out = output_folder(args.out, args.experiment)
    except (ValueError, RuntimeError) as exc:         # RuntimeError: the backend is not available
        return _error(exc)
    s = study(args.experiment)
    preload(args.experiment)
    extra = {k: v for k, v in (("workers", args.workers), ("address", args.address)) if v is not None}
    if extra and not s.sweep:
        print(f"experiments: error: --{next(iter(extra))}: experiment {args.experiment!r} runs serially only "
              f"(sweeps over cells: {', '.join(n for n in sweep_experiments())})", file=sys.stderr)
        return 2
    extra.update({o.name: getattr(args, o.name) for o in s.options if getattr(args, o.name) is not None})
    try:
        result = s.run(quick=args.quick, out=out, force=args.force, **extra)
    except ValueError as exc:
        return _error(exc)
    print(summary_text(args.experiment, result or {}, out, s))
    return 0


#: At most this many headline lines of a run's summary are printed (the rest are in its files).
SUMMARY_LINES = 12


def summary_text(name: str, result: dict, out: Path, declared: Study | None = None) -> str:
    """The few lines a run ends with: what the study measured (its ``about``), its headline
    numbers (:meth:`Study.headline_lines <experiments._study.Study.headline_lines>`, at most
    :data:`SUMMARY_LINES`) and where its files are; never a dict.  ``declared``: the study
    (default: ``experiments.<name>``'s ``STUDY``, or the generic lines when there is none)."""
    if declared is None:
        try:
            declared = study(name)
        except (ImportError, TypeError):
            declared = None
    folder = Path(result.get("out", out))
    files = sorted(p.name for p in folder.iterdir() if p.is_file()) if folder.is_dir() else []
    lines = [f"{name}: {declared.about}" if declared else f"{name}:"]
    summary = result.get("summary")
    try:                                              # the recorded summary: fresh and reused runs alike
        summary = json.loads((folder / "meta.json").read_text())["summary"]
    except (OSError, ValueError, KeyError, TypeError):
        pass
    try:
        heads = declared.headline_lines(summary) if declared else generic(summary)
    except (KeyError, TypeError, ValueError, AttributeError) as exc:   # the files are written: never fail here
        heads = [f"(the study's headline failed: {type(exc).__name__}: {exc}; its summary follows)"] + generic(summary)
    lines += [f"  {h}" for h in heads[:SUMMARY_LINES]]
    if len(heads) > SUMMARY_LINES:
        where = "findings.json" if (folder / "findings.json").exists() else "meta.json"
        lines.append(f"  ... and {len(heads) - SUMMARY_LINES} more in {where}")
    shown = ", ".join(files[:8]) + (", ..." if len(files) > 8 else "")
    lines.append(f"{'reused cached results in' if result.get('cached') else 'wrote'} {folder}/"
                 + (f" ({shown})" if files else ""))
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())

"""The declarative study: what a study is (name, one-line description, full and quick
parameters, options, files) as data, and the one ``run`` every study shares.

A study module declares, at the top of its file, ``FULL`` and ``QUICK`` (its parameters)
and, at the end, ``STUDY = Study(...)`` with its ``compute`` function and ``run =
STUDY.run``.  :meth:`Study.run` resolves the parameters, reuses an identical earlier run
(:meth:`Results.cached <experiments._common.Results.cached>`), calls ``compute`` and
writes what it returns (``data.csv``, further tables, ``findings.json``) and ``meta.json``
last, every file atomically.  The command line (:mod:`experiments._cli`) reads the same
objects for its listing, each study's ``--help`` and its options.
"""
from __future__ import annotations

import copy
import dataclasses
import json
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ._common import Results
from ._headline import generic


@dataclasses.dataclass(frozen=True)
class Option:
    """A study-specific command-line option ``--<name>`` and keyword of ``run``.

    When ``name`` is one of the study's parameters the value replaces it (``None``: the
    mode's value); otherwise it is passed to ``resolve`` and ``compute`` as a keyword."""
    name: str
    help: str
    type: Callable = str
    nargs: str | None = None          # "+": a list of values
    metavar: str | None = None


#: The options of sweep studies: their cells run through Ray (:mod:`experiments._sweep`).
SWEEP_OPTIONS = ("workers", "address")


def _json_default(v):
    """JSON for NumPy scalars (their Python value) and anything else (its ``str``)."""
    return v.item() if isinstance(v, np.generic) else str(v)


def write_data(res: Results, output: dict) -> str:
    """A compute's data files: ``rows`` as data.csv, its ``tables``, its ``findings`` as
    findings.json (each atomic); returns data.csv's path.  :meth:`Study.run` calls it after
    ``compute``; a compute calls it before its figures too, so that a figure that fails
    leaves the data of a long run (rewritten, with the final timings, at the end)."""
    csv = res.write_csv(output["rows"])
    for filename, rows in output.get("tables", {}).items():
        res.write_csv(rows, filename)
    if "findings" in output:
        res.write_json("findings.json", output["findings"], indent=1, default=_json_default)
    return str(csv)


@dataclasses.dataclass(frozen=True)
class Study:
    """One study of ``python -m experiments``.

    Parameters
    ----------
    name
        Sub-command and results folder (``<out>/<name>/``).
    about
        One line for the listing of ``python -m experiments --help``.
    reproduces
        The paper's figure or table (or the guide's section) it reproduces.
    full, quick
        Parameters of the full and the ``--quick`` run (recorded in ``meta.json``; they key
        the results cache).
    compute
        ``compute(res, P, **runtime) -> dict`` with ``rows`` (``data.csv``), ``summary``
        (``meta.json``'s and the result's summary) and optionally ``tables`` (file name ->
        rows), ``findings`` (``findings.json``) and ``result`` (entries of the returned dict
        that differ from the recorded ones).  Figures and arrays it writes itself through
        ``res`` (:class:`~experiments._common.Results`).
    writes
        What it writes besides ``meta.json`` and the figures (for ``--help``).
    options
        Its own options (:class:`Option`).
    sweep
        True when ``run`` takes ``workers`` / ``address`` (cells through Ray).
    resolve
        ``resolve(P, quick, **runtime) -> P``: defaults that depend on the registry or an
        option, and checks of the parameters (``ValueError`` naming the argument), before
        the cache is consulted.
    headline
        ``headline(summary) -> list[str]``: the few human lines a run ends with (what was
        measured, the headline numbers with their intervals), read from the recorded
        ``summary`` (JSON types); ``None``: :func:`experiments._headline.generic`.
    """
    name: str
    about: str
    reproduces: str
    full: dict
    quick: dict
    compute: Callable[..., dict]
    writes: tuple[str, ...] = ("data.csv",)
    options: tuple[Option, ...] = ()
    sweep: bool = False
    resolve: Callable[..., dict] | None = None
    headline: Callable[[dict], list[str]] | None = None

    def keywords(self) -> tuple[str, ...]:
        """The keywords ``run`` takes besides ``quick``, ``out`` and ``force``."""
        return tuple(o.name for o in self.options) + (SWEEP_OPTIONS if self.sweep else ())

    def params(self, quick: bool = False, **options) -> tuple[dict, dict]:
        """(parameters, runtime keywords) of a run: the mode's parameters (a deep copy) with
        the options that name one replaced (``None`` keeps the mode's value), resolved."""
        unknown = sorted(set(options) - set(self.keywords()))
        if unknown:
            raise TypeError(f"{self.name}.run() got an unexpected keyword argument {unknown[0]!r}")
        P = copy.deepcopy(self.quick if quick else self.full)
        runtime = {}
        for k, v in options.items():
            if k in P:
                if v is not None:
                    P[k] = v
            else:
                runtime[k] = v
        if self.resolve is not None:
            P = self.resolve(P, quick, **runtime)
        return P, runtime

    def run(self, quick: bool = False, out: str | Path | None = None, force: bool = False, **options) -> dict:
        """Run the study into ``out`` (default ``results/<name>/``), or reuse an identical
        earlier run unless ``force``; returns ``{'csv', 'out', 'figures', 'summary'}``
        (and ``'cached': True`` for a reused one)."""
        if self.sweep:
            from . import _sweep as sweep
            sweep.check_workers(options.get("workers"), options.get("address"))
        P, runtime = self.params(quick, **options)
        res = Results(self.name, out, quick, P)
        res.force = force
        if (hit := res.cached(force)) is not None:
            meta = res.meta()
            return dict(hit, figures=[str(res.dir / f) for f in meta.get("figures", [])],
                        summary=meta.get("summary", {}))
        output = self.compute(res, P, **runtime)
        csv = write_data(res, output)
        res.write_meta(output["summary"])
        return {"csv": csv, "out": str(res.dir), "figures": list(res.figures), "summary": output["summary"],
                **output.get("result", {})}

    def headline_lines(self, summary) -> list[str]:
        """The run's headline lines: its declared :attr:`headline` of ``summary`` as recorded
        in ``meta.json`` (a fresh and a reused run print the same), else the generic lines."""
        summary = json.loads(json.dumps(summary, default=_json_default))
        return (self.headline or generic)(summary) if summary else []

    def help_text(self, plain: Callable[[str], str] = str, doc: str = "") -> tuple[str, str]:
        """(description, epilog) of ``python -m experiments <name> --help``: ``doc`` (the
        module docstring), what it reproduces, its parameters and what it writes."""
        desc = plain(doc or self.about)
        desc += f"\n\nReproduces: {self.reproduces}"
        desc += "\n\nParameters (full run; --quick in brackets where it differs):\n" + "\n".join(
            f"  {k} = {_brief(v)}" + (f"  [{_brief(self.quick[k])}]" if k in self.quick and self.quick[k] != v
                                       else "") for k, v in self.full.items())
        writes = ", ".join(self.writes)
        epilog = (f"Writes DIR/{self.name}/ (DIR from --out, default results/): {writes}, meta.json (parameters, "
                  f"versions, git commit, machine, checksums of the files) and the figures (PNG and PDF); an "
                  f"identical earlier run is reused unless --force.")
        return desc, epilog


def _brief(value: Any, width: int = 70) -> str:
    """A parameter value on one line of at most ``width`` characters."""
    text = json.dumps(value, default=_json_default)
    return text if len(text) <= width else text[:width - 4] + " ..."

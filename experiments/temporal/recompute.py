"""Redo ``temporal``'s per-method statistics, intervals and headline from a finished run,
without rerunning it::

    python -m experiments.temporal.recompute RUN_DIR --out DIR

``RUN_DIR`` holds a run's ``data.csv``, ``findings.json`` and ``meta.json`` (the first two
may be gzipped, ``data.csv.gz``, as in the committed full run ``docs/research/temporal/run``).  Each
configuration's statistics come from ``data.csv``'s per-frame rows
(:func:`.metrics.per_config_from_rows`: equal to the run's own per-configuration values to
rounding), then :func:`per_setting <experiments.temporal.per_setting>` gives their mean and
interval over configurations.  The paired claims (``claims``, ``insertion``) and ``curves``
need the receivers' errors, which ``data.csv`` does not hold: they are copied from the run's
``findings.json`` (their unit was already the configuration).  Writes ``findings.json``,
``error_flicker_per_frame.png``, ``flicker_vs_error.png``, ``insertion_flicker.png`` and
``meta.json`` (``recomputed_from``: the run's folder and commit) into ``DIR``.
"""
from __future__ import annotations

import argparse
import csv
import io
import json
from pathlib import Path

from .._common import run_text as _text


def recompute(run_dir, out) -> dict:
    """The recomputed findings of the run in ``run_dir``, written with the figures to ``out``."""
    from .. import _common
    from . import INTERVALS, methods, per_setting
    from .metrics import per_config_from_rows
    from .plots import plot_summary
    run_dir = Path(run_dir)
    if Path(out).resolve() == run_dir.resolve():
        raise ValueError("out: expected another folder than the run's (its files are the inputs)")
    try:
        meta = json.loads((run_dir / "meta.json").read_text())
        old = json.loads(_text(run_dir, "findings.json"))
        rows = list(csv.DictReader(io.StringIO(_text(run_dir, "data.csv"), newline="")))
    except (OSError, ValueError) as exc:
        raise ValueError(f"run_dir: {run_dir} does not hold a temporal run ({exc})") from None
    if meta.get("experiment") != "temporal":
        raise ValueError(f"run_dir: {run_dir} holds the results of {meta.get('experiment')!r}, not 'temporal'")
    P = meta["params"]
    ms = [m for m in methods(P["quick"]) if m[0] in P["methods"]]
    gone = sorted(set(P["methods"]) - {m[0] for m in ms})
    if gone:
        raise ValueError(f"run_dir: the run's labels {gone} are no longer temporal's methods")
    settings = list(old["per_setting"])
    new = dict(old, intervals=INTERVALS)
    new["per_setting"], new["headline"] = per_setting(per_config_from_rows(rows), settings, ms, P["n_boot"])
    res = _common.Results("temporal", out, P["quick"], P)
    res.write_json("findings.json", new, indent=1)
    plot_summary(res, rows, new)
    res.write_meta({"headline": new["headline"], "run_seconds": old.get("run_seconds"),
                    "recomputed_from": {"folder": str(run_dir), "git_commit": meta.get("git_commit")}})
    return new


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m experiments.temporal.recompute", description=__doc__.split("\n\n")[0])
    ap.add_argument("run_dir", help="a temporal run's folder (data.csv, findings.json, meta.json)")
    ap.add_argument("--out", required=True, help="folder for the recomputed findings.json and figures")
    a = ap.parse_args(argv)
    recompute(a.run_dir, a.out)
    print(f"wrote {a.out}/findings.json and figures")


if __name__ == "__main__":
    main()

"""Redraw a study's figures from rows read back from a table, without rerunning the study::

    python -m experiments._replot ordering docs/research/ordering/configs.csv --out docs/research/ordering

The table is a run's ``data.csv`` (or ``data.csv.gz``, as a committed full run under
``docs/research/<study>/run/``) or the small CSV of a figure's data committed beside a research
page's figures (``docs/research/<study>/``).  A study can be redrawn this way when its module
declares ``redraw(res, rows)``: ``rows`` as :func:`typed` reads them back, ``res`` anything with
``save_figure(fig, filename)`` (here :class:`Figures`).  Writes the PNGs (what the pages show);
``--pdf`` adds the vector copy beside each, as a run does.
"""
from __future__ import annotations

import argparse
import importlib
from pathlib import Path


def _value(text: str):
    """``text`` as ``bool``, ``int`` or ``float`` where it parses as one, else unchanged."""
    if text in ("True", "False"):
        return text == "True"
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text


def typed(rows: list[dict]) -> list[dict]:
    """Rows of a CSV (values as strings, :func:`experiments._common.read_csv`) with each value
    as the ``bool``, ``int`` or ``float`` it spells, the rest strings (an empty cell stays ``''``)."""
    return [{k: _value(v) for k, v in r.items()} for r in rows]


class Figures:
    """Where :func:`replot` puts a study's figures: ``save_figure`` writes ``out / filename``
    (a ``.png``; with ``pdf`` also the ``.pdf`` beside it) with fixed metadata and closes the
    figure; :attr:`figures` lists what was written."""

    def __init__(self, out, pdf: bool = False):
        self.dir, self.pdf, self.figures = Path(out), pdf, []
        self.dir.mkdir(parents=True, exist_ok=True)

    def save_figure(self, fig, filename: str) -> Path:
        """Write ``fig`` as ``filename`` (a ``.png`` name) in :attr:`dir`; returns its path."""
        from . import _plotstyle as plotstyle
        import matplotlib.pyplot as plt
        if Path(filename).suffix != ".png":
            raise ValueError(f"filename: expected a .png name, got {filename!r}")
        path = self.dir / filename
        plotstyle.render(fig, path, "png")
        self.figures.append(path)
        if self.pdf:
            plotstyle.render(fig, path.with_suffix(".pdf"), "pdf")
            self.figures.append(path.with_suffix(".pdf"))
        plt.close(fig)
        return path


def read_table(table) -> list[dict]:
    """The rows of the CSV ``table`` (gzipped where its name ends in ``.gz``), values as strings."""
    import csv
    import gzip
    if str(table).endswith(".gz"):
        with gzip.open(table, "rt", newline="") as fh:
            return list(csv.DictReader(fh))
    from . import _common
    return _common.read_csv(table)


def replot(study: str, table, out, pdf: bool = False) -> list[Path]:
    """Redraw study ``study``'s figures from the rows of the CSV ``table`` (gzipped where its
    name ends in ``.gz``) into the folder ``out``; returns the files written.  ``ValueError``
    when the study declares no ``redraw(res, rows)`` or the table holds no rows."""
    from ._cli import experiment_names
    if study not in experiment_names():
        raise ValueError(f"study: expected one of {experiment_names()}, got {study!r}")
    redraw = getattr(importlib.import_module(f"experiments.{study}"), "redraw", None)
    if not callable(redraw):
        raise ValueError(f"study: experiments.{study} declares no redraw(res, rows) to draw its figures from a table")
    try:
        rows = typed(read_table(table))
    except (OSError, EOFError) as exc:
        raise ValueError(f"table: cannot read {table} ({exc})") from None
    if not rows:
        raise ValueError(f"table: {table} holds no rows")
    import matplotlib
    matplotlib.use("Agg")
    res = Figures(out, pdf)
    redraw(res, rows)
    return res.figures


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(prog="python -m experiments._replot", description=__doc__.split("::")[0])
    ap.add_argument("study", help="the study whose figures to redraw (its module declares redraw(res, rows))")
    ap.add_argument("table", help="CSV of the figure's rows: a run's data.csv or a committed table")
    ap.add_argument("--out", required=True, help="folder for the figures")
    ap.add_argument("--pdf", action="store_true", help="also write the vector PDF beside each PNG")
    a = ap.parse_args(argv)
    for path in replot(a.study, a.table, a.out, a.pdf):
        print(f"wrote {path}")


if __name__ == "__main__":
    main()

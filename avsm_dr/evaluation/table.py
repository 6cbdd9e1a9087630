"""A tidy table: one dict per row, columns in order of first appearance (no pandas needed;
``pandas.DataFrame(list(table))`` converts it)."""
from __future__ import annotations

import csv
import json
from pathlib import Path

#: Columns the text view shows first (the others are in the rows and the CSV).
SUMMARY_COLUMNS = ("method", "scene", "seed", "light", "receivers", "rmse", "depth_l2", "bytes")
#: Rows the text view shows.
SHOWN_ROWS = 20


def _cell(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, dict):
        return json.dumps(v, sort_keys=True, default=str)
    return str(v)


class Table:
    """Rows (dicts) of one evaluation.

    ``len(t)``, ``t[i]`` (a row), iteration over rows, :meth:`column`, :meth:`where`,
    :meth:`to_csv`; ``repr(t)`` is a short text table of :data:`SUMMARY_COLUMNS`."""

    def __init__(self, rows=()):
        if isinstance(rows, (str, bytes, dict)) or not hasattr(rows, "__iter__"):
            raise ValueError(f"rows: expected an iterable of dicts, got {type(rows).__name__}")
        rows = list(rows)
        if not all(isinstance(r, dict) for r in rows):
            raise ValueError("rows: expected dicts")
        self.rows = [dict(r) for r in rows]

    @property
    def columns(self) -> list[str]:
        """Column names in order of first appearance."""
        return list(dict.fromkeys(k for r in self.rows for k in r))

    def __len__(self) -> int:
        return len(self.rows)

    def __iter__(self):
        return iter(self.rows)

    def __getitem__(self, i) -> dict:
        return self.rows[i]

    def _check(self, name):
        if name not in self.columns:
            raise ValueError(f"{name}: no such column; columns: {self.columns}")

    def column(self, name: str) -> list:
        """The values of column ``name``, row by row (``np.asarray`` makes numbers an array)."""
        self._check(name)
        return [r.get(name) for r in self.rows]

    def where(self, **eq) -> "Table":
        """Rows whose column ``k`` equals ``v`` for every ``k=v``; a list, tuple or set ``v``
        matches any of its values, a callable ``v`` where ``v(value)`` is true."""
        for k in eq:
            self._check(k)

        def match(v, x) -> bool:
            return v(x) if callable(v) else x in v if isinstance(v, (list, tuple, set, frozenset)) else x == v
        return Table([r for r in self.rows if all(match(v, r.get(k)) for k, v in eq.items())])

    def to_csv(self, path) -> Path:
        """Write the rows as CSV (floats with 9 significant digits, dicts as JSON)."""
        path = Path(path)
        cols = self.columns
        with path.open("w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=cols)
            w.writeheader()
            for r in self.rows:
                w.writerow({k: (f"{v:.9g}" if isinstance(v, float) else _cell(v)) for k, v in r.items()})
        return path

    def __repr__(self) -> str:
        cols = [c for c in SUMMARY_COLUMNS if c in self.columns]
        shown = self.rows[:SHOWN_ROWS]
        cells = [[_cell(r.get(c, "")) for c in cols] for r in shown]
        widths = [max([len(c)] + [len(row[i]) for row in cells]) for i, c in enumerate(cols)]
        lines = ["  ".join(c.ljust(w) for c, w in zip(cols, widths))]
        lines += ["  ".join(v.ljust(w) for v, w in zip(row, widths)) for row in cells]
        more = f", first {SHOWN_ROWS} shown" if len(self.rows) > SHOWN_ROWS else ""
        lines.append(f"({len(self.rows)} rows x {len(self.columns)} columns{more})")
        return "\n".join(lines)

    __str__ = __repr__


def read_csv(path: str | Path) -> list[dict]:
    """Rows of a CSV file (a study's ``data.csv``, :meth:`Table.to_csv`), values as strings."""
    with Path(path).open(newline="") as fh:
        return list(csv.DictReader(fh))

"""Markdown summary of a ``scripts/device_check.sh`` run.

    python scripts/device_table.py OUT > OUT/device_check.md

Reads ``OUT/steps.tsv`` (step, backend, seconds, exit status), ``OUT/paper_table/paper_table.md``,
``OUT/frame/data.csv``
(``python -m experiments frame``) and ``OUT/bench/data.csv`` (``python -m experiments bench``) where
present, and prints four tables: the steps; the paper table; per kind, the frame at the largest resolution
of each scene (capture / build / lookup in ms, the frame's stage shares); per bench setting,
build (M insertions/s) and lookup (M receivers/s) rates and the ratio to the Numba peer.
Needs only the standard library (a GPU host may lack everything else).
"""
from __future__ import annotations

import csv
import sys
from pathlib import Path


def _rows(path: Path) -> list[dict]:
    if not path.is_file():
        return []
    with path.open(newline="") as f:
        return list(csv.DictReader(f, delimiter="\t" if path.suffix == ".tsv" else ","))


def _num(v) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


def _fmt(x: float, digits: int = 3) -> str:
    return "" if x != x else f"{x:.{digits}g}"


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def steps_table(out: Path) -> str:
    """The steps: name, backend, seconds, exit status."""
    rows = _rows(out / "steps.tsv")
    return _table(["step", "backend", "seconds", "exit status"],
                  [[r["step"], r["backend"], r["seconds"], r["status"]] for r in rows])


def frame_table(out: Path) -> str:
    """Per scene and kind at the scene's largest resolution (first capture method):
    capture, build and lookup times in ms and the frame's shares."""
    rows = [r for r in _rows(out / "frame" / "data.csv") if not r.get("note")]
    if not rows:
        return "(no frame results)"
    body = []
    for scene in sorted({r["scene"] for r in rows}):
        mine = [r for r in rows if r["scene"] == scene]
        res = max(int(r["resolution"]) for r in mine)
        method = sorted({r["method"] for r in mine})[0]
        for r in sorted((r for r in mine if int(r["resolution"]) == res and r["method"] == method),
                        key=lambda r: r["kind"]):
            body.append([scene, f"{res}^2", method or "-", r["kind"], r["segments"],
                         _fmt(1e3 * _num(r["capture_s"])), _fmt(1e3 * _num(r["build_s"])),
                         _fmt(1e3 * _num(r["lookup_s"])), r["lookups"],
                         _fmt(_num(r["capture_share"]), 2), _fmt(_num(r["build_share"]), 2)])
    return _table(["scene", "map", "capture", "kind", "segments", "capture ms", "build ms", "lookup ms",
                   "lookups", "capture share", "build share"], body)


def bench_table(out: Path) -> str:
    """Our settings on the bench's synthetic maps: build and lookup rates, ratio to Numba."""
    rows = [r for r in _rows(out / "bench" / "data.csv") if r.get("impl") == "drjit"]
    if not rows:
        return "(no bench results)"
    body = [[r["map"], r["setting"], _fmt(_num(r["insertions_per_s"]) / 1e6), _fmt(_num(r["lookups_per_s"]) / 1e6),
             _fmt(_num(r.get("speedup_vs_numba"))), _fmt(_num(r.get("lookup_speedup_vs_numba")))] for r in rows]
    return _table(["map", "setting", "build M ins/s", "lookup M/s", "build vs Numba", "lookup vs Numba"], body)


def main(argv: list[str]) -> int:
    """Print the Markdown report for the folder ``argv[0]``."""
    if len(argv) != 1:
        print("usage: python scripts/device_table.py OUT", file=sys.stderr)
        return 2
    out = Path(argv[0])
    print("# Device check\n")
    print("## Steps\n\n" + steps_table(out) + "\n")
    table1 = out / "paper_table" / "paper_table.md"
    print("## The AVSM paper's Table 1 at equal work (python -m experiments.bench.paper_table)\n\n"
          + (table1.read_text() if table1.is_file() else "(no paper table)") + "\n")
    print("## Frame (python -m experiments frame --quick)\n\n" + frame_table(out) + "\n")
    print("## Bench (python -m experiments bench --quick)\n\n" + bench_table(out))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
